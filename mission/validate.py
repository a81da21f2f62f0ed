"""The check every plan passes before it is rendered, whoever made it.

Rules (``conf/drone``): at least one view; every value finite; every camera at least
``min_height_m`` above the ground (z = 0), at least ``min_clearance_m`` from the proxy surface and
not inside a closed volume of the proxy; every pitch within the gimbal range. The first violation
stops the cell with one line naming the planner, the view and the rule; nothing is rendered.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from drone.model import DroneSettings
from scene.enclosure import enclosed_positions, raycasting_scene
from scene.plan import Plan, PlanningError


class PlanRejected(PlanningError):
    """A plan broke a rule no drone may break (the message names planner, view and rule)."""


def validate_plan(plan: Plan, proxy: trimesh.Trimesh, drone: DroneSettings) -> None:
    """Raise PlanRejected at the first view of ``plan`` that breaks a rule (see the module doc)."""
    if not isinstance(plan, Plan):
        raise PlanRejected(f"a planner must return scene.plan.Plan, got {type(plan).__name__}")
    name = plan.planner
    vps = np.asarray(plan.viewpoints, dtype=float)
    if vps.ndim != 2 or vps.shape[1] != 5 or len(vps) == 0:
        raise PlanRejected(f"planner {name!r}: needs (V >= 1, 5) viewpoints, got shape {vps.shape}")

    def reject(bad: np.ndarray, rule: str) -> None:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise PlanRejected(f"planner {name!r}: view {i} {vps[i].round(3).tolist()}: {rule}")

    reject(~np.isfinite(vps).all(axis=1), "a position or angle is not finite")
    reject(
        vps[:, 2] < drone.min_height_m,
        f"below the minimum height (drone.min_height_m = {drone.min_height_m} m)",
    )
    reject(
        (vps[:, 4] < drone.gimbal_pitch_min_deg - 1e-6) | (vps[:, 4] > drone.gimbal_pitch_max_deg + 1e-6),
        f"pitch outside the gimbal range [{drone.gimbal_pitch_min_deg}, {drone.gimbal_pitch_max_deg}] deg",
    )
    scene = raycasting_scene(proxy)
    clearance = scene.compute_distance(o3d.core.Tensor(vps[:, :3].astype(np.float32))).numpy()
    reject(
        clearance < drone.min_clearance_m,
        f"closer to the proxy than drone.min_clearance_m = {drone.min_clearance_m} m",
    )
    reject(enclosed_positions(scene, vps[:, :3]), "inside a closed volume of the proxy")
