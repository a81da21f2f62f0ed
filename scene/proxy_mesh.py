"""The proxy: the mesh every planner plans on, and what may travel with it.

A proxy is a ``trimesh.Trimesh`` in world metres, Z up, ground at z = 0 (the frame of
``scene.camera``), built by ``pipeline.proxy`` from the exploratory flight (or, for planner work, the
degraded ground truth). Its ``metadata`` may carry the exploratory flight's own evidence under the
keys below; a planner that reads one must work without it (a degraded ground truth has neither).
"""

# The exploratory flight's oriented cloud, {"points": (N, 3), "normals": (N, 3)} in world metres
# (Yan's confidence term and ours_plus' evidence read the coarse model's points).
PROXY_CLOUD_KEY = "exploration_cloud"
# The exploratory flight's registered views, {"recon_dir": <recon folder holding sparse/>,
# "image_dir": <its images>}: its poses and images, for ours_plus' photo-consistency evidence
# (planner/ours/photo_evidence.py).
PROXY_VIEWS_KEY = "exploration_views"
