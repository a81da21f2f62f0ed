"""Clustered CMA-ES refinement of viewpoint poses (paper Sec. III-E).

The viewpoints are split into spatial clusters of about ``cluster_size`` (recursive median splits
along the longest axis). Each cluster is optimised on its own with CMA-ES (``cma`` package) over
(x, y, z, pitch, yaw) per viewpoint, every variable scaled to [0, 1] inside its box:
  * position: the start position +- ``position_box_m`` (z never below the minimum altitude),
  * pitch: the start pitch +- ``pitch_box_deg`` within the gimbal range, yaw: +- ``yaw_box_deg``.
The minimum clearance from the proxy is not a box: a population member breaking it scores worse
than any feasible one (by its violation). The objective is R of the whole set with the cluster's
rows replaced (``ObjectiveState.evaluate``: one visibility batch and one incremental scoring per
generation). A cluster's best pose set is committed only if it beats the current R, so a pass
never lowers R.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cma
import numpy as np
from tqdm import tqdm

from planner.objective import ObjectiveState
from planner.ours.candidates import FlightLimits
from planner.visibility import VisibilityModel


@dataclass
class CmaSettings:
    """CMA-ES settings of one pass (see the module docstring).

    Attributes:
        cluster_size: viewpoints per cluster (paper: 12).
        max_generations: CMA-ES generations per cluster and pass.
        popsize: population size; None: cma's default 4 + 3 ln(5 m).
        sigma0: initial step size in box units (the box spans 1).
        position_box_m: half-size of the position box in metres.
        pitch_box_deg, yaw_box_deg: half-sizes of the angle boxes in degrees.
    """

    cluster_size: int = 12
    max_generations: int = 6
    popsize: int | None = None
    sigma0: float = 0.25
    position_box_m: float = 3.0
    pitch_box_deg: float = 20.0
    yaw_box_deg: float = 30.0


def spatial_clusters(positions: np.ndarray, cluster_size: int) -> list[np.ndarray]:
    """Split point indices into spatially compact clusters of at most ``cluster_size`` (near equal)."""
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    out: list[np.ndarray] = []

    def split(idx: np.ndarray, n_clusters: int) -> None:
        if n_clusters <= 1 or len(idx) <= cluster_size:
            out.append(np.sort(idx))
            return
        axis = int(np.argmax(np.ptp(pos[idx], axis=0)))
        order = idx[np.argsort(pos[idx, axis], kind="stable")]
        left = n_clusters // 2
        cut = int(round(len(idx) * left / n_clusters))
        split(order[:cut], left)
        split(order[cut:], n_clusters - left)

    if len(pos):
        split(np.arange(len(pos)), int(np.ceil(len(pos) / cluster_size)))
    return out


def _boxes(vps: np.ndarray, limits: FlightLimits, s: CmaSettings) -> tuple[np.ndarray, np.ndarray]:
    lo = np.column_stack(
        [
            vps[:, 0] - s.position_box_m,
            vps[:, 1] - s.position_box_m,
            np.maximum(vps[:, 2] - s.position_box_m, limits.min_altitude_m),
            np.maximum(vps[:, 4] - s.pitch_box_deg, limits.pitch_min_deg),
            vps[:, 3] - s.yaw_box_deg,
        ]
    )
    hi = np.column_stack(
        [
            vps[:, 0] + s.position_box_m,
            vps[:, 1] + s.position_box_m,
            np.maximum(vps[:, 2] + s.position_box_m, limits.min_altitude_m),
            np.minimum(vps[:, 4] + s.pitch_box_deg, limits.pitch_max_deg),
            vps[:, 3] + s.yaw_box_deg,
        ]
    )
    return lo, hi


def _to_viewpoints(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Box coordinates (..., m * 5) -> viewpoints (..., m, 5) in x, y, z, yaw, pitch order."""
    v = lo + np.clip(x.reshape(*x.shape[:-1], -1, 5), 0.0, 1.0) * (hi - lo)  # x, y, z, pitch, yaw
    return v[..., [0, 1, 2, 4, 3]]


def _cluster_seed(seed: int, pass_index: int, cluster_index: int) -> int:
    return (
        int(np.random.SeedSequence([int(seed), int(pass_index), int(cluster_index)]).generate_state(1)[0])
        % (2**31 - 2)
        + 1
    )


def refine_clusters(
    state: ObjectiveState,
    viewpoints: np.ndarray,
    rows: np.ndarray,
    model: VisibilityModel,
    limits: FlightLimits,
    settings: CmaSettings,
    seed: int,
    pass_index: int = 0,
    point_rows: bool = True,
    desc: str = "CMA-ES",
    time_term=None,
) -> dict:
    """One clustered CMA-ES pass over the viewpoints at ``rows``; updates ``viewpoints`` and ``state``.

    Args:
        state: the objective state of ``viewpoints`` (same row order).
        viewpoints: (V, 5) current viewpoints; the refined rows are written in place.
        rows: the row indices that may move.
        model: visibility model of the state.
        limits: flight limits.
        settings: CMA-ES settings.
        seed, pass_index: make the per-cluster CMA-ES seeds.
        point_rows: whether the moved rows count for the point scores (see ``ObjectiveState``).
        time_term: a ``planner.ours.flight_time_term.FlightTimeTerm`` (``ours_plus``): maximise R minus
            the flight-time cost, the visiting order fixed for the pass; None: R alone (the paper).

    Returns:
        statistics: evaluations, generations, clusters, improved clusters, R before and after, time.
    """
    t0 = time.perf_counter()
    rows = np.asarray(rows, dtype=np.intp)
    r_start = state.R
    evaluations = generations = improved = 0
    clusters = [rows[c] for c in spatial_clusters(viewpoints[rows, :3], settings.cluster_size)]
    if time_term is not None:
        order = time_term.order(viewpoints)
        slot = np.empty_like(order)
        slot[order] = np.arange(len(order))
    for ci, cluster in enumerate(tqdm(clusters, desc=desc, leave=False, disable=None)):
        m = len(cluster)
        lo, hi = _boxes(viewpoints[cluster], limits, settings)
        start = viewpoints[cluster][:, [0, 1, 2, 4, 3]]
        span = np.where(hi > lo, hi - lo, 1.0)
        x0 = np.clip((start - lo) / span, 0.0, 1.0).ravel()
        opts = {
            "bounds": [0.0, 1.0],
            "maxiter": int(settings.max_generations),
            "verbose": -9,
            "seed": _cluster_seed(seed, pass_index, ci),
        }
        if settings.popsize:
            opts["popsize"] = int(settings.popsize)
        es = cma.CMAEvolutionStrategy(x0, float(settings.sigma0), opts)
        # The ordered set before this cluster moves: its cost, and the base its alternatives edit.
        ordered = None if time_term is None else viewpoints[order]
        current_cost = 0.0 if time_term is None else float(time_term.cost(ordered))
        best_r, best_vps, best_obs = state.R - current_cost, None, None
        npr = np.full(m, bool(point_rows))
        while not es.stop():
            xs = np.asarray(es.ask())
            cand = _to_viewpoints(xs, lo, hi)  # (L, m, 5)
            lam = len(cand)
            flat = cand.reshape(-1, 5)
            violation = limits.violations(flat, model).reshape(lam, m).sum(axis=1)
            feasible = np.flatnonzero(violation <= 1e-9)
            fitness = 1.0 + violation  # any infeasible member is worse than every feasible one (-R <= 0)
            if len(feasible):
                obs = model.observe(cand[feasible].reshape(-1, 5))
                prop = state.evaluate(cluster, obs, len(feasible), new_point_rows=npr)
                value = prop.R
                if time_term is not None:
                    sets = np.repeat(ordered[None], len(feasible), axis=0)
                    sets[:, slot[cluster]] = cand[feasible]
                    value = value - time_term.cost(sets)
                fitness[feasible] = -value
                evaluations += len(feasible)
                j = int(np.argmax(value))
                if value[j] > best_r:
                    best_r = float(value[j])
                    best_vps = cand[feasible[j]].copy()
                    best_obs = obs.take(np.arange(j * m, (j + 1) * m))
            es.tell(list(xs), fitness.tolist())
            generations += 1
        if best_vps is not None and best_r > state.R - current_cost + 1e-9:
            state.commit(cluster, best_obs, new_point_rows=npr)
            best_vps[:, 3] = (best_vps[:, 3] + 180.0) % 360.0 - 180.0
            viewpoints[cluster] = best_vps
            improved += 1
    return {
        "evaluations": evaluations,
        "generations": generations,
        "clusters": len(clusters),
        "improved_clusters": improved,
        "R_before": r_start,
        "R_after": state.R,
        "time_s": time.perf_counter() - t0,
    }
