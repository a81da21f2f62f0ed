"""Every plan within the drone's heights by construction: the shared step between a planner and the
plan check (``pipeline.cell.plan_stage``), whoever planned.

A view above ``drone.ceiling_m`` less ``CEILING_MARGIN_M`` (heights above the take-off point,
z = 0 of the local frame) is moved straight down to that height, one below ``drone.min_height_m``
straight up to the floor, each keeping its look direction; a moved view that then comes closer
to the proxy than ``drone.min_clearance_m`` or sits inside a closed volume of it is dropped. A
plan whose views all lie within the heights comes back as it is (the same object): the simulated
study's plans, whose views stay far below 120 m, are not touched. What was moved and dropped is
returned for the record (``plan.json``'s ``envelope``), with the forecast of the plan before the
step beside it.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

from drone.model import DroneSettings
from scene.enclosure import enclosed_positions, raycasting_scene
from scene.plan import Plan, PlanningError

# A moved view stays this far (m) below the ceiling: a mission's heights are ellipsoidal
# (mission.model), and the Earth's curvature lifts a waypoint d m from take-off by d^2 / 2R above the
# local plane: 8 cm at 1 km, 0.5 m at 2.5 km; a view at the ceiling itself would read 120.001 m.
CEILING_MARGIN_M = 0.5


def keep_within_heights(
    plan: Plan, proxy: trimesh.Trimesh, drone: DroneSettings, takeoff_z: float = 0.0
) -> tuple[Plan, dict | None]:
    """``plan`` with every view within [``min_height_m``, ``ceiling_m``] above ``takeoff_z``.

    Returns:
        (the plan, None) when nothing moved; else (a new plan, a record: ``n_moved_down``,
        ``n_moved_up``, ``n_dropped``, ``max_move_m``, ``ceiling_m``, ``floor_m``, ``n_before``).

    Raises:
        PlanningError: no view is left (every one broke a height and could not be moved).
    """
    vps = np.asarray(plan.viewpoints, dtype=float)
    height = vps[:, 2] - float(takeoff_z)
    top = drone.ceiling_m - min(CEILING_MARGIN_M, 0.5 * (drone.ceiling_m - drone.min_height_m))
    with np.errstate(invalid="ignore"):
        high = height > top
        low = height < drone.min_height_m
    if not (high | low).any():
        return plan, None
    moved = vps.copy()
    moved[high, 2] = float(takeoff_z) + top
    moved[low, 2] = float(takeoff_z) + drone.min_height_m
    changed = np.flatnonzero(high | low)
    scene = raycasting_scene(proxy)
    points = moved[changed, :3].astype(np.float32)
    clearance = scene.compute_distance(o3d.core.Tensor(points)).numpy()
    blocked = (clearance < drone.min_clearance_m) | enclosed_positions(scene, moved[changed, :3])
    keep = np.ones(len(vps), bool)
    keep[changed[blocked]] = False
    if not keep.any():
        raise PlanningError(
            f"planner {plan.planner!r}: no view is left within drone.min_height_m = {drone.min_height_m} m "
            f"and drone.ceiling_m = {drone.ceiling_m} m above take-off"
        )
    shift = np.abs(moved[:, 2] - vps[:, 2])
    record = {
        "ceiling_m": drone.ceiling_m,
        "moved_to_m": top,
        "floor_m": drone.min_height_m,
        "n_before": len(vps),
        "n_moved_down": int((high & keep).sum()),
        "n_moved_up": int((low & keep).sum()),
        "n_dropped": int((~keep).sum()),
        "max_move_m": round(float(shift[keep].max()), 3),
        "highest_before_m": round(float(np.nanmax(height)), 3),
    }
    info = dict(plan.info)
    info["envelope"] = record
    kinds = [k for k, kept in zip(plan.kinds, keep, strict=True) if kept]
    return Plan(moved[keep], kinds, plan.planner, info), record
