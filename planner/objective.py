"""Incremental evaluation of the global objective R (Eq. 10) over a changing viewpoint set.

``ObjectiveState`` holds the (V, P) observations of the current viewpoints, the per-point
aggregates (observer count, sum of unit viewing directions, best frontality, best distance score,
point score) and the (V, V) common-visible-point counts. A proposed change (remove some rows, add
m new rows; many alternative proposals at once, as a CMA-ES population) is scored by touching only

* the points seen by a removed or added row (their R_point is re-reduced over the visible pairs
  of the kept rows plus the new rows; every other point keeps its cached score), and
* the overlap rows and columns of the new viewpoints (the top-k lists and connected components
  of the kept viewpoints among themselves are computed once per proposal batch).

The numbers equal ``planner.heuristics.global_score`` (float32 geometry, float64 sums).

Two point-score modes: ``detail`` (``point_scores``: Eq. 1-5 as printed, or the per-view form, by
``HeuristicParams.point_score``) and ``coverage`` (``coverage_point_scores``). Rows may
be flagged not to count for the point scores (the detail viewpoints during the coverage pass):
they still count for the viewpoint-set terms.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planner.heuristics import (
    HeuristicParams,
    distance_score,
    pair_matchability,
    smith_w1,
    smith_w3,
    view_geometry,
    view_quality,
)
from planner.objective_proposals import ProposalScoring, _dot3, _topk_sum, _topk_values
from planner.visibility import Observations


class ObjectiveState(ProposalScoring):
    """R of a viewpoint set, updatable by rows.

    Args:
        params: heuristic constants (the distance range is the one of the pass).
        n_points: P.
        mode: ``detail`` or ``coverage`` point scores.
        points: (P, 3) the samples in metres; needed when ``params.matchable_overlap``.
        point_weights: (P,) positive weight of each sample's score in R (``ours_plus``: how unsure
            the proxy is there); None: every sample counts once, as in the paper.
    """

    def __init__(
        self,
        params: HeuristicParams,
        n_points: int,
        mode: str = "detail",
        points: np.ndarray | None = None,
        point_weights: np.ndarray | None = None,
    ) -> None:
        if mode not in ("detail", "coverage"):
            raise ValueError(f"mode must be 'detail' or 'coverage', got {mode!r}")
        if params.matchable_overlap and (points is None or len(points) != int(n_points)):
            raise ValueError("matchable_overlap needs the (P, 3) sample points")
        self.points = None if points is None else np.asarray(points, dtype=np.float64)
        if point_weights is not None:
            point_weights = np.asarray(point_weights, dtype=np.float64).reshape(-1)
            if (
                len(point_weights) != int(n_points)
                or not (np.isfinite(point_weights) & (point_weights > 0)).all()
            ):
                raise ValueError("point_weights must be (P,) finite and positive")
        self.point_weights = point_weights
        self.params = params
        self.mode = mode
        self.per_view = mode == "detail" and params.point_score == "per_view"
        self.n_points = int(n_points)
        self._n = 0
        self._allocate(16)
        self.point_score = np.zeros(self.n_points)
        self.count = np.zeros(self.n_points, np.int64)
        self.evaluations = 0
        self._removal_cache = None
        self._parts = self._full_parts()

    # Row storage with spare capacity: appending a viewpoint does not copy the (V, P) arrays.
    def _allocate(self, capacity: int) -> None:
        n, n_pt = self._n, self.n_points
        old = getattr(self, "_vis", None)
        vis = np.zeros((capacity, n_pt), bool)
        dist = np.zeros((capacity, n_pt), np.float32)
        direc = np.zeros((capacity, n_pt, 3), np.float32)
        cos = np.zeros((capacity, n_pt), np.float32)
        front = np.zeros((capacity, n_pt), np.float32)
        dsc = np.zeros((capacity, n_pt), np.float32)
        quality = np.zeros((capacity, n_pt), np.float32)
        centre = np.zeros((capacity, 3))
        look = np.zeros((capacity, 3))
        prow = np.zeros(capacity, bool)
        common = np.zeros((capacity, capacity), np.int64)
        if old is not None and n:
            arrays = (vis, dist, direc, cos, front, dsc, quality, centre, look, prow)
            for new, cur in zip(arrays, self._row_arrays(), strict=True):
                new[:n] = cur[:n]
            common[:n, :n] = self._common[:n, :n]
        self._vis, self._dist, self._dir, self._cos = vis, dist, direc, cos
        self._front, self._dsc, self._q, self._prow, self._common = front, dsc, quality, prow, common
        self._centre, self._look = centre, look

    def _row_arrays(self) -> tuple:
        return (
            self._vis,
            self._dist,
            self._dir,
            self._cos,
            self._front,
            self._dsc,
            self._q,
            self._centre,
            self._look,
            self._prow,
        )

    def _write_rows(self, slots: np.ndarray, obs: Observations, point_rows: np.ndarray) -> None:
        self._vis[slots] = obs.visible
        self._dist[slots] = obs.distance
        self._dir[slots] = obs.direction
        self._cos[slots] = obs.cos_incidence
        self._front[slots], self._dsc[slots] = self._row_scores(obs)
        if self.params.matchable_overlap:
            self._centre[slots], self._look[slots] = self._geometry(obs)
        if self.per_view:
            self._q[slots] = view_quality(obs.visible, obs.distance, obs.cos_incidence, self.params)
        self._prow[slots] = point_rows

    @property
    def obs(self) -> Observations:
        n = self._n
        return Observations(self._vis[:n], self._dist[:n], self._dir[:n], self._cos[:n])

    @property
    def point_rows(self) -> np.ndarray:
        return self._prow[: self._n]

    @property
    def front(self) -> np.ndarray:
        return self._front[: self._n]

    @property
    def dscore(self) -> np.ndarray:
        return self._dsc[: self._n]

    @property
    def common(self) -> np.ndarray:
        return self._common[: self._n, : self._n]

    @property
    def n_visible(self) -> np.ndarray:
        return self._vis[: self._n].sum(axis=1)

    # ----------------------------------------------------------------------------------- basics
    @property
    def n_viewpoints(self) -> int:
        return self._n

    @property
    def visible(self) -> np.ndarray:
        return self.obs.visible

    @property
    def R(self) -> float:
        return self._parts["R"]

    def parts(self) -> dict[str, float]:
        """Current R and its parts (``R_point_sum``, ``visibility``, ``overlap``, ``connectivity``,
        ``R_viewpoint``)."""
        return dict(self._parts)

    def _geometry(self, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
        return view_geometry(obs.visible, obs.distance, obs.direction, self.points)

    def _match(self, rows_a, rows_b) -> np.ndarray | float:
        """g between the stored rows ``rows_a`` x ``rows_b`` (1.0 without the matchable overlap)."""
        if not self.params.matchable_overlap:
            return 1.0
        ca, la = self._centre[rows_a], self._look[rows_a]
        cb, lb = self._centre[rows_b], self._look[rows_b]
        return pair_matchability(ca[:, None], la[:, None], cb[None], lb[None], self.params)

    def _row_scores(self, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
        p = self.params
        front = np.where(obs.visible, np.maximum(obs.cos_incidence, 0.0), 0.0).astype(np.float32)
        dsc = distance_score(obs.distance, p.target_lo_m, p.target_hi_m, p.d_margin_m)
        return front, np.where(obs.visible, dsc, 0.0).astype(np.float32)

    def reset(self, obs: Observations, point_rows: np.ndarray | None = None) -> dict[str, float]:
        """Replace the whole set by ``obs`` (all rows count for points unless ``point_rows`` says)."""
        n = len(obs)
        self._n = 0
        self._allocate(max(16, 2 * n))
        self._n = n
        prow = np.ones(n, bool) if point_rows is None else np.asarray(point_rows, bool).reshape(n)
        self._write_rows(np.arange(n), obs, prow)
        a = obs.visible.astype(np.float32)
        self._common[:n, :n] = np.rint(a @ a.T).astype(np.int64)
        self._recompute_points(np.arange(self.n_points))
        self._parts = self._full_parts()
        return self.parts()

    # --------------------------------------------------------------------------- point scores
    def _point_terms(self, cols: np.ndarray, rows_mask: np.ndarray):
        """Background aggregates over the rows in ``rows_mask`` (point rows only) for columns ``cols``."""
        sel = np.flatnonzero(rows_mask & self.point_rows)
        vis = self.obs.visible[np.ix_(sel, cols)]
        count = vis.sum(axis=0)
        dmax = self.dscore[np.ix_(sel, cols)].max(axis=0) if len(sel) else np.zeros(len(cols), np.float32)
        if self.mode == "coverage":
            return count, dmax, None, None, None, None
        fmax = self.front[np.ix_(sel, cols)].max(axis=0) if len(sel) else np.zeros(len(cols), np.float32)
        ri, ci = np.nonzero(vis)
        u = self.obs.direction[sel[ri], cols[ci]].astype(np.float64)
        usum = np.stack([np.bincount(ci, u[:, k], minlength=len(cols)) for k in range(3)], axis=1)
        return count, dmax, fmax, usum, ci, u

    def _per_view_terms(self, cols: np.ndarray, rows_mask: np.ndarray):
        """Per-view aggregates over the rows in ``rows_mask`` (point rows only) for columns ``cols``:
        good-view count (T,), the k_count best qualities (T, k_count, zero-padded), the sum of the
        good views' unit directions (T, 3), and the good pairs' column index and direction."""
        sel = np.flatnonzero(rows_mask & self.point_rows)
        k = int(self.params.k_count)
        q = self._q[np.ix_(sel, cols)]
        good = q > 0
        top = _topk_values(q.T, k)
        top = np.pad(top, ((0, 0), (0, k - top.shape[1])))
        ri, ci = np.nonzero(good)
        u = self.obs.direction[sel[ri], cols[ci]].astype(np.float64)
        usum = np.stack([np.bincount(ci, u[:, j], minlength=len(cols)) for j in range(3)], axis=1)
        return good.sum(axis=0), top, usum, ci, u

    def _per_view_combine(self, count, top_sum, sq_sum):
        p = self.params
        sigma = np.sqrt(sq_sum / (count + p.eps))
        return (top_sum / float(p.k_count)) * smith_w1(sigma) * smith_w3(sigma)

    def _combine(self, count, dmax, fmax, sq_sum):
        p = self.params
        cnt = np.minimum(1.0, count / float(p.k_count))
        if self.mode == "coverage":
            w = float(p.coverage_closeness_weight)
            return cnt * ((1.0 - w) + w * dmax)
        sigma = np.sqrt(sq_sum / (count + p.eps))
        return fmax * dmax * smith_w1(sigma) * smith_w3(sigma) * cnt

    def _recompute_points(self, cols: np.ndarray) -> None:
        cols = np.asarray(cols, dtype=np.intp)
        if len(cols) == 0:
            return
        if self.per_view:
            count, top, usum, ci, u = self._per_view_terms(cols, np.ones(self.n_viewpoints, bool))
            self.count[cols] = count
            u_bar = usum / np.maximum(np.linalg.norm(usum, axis=1, keepdims=True), 1e-300)
            sq = np.bincount(ci, np.arccos(np.clip(_dot3(u, u_bar[ci]), -1.0, 1.0)) ** 2, minlength=len(cols))
            self.point_score[cols] = self._per_view_combine(count, top.sum(axis=1, dtype=np.float64), sq)
            return
        count, dmax, fmax, usum, ci, u = self._point_terms(cols, np.ones(self.n_viewpoints, bool))
        self.count[cols] = count
        if self.mode == "coverage":
            self.point_score[cols] = self._combine(count, dmax, None, None)
            return
        u_bar = usum / np.maximum(np.linalg.norm(usum, axis=1, keepdims=True), 1e-300)
        ang = np.arccos(np.clip(_dot3(u, u_bar[ci]), -1.0, 1.0))
        sq = np.bincount(ci, ang**2, minlength=len(cols))
        self.point_score[cols] = self._combine(count, dmax.astype(float), fmax.astype(float), sq)

    # ---------------------------------------------------------------------------- full score
    def _weighted_sum(self, scores: np.ndarray, cols: np.ndarray | None = None):
        """Sum over the last axis of point scores (of the columns ``cols``, default all), each times
        its sample's weight; a float for 1-D ``scores``, else one sum per leading index."""
        if self.point_weights is not None:
            scores = scores * (self.point_weights if cols is None else self.point_weights[cols])
        total = scores.sum(axis=-1)
        return float(total) if np.ndim(total) == 0 else total

    def _full_parts(self) -> dict[str, float]:
        self._removal_cache = None  # called after every change of the set
        n_vp = self.n_viewpoints
        rp = self._weighted_sum(self.point_score)
        if n_vp == 0:
            return {
                "R": rp,
                "R_point_sum": rp,
                "visibility": 0.0,
                "overlap": 0.0,
                "connectivity": 0.0,
                "R_viewpoint": 0.0,
            }
        rows = np.arange(n_vp)
        f = self._pair_scores(self.common, self.n_visible, self.n_visible) * self._match(rows, rows)
        np.fill_diagonal(f, 0.0)
        s_ovl = float(_topk_sum(f, self.params.top_k).sum() / (self.params.top_k * n_vp))
        edges = f > self.params.tau_edge
        _, labels = connected_components(coo_matrix(edges).tocsr(), directed=False)
        s_conn = float(np.bincount(labels).max() / n_vp)
        s_vis = float(self.n_visible.sum() / (n_vp * self.n_points))
        r_vp = (s_vis + s_ovl + s_conn) / 3.0
        return {
            "R": rp + self.n_points * r_vp,
            "R_point_sum": rp,
            "visibility": s_vis,
            "overlap": s_ovl,
            "connectivity": s_conn,
            "R_viewpoint": r_vp,
        }

    def _pair_scores(self, common, n_a, n_b) -> np.ndarray:
        smaller = np.minimum(np.asarray(n_a)[..., :, None], np.asarray(n_b)[..., None, :])
        r = np.where(smaller > 0, common / np.maximum(smaller, 1), 0.0)
        p = self.params
        return np.clip((r - p.r_min) / (p.r_max - p.r_min), 0.0, 1.0)

    # --------------------------------------------------------------------------------- commit
    def commit(
        self, remove, new: Observations | None = None, new_point_rows: np.ndarray | None = None
    ) -> dict[str, float]:
        """Apply one change: drop ``remove``, add ``new``. When as many rows are added as removed,
        the new rows take the removed rows' places (order kept); otherwise removed rows are deleted
        and new rows appended. Returns the new parts."""
        remove = np.unique(np.asarray(remove, dtype=np.intp).reshape(-1))
        new = Observations.empty(self.n_points) if new is None else new
        m = len(new)
        npr = np.ones(m, bool) if new_point_rows is None else np.asarray(new_point_rows, bool).reshape(m)
        touched = np.zeros(self.n_points, bool)
        if len(remove):
            touched |= self.obs.visible[remove].any(axis=0)
        if m:
            touched |= new.visible.any(axis=0)
        if m == len(remove) and m:
            slots = remove
        else:
            if len(remove):
                keep = np.ones(self._n, bool)
                keep[remove] = False
                kept = np.flatnonzero(keep)
                k = len(kept)
                for arr in self._row_arrays():
                    arr[:k] = arr[kept]
                self._common[:k, :k] = self._common[np.ix_(kept, kept)]
                self._n = k
            if self._n + m > len(self._vis):
                self._allocate(max(2 * len(self._vis), self._n + m))
            slots = np.arange(self._n, self._n + m)
            self._n += m
        if m:
            self._write_rows(slots, new, npr)
            a = self._vis[: self._n].astype(np.float32)
            rows = np.rint(a[slots] @ a.T).astype(np.int64)
            self._common[slots, : self._n] = rows
            self._common[: self._n, slots] = rows.T
        self._recompute_points(np.flatnonzero(touched))
        self._parts = self._full_parts()
        return self.parts()
