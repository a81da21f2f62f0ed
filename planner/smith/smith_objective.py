"""Smith et al.'s objective: the observation rays of the current views and the reconstructability h
of every proxy sample, with the best change of mean(max(h_target - h, 0)^2) a view could make from a
trial position (``planner.smith.smith`` runs the optimisation around it)."""

from __future__ import annotations

import numpy as np

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
from planner.visibility import VisibilityModel


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
