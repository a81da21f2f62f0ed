"""The paper's planner (``ours``) and its variant ``ours_plus``: candidates, CMA-ES refinement,
culling, the crew's budget, stereo partners, evidence, and their settings. ``ours.plan`` is the
entry point (``conf/planner/ours.yaml``), ``ours_plus.plan`` the variant's."""
