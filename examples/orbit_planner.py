"""An example planner for ``python run.py planner=orbit``: rings of views around the structure.

The whole contract (README, "Add your planner"): ``plan(proxy, intrinsics, params, seed) -> Plan``.
The proxy is a trimesh.Trimesh in world metres (Z up, ground at z = 0); intrinsics is the camera
(``scene.camera.Intrinsics``); params is this planner's config node (examples/conf/planner/orbit.yaml,
with ``name`` and ``_target_``); seed makes a randomised planner repeatable.
"""

import math

import numpy as np

from planner.lawnmower.lawnmower import structure_bounds_from_proxy
from scene.camera import yaw_pitch_from_direction
from scene.plan import Plan, PlanningError


def plan(proxy, intrinsics, params, seed):
    distance = float(params["target_gsd_m"]) * intrinsics.focal_px  # metres: the GSD's distance
    box = structure_bounds_from_proxy(proxy)  # the building, without the reconstructed ground apron
    lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi[:2] - lo[:2])) + distance  # the ring clears the footprint
    footprint = 2.0 * distance * math.tan(math.radians(intrinsics.hfov_deg) / 2.0)
    n_views = max(8, math.ceil(2.0 * math.pi * radius / ((1.0 - float(params["overlap"])) * footprint)))
    rings = [float(f) * hi[2] for f in params["ring_height_fractions"]]
    if not rings or min(rings) < float(params["min_altitude_m"]):
        raise PlanningError(f"orbit: ring heights {rings} must lie above min_altitude_m")
    views = []
    for z in rings:
        angles = np.linspace(0.0, 2.0 * math.pi, n_views, endpoint=False)
        xy = centre[:2] + radius * np.column_stack([np.cos(angles), np.sin(angles)])
        target = np.array([centre[0], centre[1], 0.5 * hi[2]])  # aim at mid-height
        positions = np.column_stack([xy, np.full(n_views, z)])
        yaw, pitch = yaw_pitch_from_direction(target - positions)
        views.append(np.column_stack([positions, yaw, np.clip(pitch, -90.0, 30.0)]))
    viewpoints = np.vstack(views)
    info = {"n_rings": len(rings), "views_per_ring": n_views, "radius_m": radius}
    return Plan(viewpoints, ["orbit"] * len(viewpoints), params["name"], info)
