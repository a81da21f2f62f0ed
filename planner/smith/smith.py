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
    objective_terms,
    pair_terms,
    reconstructability,
    top_rays,
)
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


class SmithObjective:
    """Observation rays of the current views and the reconstructability h of every sample.

    Args:
        model: visibility with Smith's limits (d < d_max, cos(theta) >= 0.087, in the image, unoccluded).
        viewpoints: (V, 5) current views.
        max_distance_m: d_max of the resolution term.
        max_rays, h_unobserved, h_target: see ``planner.smith.smith_heuristic``.
    """

    def __init__(
        self,
        model: VisibilityModel,
        viewpoints: np.ndarray,
        max_distance_m: float,
        max_rays: int = MAX_RAYS,
        h_unobserved: float = H_UNOBSERVED,
        h_target: float = H_TARGET,
    ) -> None:
        self.model = model
        self.viewpoints = np.array(viewpoints, dtype=float)
        self.d_max = float(max_distance_m)
        self.max_rays = int(max_rays)
        self.h_unobserved = float(h_unobserved)
        self.h_target = float(h_target)
        obs = model.observe(self.viewpoints)
        self.visible = obs.visible
        self.direction = obs.direction
        self.cos = obs.cos_incidence
        self.scale = (1.0 - obs.distance / self.d_max).astype(np.float32)
        self.active = np.ones(len(self.viewpoints), bool)
        self._points32 = model.points.astype(np.float32)
        self._normals32 = model.normals.astype(np.float32)
        n_points = model.n_points
        self.h = np.empty(n_points)
        self.ray_dir = np.zeros((n_points, self.max_rays, 3), np.float32)
        self.ray_scale = np.zeros((n_points, self.max_rays), np.float32)
        self.ray_cos = np.zeros((n_points, self.max_rays), np.float32)
        self.ray_valid = np.zeros((n_points, self.max_rays), bool)
        self.ray_view = np.full((n_points, self.max_rays), -1, np.intp)  # view of each slot
        self.refresh(np.arange(n_points))

    def refresh(self, samples: np.ndarray) -> None:
        """Recompute the kept rays and h of the given samples from the active views (from scratch)."""
        samples = np.asarray(samples, dtype=np.intp)
        if len(samples) == 0:
            return
        views = np.flatnonzero(self.active)
        vis = self.visible[np.ix_(views, samples)]
        cos = self.cos[np.ix_(views, samples)]
        idx, valid = top_rays(vis, cos, self.max_rays)  # (S, R) indices into ``views``
        r = idx.shape[1]
        v = views[idx]
        s = samples[:, None]
        self.ray_dir[samples] = 0.0
        self.ray_valid[samples] = False
        self.ray_view[samples] = -1
        self.ray_dir[samples, :r] = self.direction[v, s]
        self.ray_scale[samples, :r] = self.scale[v, s]
        self.ray_cos[samples, :r] = self.cos[v, s]
        self.ray_valid[samples, :r] = valid
        self.ray_view[samples, :r] = np.where(valid, v, -1)
        h = reconstructability(
            self.ray_dir[samples], self.ray_scale[samples], self.ray_cos[samples], self.ray_valid[samples]
        )
        self.h[samples] = np.where(self.ray_valid[samples].any(axis=1), h, self.h_unobserved)

    def objective(self) -> float:
        """mean over samples of max(h_target - h, 0)^2."""
        return float(objective_terms(self.h, self.h_target).mean())

    def set_active(self, views: np.ndarray, active: bool) -> None:
        """Add or remove the observations of ``views``, updating h incrementally.

        A ray that joins or leaves a sample's kept rays adds or removes its pair terms with the
        others (O(R) per sample instead of the O(R^2) of ``refresh``). A sample whose kept rays are
        full swaps its least frontal ray for a more frontal newcomer, and refills a freed slot with
        the most frontal view it sees but did not keep. The kept rays and h equal those ``refresh``
        computes from scratch (tested).
        """
        views = np.asarray(views, dtype=np.intp).ravel()
        for view in views.tolist():
            if self.active[view] == active:
                continue
            self.active[view] = active
            if active:
                self._add_rays(view)
            else:
                self._remove_rays(view)

    def move(self, views: np.ndarray, new_viewpoints: np.ndarray) -> None:
        """Replace the poses of ``views`` (their observations leave first), recompute their rays and
        activate them."""
        views = np.asarray(views, dtype=np.intp)
        self.set_active(views[self.active[views]], False)
        obs = self.model.observe(new_viewpoints)
        self.viewpoints[views] = new_viewpoints
        self.visible[views] = obs.visible
        self.direction[views] = obs.direction
        self.cos[views] = obs.cos_incidence
        self.scale[views] = 1.0 - obs.distance / self.d_max
        self.set_active(views, True)

    def _slot_pair_sums(self, samples: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Sum (S,) of the pair terms of slot ``slots[k]`` of sample ``samples[k]`` with the sample's
        other valid slots."""
        terms = pair_terms(
            self.ray_dir[samples, slots][:, None],
            self.ray_scale[samples, slots][:, None],
            self.ray_cos[samples, slots][:, None],
            self.ray_dir[samples],
            self.ray_scale[samples],
            self.ray_cos[samples],
        )
        others = self.ray_valid[samples].copy()
        others[np.arange(len(samples)), slots] = False
        return np.sum(np.where(others, terms, 0.0), axis=1)

    def _set_h(self, samples: np.ndarray, pair_sum: np.ndarray) -> None:
        self.h[samples] = np.where(self.ray_valid[samples].any(axis=1), pair_sum, self.h_unobserved)

    def _pair_sum(self, samples: np.ndarray) -> np.ndarray:
        """The current sum of pair terms of ``samples`` (h, or 0 where h is the unobserved value)."""
        return np.where(self.ray_valid[samples].any(axis=1), self.h[samples], 0.0)

    def _write_rays(self, samples: np.ndarray, slots: np.ndarray, views: np.ndarray) -> None:
        """Put the rays of ``views[k]`` into slot ``slots[k]`` of sample ``samples[k]``."""
        self.ray_dir[samples, slots] = self.direction[views, samples]
        self.ray_scale[samples, slots] = self.scale[views, samples]
        self.ray_cos[samples, slots] = self.cos[views, samples]
        self.ray_valid[samples, slots] = True
        self.ray_view[samples, slots] = views

    def _swap_rays(self, samples: np.ndarray, slots: np.ndarray, views: np.ndarray) -> None:
        """Replace the ray in slot ``slots[k]`` of sample ``samples[k]`` by view ``views[k]``'s."""
        pair_sum = self._pair_sum(samples) - self._slot_pair_sums(samples, slots)
        self._write_rays(samples, slots, views)
        self._set_h(samples, pair_sum + self._slot_pair_sums(samples, slots))

    def _remove_rays(self, view: int) -> None:
        """Take (now inactive) ``view``'s rays out of the samples that keep them."""
        rows, slots = np.nonzero(self.ray_view == view)
        if len(rows) == 0:
            return
        # The most frontal active view a sample sees but does not keep takes the freed slot.
        cos = np.where(self.active[:, None] & self.visible[:, rows], self.cos[:, rows], -np.inf)
        kept_rows, kept_slots = np.nonzero(self.ray_valid[rows])
        cos[self.ray_view[rows[kept_rows], kept_slots], kept_rows] = -np.inf
        best = np.argmax(cos, axis=0)
        replace = np.isfinite(cos[best, np.arange(len(rows))])
        if replace.any():
            self._swap_rays(rows[replace], slots[replace], best[replace])
        quick, quick_slots = rows[~replace], slots[~replace]
        if len(quick):
            pair_sum = self._pair_sum(quick) - self._slot_pair_sums(quick, quick_slots)
            self.ray_valid[quick, quick_slots] = False
            self.ray_view[quick, quick_slots] = -1
            self.ray_dir[quick, quick_slots] = 0.0
            self._set_h(quick, pair_sum)

    def _add_rays(self, view: int) -> None:
        """Put (now active) ``view``'s rays into the samples it sees."""
        samples = np.flatnonzero(self.visible[view])
        if len(samples) == 0:
            return
        valid = self.ray_valid[samples]
        full = valid.all(axis=1)
        # A full sample takes the ray in only if it is more frontal than its least frontal kept ray,
        # which it then replaces.
        kept_cos = np.where(valid, self.ray_cos[samples], np.inf)
        least = np.argmin(kept_cos, axis=1)
        enters = full & (self.cos[view, samples] > kept_cos[np.arange(len(samples)), least])
        if enters.any():
            self._swap_rays(samples[enters], least[enters], np.full(int(enters.sum()), view))
        free, slots = samples[~full], np.argmin(valid[~full], axis=1)
        if len(free) == 0:
            return
        before = self._pair_sum(free)
        self._write_rays(free, slots, np.full(len(free), view))
        self._set_h(free, before + self._slot_pair_sums(free, slots))

    def position_gains(self, positions: np.ndarray, search: DirectionSearch):
        """Value of trial camera positions: the best objective change over viewing directions.

        Only samples within d_max, facing the position (cos >= 0.087), unoccluded and holding fewer
        than ``max_rays`` rays count (as in the public code). Vectorised over (positions x samples).

        Args:
            positions: (B, 3) trial positions in metres.
            search: the direction bins and grid.

        Returns:
            value (B,) the summed change of max(h_target - h, 0)^2 (<= 0, lower is better), and
            the best yaw (B,) and pitch (B,) in degrees.
        """
        pos = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        pts = self._points32
        to_cam = pos[:, None, :] - pts[None]  # (B, P, 3)
        dist = np.linalg.norm(to_cam, axis=-1)
        unit = to_cam / np.maximum(dist, 1e-9)[..., None]
        cos = np.einsum("bpk,pk->bp", unit, self._normals32)
        n_rays = self.ray_valid.sum(axis=1)
        cand = (dist < self.d_max) & (cos >= MIN_COS_INCIDENCE) & (n_rays < self.max_rays)[None]
        bi, si = np.nonzero(cand)
        if len(bi):
            origins = self.model.points[si] + self.model.ray_offset_m * self.model.normals[si]
            free = ~self.model.occluded(origins, pos[bi])
            bi, si = bi[free], si[free]
        u = unit[bi, si]
        scale = 1.0 - dist[bi, si] / self.d_max
        c = cos[bi, si]
        added = pair_terms(
            u[:, None, :], scale[:, None], c[:, None], self.ray_dir[si], self.ray_scale[si], self.ray_cos[si]
        )
        added = np.sum(np.where(self.ray_valid[si], added, 0.0), axis=1)
        h_old = self.h[si]
        h_new = np.where(n_rays[si] >= 1, h_old + added, 0.0)
        delta = objective_terms(h_new, self.h_target) - objective_terms(h_old, self.h_target)
        bins = search.bin_of(-u)
        gains = np.bincount(
            bi * search.n_bins + bins, weights=delta, minlength=len(pos) * search.n_bins
        ).reshape(len(pos), search.n_bins)
        return search.best(gains)


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
