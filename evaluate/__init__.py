"""Scoring a reconstruction against a scene's ground truth (accuracy, completeness, cost) and the
error pictures of the paper's Figure 3.

Modules: ``metrics`` (score_points, score_file), ``geometry`` (region clipping, surface samples,
exact point-to-triangle distance), ``loading`` (point cloud / mesh files), ``cost`` (run-directory
cost metrics), ``record`` (metrics.json), ``visualise`` (coloured PLYs, PNG views), ``run`` (the
pipeline stage ``evaluate_reconstruction``), ``__main__`` (``uavplan-evaluate``).
"""
