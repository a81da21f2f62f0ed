"""Smith et al. 2018 ("Aerial path planning for urban scene reconstruction", ACM TOG 37(6)) baseline.

1. Initial flight: a regular grid at 80 % front and side overlap (measured on the structure top)
   flown at the target-GSD distance above the structure top: one nadir pass and two oblique passes
   (lines along x, then along y, the camera tilted forward, so alternating lines look both ways).
2. Optimisation (the public code's ``optimize_trajectory``): every view keeps its own Nelder-Mead
   simplex over its 3-D position (reflection 1, expansion 2, contractions 0.5, shrink 0.5; initial
   simplex a randomly rotated regular tetrahedron of size 0.05 x min_distance). The value of a trial
   position is the best total change of the objective mean(max(h_target - h, 0)^2) over the samples
   a camera there could see, the viewing direction being chosen by exhaustive search over a grid of
   directions on the lower hemisphere (``planner.smith.smith_directions``). Positions below the minimum
   altitude, within the minimum distance of the proxy or inside a closed volume of it get a positive
   penalty (``position_penalty``). Each round draws
   views with probability proportional to their remaining budget (100 steps each), keeps those
   mutually farther apart than ``parallel_separation_m``, removes their observations, takes one
   Nelder-Mead step for all of them at once (vectorised: the steps' trial positions are evaluated
   in batches) and puts their new observations back. A view whose best step gains nothing (or is
   penalised) moves min_distance towards a point 0.9 d_max above the scene centre, is lifted until
   clear and outside every closed volume, and its simplex restarted (``restart_positions``). The loop
   ends when every budget is spent or the objective improved by less than 1e-4 x h_target over the
   last ``convergence_window`` sweeps (a sweep: as many single-view steps as there are views).
3. The views are ordered by a travelling-salesman path (``planner.trajectory``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numpy as np
import trimesh
from tqdm import tqdm

from planner.base import merge_params
from planner.lawnmower.lawnmower import footprint_m, grid_positions, structure_bounds_from_proxy
from planner.sampling import sample_surface, validate_proxy
from planner.smith.smith_directions import DirectionSearch
from planner.smith.smith_heuristic import (
    H_TARGET,
    H_UNOBSERVED,
    MAX_RAYS,
    MIN_COS_INCIDENCE,
)
from planner.smith.smith_objective import SmithObjective
from planner.trajectory import order_viewpoints
from planner.visibility import VisibilityLimits, VisibilityModel
from scene.base import Box
from scene.camera import Intrinsics
from scene.plan import Plan, PlanningError

DEFAULTS = {
    "n_samples": 2048,
    "max_distance_m": 50.0,
    "min_distance_m": 5.0,
    "min_altitude_m": 5.0,
    "h_target": H_TARGET,
    "max_rays": MAX_RAYS,
    "h_unobserved": H_UNOBSERVED,
    "front_overlap": 0.8,
    "side_overlap": 0.8,
    "target_gsd_m": 0.03,
    "grid_altitude_above_top_m": None,
    "overlap_reference": "top",
    "grid_margin_m": 0.0,
    "oblique_pitch_deg": -45.0,
    "max_iters": 100,
    "simplex_size_factor": 0.05,
    "parallel_separation_m": None,
    "convergence_window": 10,
    "convergence_tol": 1e-4,
    "n_yaw": 128,
    "n_pitch": 45,
    "bin_subdivisions": 3,
    "fov_margin_deg": 2.0,
    "structure_min_height_m": 0.5,
    "takeoff_xyz": None,
    "tsp_runs": 1,
    "progress": True,
}


def _merged(params: Mapping | None) -> dict:
    merged = merge_params("smith", DEFAULTS, params)
    for key in ("front_overlap", "side_overlap"):
        if not 0.0 < float(merged[key]) < 1.0:
            raise ValueError(f"smith: {key} must lie in (0, 1), got {merged[key]}")
    if not float(merged["max_distance_m"]) > float(merged["min_distance_m"]) >= 0.0:
        raise ValueError(
            f"smith: need 0 <= min_distance_m < max_distance_m, got {merged['min_distance_m']}, "
            f"{merged['max_distance_m']}"
        )
    if merged["overlap_reference"] not in ("top", "ground"):
        raise ValueError(
            f"smith: overlap_reference must be 'top' or 'ground', got {merged['overlap_reference']!r}"
        )
    if merged["grid_altitude_above_top_m"] is None and not float(merged["target_gsd_m"]) > 0.0:
        raise ValueError(f"smith: target_gsd_m must be > 0, got {merged['target_gsd_m']}")
    if int(merged["max_iters"]) < 1 or int(merged["n_samples"]) < 1 or int(merged["max_rays"]) < 2:
        raise ValueError("smith: max_iters and n_samples must be >= 1 and max_rays >= 2")
    return merged


def check_params(params: Mapping | None, intrinsics: Intrinsics) -> None:
    """Refuse a bad setting before any work (the planner contract, ``planner.base``)."""
    del intrinsics
    _merged(params)


def initial_grid(bounds: Box, intrinsics: Intrinsics, params: Mapping) -> tuple[np.ndarray, list[str]]:
    """Smith's initial flight: one nadir and two oblique grid passes over the structure.

    The grid flies ``grid_altitude_above_top_m`` above the structure top (None: the target distance
    of ``target_gsd_m``, the GSD every planner of a study shares). The front / side overlaps hold
    on the structure top (``overlap_reference: top``, where a nadir grid's matches are) or on the
    ground (``ground``, the flat-terrain rule of survey apps, which starves tall structures).

    Args:
        bounds: box around the structure (m).
        intrinsics: the camera.
        params: merged smith parameters (overlaps, ``target_gsd_m``, ``grid_altitude_above_top_m``,
            ``overlap_reference``, ``grid_margin_m``, ``oblique_pitch_deg``).

    Returns:
        viewpoints (V, 5) and their kinds (``nadir`` / ``oblique``).
    """
    above = params["grid_altitude_above_top_m"]
    if above is None:
        above = intrinsics.distance_for_gsd(float(params["target_gsd_m"]))
    top = float(bounds.hi[2])
    altitude = top + float(above)
    reference = top if params["overlap_reference"] == "top" else float(bounds.lo[2])
    across_w, along_l = footprint_m(intrinsics, altitude - reference)
    spacing_along = (1.0 - float(params["front_overlap"])) * along_l
    spacing_across = (1.0 - float(params["side_overlap"])) * across_w
    margin = float(params["grid_margin_m"])
    lo, hi = bounds.lo_array[:2] - margin, bounds.hi_array[:2] + margin
    passes = [("x", -90.0, "nadir"), ("x", float(params["oblique_pitch_deg"]), "oblique")]
    passes.append(("y", float(params["oblique_pitch_deg"]), "oblique"))
    rows, kinds = [], []
    for direction, pitch, kind in passes:
        pos, heading, _ = grid_positions(lo, hi, altitude, spacing_along, spacing_across, direction)
        yaw = np.mod(heading + 180.0, 360.0) - 180.0
        rows.append(np.column_stack([pos, yaw, np.full(len(pos), pitch)]))
        kinds += [kind] * len(pos)
    return np.concatenate(rows), kinds


_TETRAHEDRON = np.array(
    [[1.0, 0.0, -1.0 / math.sqrt(2.0)], [-1.0, 0.0, -1.0 / math.sqrt(2.0)], [0.0, 1.0, 1.0 / math.sqrt(2.0)]]
    + [[0.0, -1.0, 1.0 / math.sqrt(2.0)]]
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def initial_simplex(position: np.ndarray, size_m: float, rng: np.random.Generator) -> np.ndarray:
    """(4, 3) randomly rotated regular tetrahedron of edge ``2 * size_m`` around ``position`` (m)."""
    return np.asarray(position, dtype=float)[None] + (_TETRAHEDRON * float(size_m)) @ _random_rotation(rng).T


class NelderMeadStepper:
    """One Nelder-Mead step (reflection 1, expansion 2, contractions 0.5, shrink 0.5) for many simplices.

    The step follows the public code's ``nelder_mead``: the simplex's vertices are re-evaluated at
    every step (the objective changes as the other views move). ``evaluate(points (N, 3))`` returns
    (value (N,), yaw (N,), pitch (N,)); lower values are better. All vertices of all simplices are
    evaluated in one call, the reflections in a second and the expansions/contractions in a third.
    """

    def __init__(self, evaluate) -> None:
        self.evaluate = evaluate

    def step(self, simplices: np.ndarray):
        """Step (K, 4, 3) simplices in place; return best position (K, 3), value, yaw, pitch (K,)."""
        k = len(simplices)
        vals, yaws, pitches = (a.reshape(k, 4) for a in self.evaluate(simplices.reshape(-1, 3)))
        order = np.argsort(vals, axis=1, kind="stable")
        rows = np.arange(k)
        best, lousy, worst = order[:, 0], order[:, -2], order[:, -1]
        v_best, v_lousy, v_worst = vals[rows, best], vals[rows, lousy], vals[rows, worst]
        x_worst = simplices[rows, worst]
        hpc = (simplices.sum(axis=1) - x_worst) / 3.0
        refl = hpc + (hpc - x_worst)
        v_refl, yaw_refl, pitch_refl = self.evaluate(refl)

        expand = v_refl < v_best
        accept_refl = ~expand & (v_refl < v_lousy)
        outside = ~expand & ~accept_refl & (v_refl < v_worst)
        inside = ~expand & ~accept_refl & ~outside
        trial = np.where(
            expand[:, None],
            refl + (refl - hpc),
            np.where(outside[:, None], hpc + 0.5 * (hpc - x_worst), hpc - 0.5 * (hpc - x_worst)),
        )
        need = expand | outside | inside
        v_trial = np.full(k, np.inf)
        yaw_trial, pitch_trial = np.zeros(k), np.zeros(k)
        if need.any():
            v_trial[need], yaw_trial[need], pitch_trial[need] = self.evaluate(trial[need])

        out_pos = simplices[rows, best].copy()
        out_val, out_yaw, out_pitch = v_best.copy(), yaws[rows, best].copy(), pitches[rows, best].copy()

        exp_ok = expand & (v_trial < v_best)
        exp_no = expand & ~exp_ok
        new_worst = np.where(exp_ok[:, None], trial, np.where(exp_no[:, None], refl, x_worst))
        new_worst = np.where(accept_refl[:, None], refl, new_worst)
        contract = outside | inside
        con_ok = contract & (v_trial < v_worst)
        new_worst = np.where(con_ok[:, None], trial, new_worst)
        simplices[rows, worst] = new_worst
        for mask, pos, val, yaw, pitch in (
            (exp_ok, trial, v_trial, yaw_trial, pitch_trial),
            (exp_no, refl, v_refl, yaw_refl, pitch_refl),
            (con_ok & (v_trial < v_best), trial, v_trial, yaw_trial, pitch_trial),
        ):
            out_pos[mask], out_val[mask], out_yaw[mask], out_pitch[mask] = (
                pos[mask],
                val[mask],
                yaw[mask],
                pitch[mask],
            )
        shrink = contract & ~con_ok
        if shrink.any():
            anchor = simplices[shrink, best[shrink]][:, None, :]
            simplices[shrink] = anchor + 0.5 * (simplices[shrink] - anchor)
        return out_pos, out_val, out_yaw, out_pitch


def _far_apart_views(positions: np.ndarray, budget: np.ndarray, separation: float, rng) -> np.ndarray:
    """Views drawn by remaining budget, kept when farther than ``separation`` from those kept."""
    draws = rng.choice(len(budget), size=len(budget), p=budget / budget.sum())
    sep2 = separation * separation
    blocked = np.zeros(len(budget), bool)
    chosen: list[int] = []
    for idx in draws.tolist():
        if not blocked[idx]:
            chosen.append(idx)
            blocked |= np.sum((positions - positions[idx]) ** 2, axis=1) < sep2
            if blocked.all():
                break
    return np.asarray(chosen, dtype=np.intp)


def restart_positions(
    positions: np.ndarray,
    scene_centre: np.ndarray,
    d_max: float,
    min_distance: float,
    min_altitude: float,
    model: VisibilityModel,
    max_lifts: int = 1000,
) -> np.ndarray:
    """Where views that contribute nothing go next (the public code's rule), (K, 3) metres.

    Each moves ``min_distance`` towards the point ``0.9 d_max`` above ``scene_centre`` (x, y), then
    up by ``min_distance`` while ``position_penalty`` is positive there (below ``min_altitude``,
    closer than ``min_distance`` to the proxy, or inside a closed volume of it).
    """
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    target = np.array([scene_centre[0], scene_centre[1], 0.9 * float(d_max)])
    step = target[None] - positions
    length = np.linalg.norm(step, axis=1, keepdims=True)
    moved = positions + np.where(length > 1e-9, step / np.maximum(length, 1e-9), 0.0) * min_distance
    for _ in range(max_lifts):
        blocked = position_penalty(moved, model, min_distance, min_altitude) > 0.0
        if not blocked.any():
            break
        moved[blocked, 2] += min_distance
    return moved


def position_penalty(
    points: np.ndarray, model: VisibilityModel, min_distance: float, min_altitude: float
) -> np.ndarray:
    """(N,) penalty of camera positions (N, 3): 0 in the flyable airspace, positive (metres) outside.

    Below ``min_altitude``: the height missing; within ``min_distance`` of the proxy: the distance
    missing; inside a closed volume of the proxy (``VisibilityModel.enclosed``) and farther than
    ``min_distance`` from its surface: the depth. The public code penalises a position behind the
    nearest surface only within min_distance of it (its closest-point search radius), so a position
    deeper inside a large volume (a nave) went unpenalised and a view could end inside the building,
    where no drone flies; here the whole interior is outside the airspace.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    penalty = np.where(points[:, 2] < min_altitude, min_altitude - points[:, 2], 0.0)
    ok = penalty == 0.0
    if ok.any():
        clearance = model.clearance(points[ok])
        near = clearance < min_distance
        deep = np.zeros(len(clearance), bool)
        if (~near).any():
            deep[~near] = model.enclosed(points[ok][~near])
        penalty[ok] = np.where(near, min_distance - clearance, np.where(deep, clearance, 0.0))
    return penalty


def optimise(
    objective: SmithObjective,
    search: DirectionSearch,
    params: Mapping,
    scene_centre: np.ndarray,
    rng: np.random.Generator,
) -> dict:
    """Smith's per-view Nelder-Mead optimisation of ``objective.viewpoints`` (in place).

    Returns:
        a record: objective per sweep, rounds, steps, restarts, penalised evaluations.
    """
    min_dist = float(params["min_distance_m"])
    min_alt = float(params["min_altitude_m"])
    model = objective.model
    n_views = len(objective.viewpoints)
    budget = np.full(n_views, float(params["max_iters"]))
    simplices = np.stack(
        [
            initial_simplex(p, float(params["simplex_size_factor"]) * min_dist, rng)
            for p in objective.viewpoints[:, :3]
        ]
    )
    separation = params["parallel_separation_m"]
    # The public code steps views together when their squared distance is >= 2 d_max^2.
    separation = math.sqrt(2.0) * objective.d_max if separation is None else float(separation)
    counters = {"evaluations": 0, "penalised": 0}

    def evaluate(points: np.ndarray):
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        value, yaw, pitch = np.zeros(len(points)), np.zeros(len(points)), np.full(len(points), -90.0)
        penalty = position_penalty(points, model, min_dist, min_alt)
        ok = penalty == 0.0
        value[~ok] = penalty[~ok]
        if ok.any():
            value[ok], yaw[ok], pitch[ok] = objective.position_gains(points[ok], search)
        counters["evaluations"] += len(points)
        counters["penalised"] += int((~ok).sum())
        return value, yaw, pitch

    stepper = NelderMeadStepper(evaluate)
    # The window counts sweeps (as many single-view steps as there are views): with views stepped
    # only when d_max apart, a round on a small scene moves one view, and a window of rounds would
    # stop after a few steps per view.
    per_sweep = [objective.objective()]
    window = int(params["convergence_window"])
    tol = float(params["convergence_tol"]) * objective.h_target
    restarts = steps = rounds = 0
    total_budget = budget.sum()
    bar = tqdm(total=int(total_budget), desc="smith nelder-mead", unit="step", disable=not params["progress"])
    while budget.sum() > 0:
        chosen = _far_apart_views(objective.viewpoints[:, :3], budget, separation, rng)
        budget[chosen] -= 1
        objective.set_active(chosen, False)
        # ``simplices[chosen]`` is a copy (fancy indexing): step it, then write it back, or every
        # step would start again from the view's first tetrahedron.
        stepped = simplices[chosen]
        pos, val, yaw, pitch = stepper.step(stepped)
        simplices[chosen] = stepped
        new_vps = objective.viewpoints[chosen].copy()
        gained = val < 0.0
        new_vps[gained, :3] = pos[gained]
        new_vps[gained, 3] = np.mod(yaw[gained] + 180.0, 360.0) - 180.0
        new_vps[gained, 4] = pitch[gained]
        # A view whose best step gains nothing or is penalised contributes nothing where it is. As in
        # the public code (optimize_trajectory.cu), it moves min_distance towards a point 0.9 d_max
        # above the scene centre, is lifted by min_distance until it is clear of the proxy and the
        # ground (and out of any closed volume), and restarts from a fresh simplex.
        useless = val >= 0.0
        if useless.any():
            moved = restart_positions(
                objective.viewpoints[chosen[useless], :3],
                scene_centre,
                objective.d_max,
                min_dist,
                min_alt,
                model,
            )
            new_vps[useless, :3] = moved
            for j, p in zip(np.flatnonzero(useless), moved, strict=True):
                simplices[chosen[j]] = initial_simplex(
                    p, float(params["simplex_size_factor"]) * min_dist, rng
                )
            restarts += int(useless.sum())
        objective.move(chosen, new_vps)
        steps += len(chosen)
        rounds += 1
        bar.update(len(chosen))
        if steps >= len(per_sweep) * n_views:
            per_sweep.append(objective.objective())
            if len(per_sweep) > window and per_sweep[-1 - window] - per_sweep[-1] < tol:
                break
    bar.close()
    return {
        "objective_per_sweep": per_sweep,
        "rounds": rounds,
        "steps": steps,
        "restarts": restarts,
        "evaluations": counters["evaluations"],
        "penalised_evaluations": counters["penalised"],
        "parallel_separation_m": separation,
    }


def plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan:
    """Plan Smith et al.'s flight on a proxy mesh.

    Args:
        proxy: proxy triangle mesh in world metres (Z up, ground at z = 0).
        intrinsics: the camera.
        params: see ``DEFAULTS`` and ``conf/planner/smith.yaml`` (metres, degrees).
        seed: seeds the surface samples, the simplices and the view draws.

    Returns:
        The plan: the optimised views in TSP order, kinds ``nadir`` / ``oblique`` of their initial pass.
    """
    p = _merged(params)
    validate_proxy(proxy)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    points, normals = sample_surface(proxy, int(p["n_samples"]), seed)
    limits = VisibilityLimits(0.0, float(p["max_distance_m"]), math.degrees(math.acos(MIN_COS_INCIDENCE)))
    model = VisibilityModel(proxy, points, normals, intrinsics, limits)
    search = DirectionSearch(
        intrinsics, int(p["n_yaw"]), int(p["n_pitch"]), int(p["bin_subdivisions"]), float(p["fov_margin_deg"])
    )
    bounds = structure_bounds_from_proxy(proxy, float(p["structure_min_height_m"]))
    viewpoints, kinds = initial_grid(bounds, intrinsics, p)
    if len(viewpoints) == 0:
        raise PlanningError("smith: the initial grid is empty")
    timings["setup"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    objective = SmithObjective(
        model,
        viewpoints,
        float(p["max_distance_m"]),
        int(p["max_rays"]),
        float(p["h_unobserved"]),
        float(p["h_target"]),
    )
    initial_objective = objective.objective()
    record = optimise(objective, search, p, bounds.center, rng)
    timings["optimise"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    final = objective.viewpoints
    start = None if p["takeoff_xyz"] is None else np.asarray(p["takeoff_xyz"], dtype=float)
    order = order_viewpoints(final[:, :3], start=start, runs=int(p["tsp_runs"]))
    timings["tsp"] = time.perf_counter() - t0
    timings["total"] = sum(timings.values())
    info = {
        "parameters": {k: v for k, v in p.items() if k != "progress"},
        "timings_s": timings,
        "n_samples": int(len(points)),
        "n_initial_views": int(len(viewpoints)),
        "objective_initial": initial_objective,
        "objective_final": objective.objective(),
        "objective_per_sweep": record.pop("objective_per_sweep"),
        "optimisation": record,
        "rays_cast": model.rays_cast,
    }
    return Plan(viewpoints=final[order], kinds=[kinds[i] for i in order], planner="smith", info=info)
