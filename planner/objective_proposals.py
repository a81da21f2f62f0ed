"""Scoring proposals against an ``ObjectiveState`` (``planner.objective``): a batch of alternative
changes (remove some rows, add m new rows) scored by touching only the points a changed row sees and
the overlap rows and columns of the new viewpoints; one row's removal; and the array helpers both
share. ``ProposalScoring`` is ``ObjectiveState``'s half that reads the state and changes nothing."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from planner.heuristics import (
    distance_score,
    pair_matchability,
    view_quality,
)
from planner.visibility import Observations


@dataclass
class Proposal:
    """Scores of a batch of alternative changes (arrays (L,) over the L alternatives)."""

    R: np.ndarray
    R_point_sum: np.ndarray
    visibility: np.ndarray
    overlap: np.ndarray
    connectivity: np.ndarray

    @property
    def R_viewpoint(self) -> np.ndarray:
        return (self.visibility + self.overlap + self.connectivity) / 3.0


class ProposalScoring:
    """The proposal half of ``ObjectiveState``: it reads the state's rows and cached point scores."""

    # ------------------------------------------------------------------------------ proposals
    def evaluate(
        self,
        remove,
        new: Observations | None = None,
        n_alternatives: int = 1,
        new_point_rows: np.ndarray | None = None,
    ) -> Proposal:
        """Score L alternative changes that each drop the rows ``remove`` and add m new rows.

        Args:
            remove: row indices dropped by every alternative (may be empty).
            new: L * m observations, alternative after alternative (None or 0 rows: m = 0).
            n_alternatives: L.
            new_point_rows: (m,) whether each new row counts for the point scores (default: yes).

        Returns:
            a ``Proposal`` with (L,) arrays; the state itself is unchanged.
        """
        lam = int(n_alternatives)
        remove = np.unique(np.asarray(remove, dtype=np.intp).reshape(-1))
        n_pt = self.n_points
        if new is None or len(new) == 0:
            new = Observations.empty(n_pt)
            m = 0
        else:
            if len(new) % lam:
                raise ValueError(f"{len(new)} new rows do not split into {lam} alternatives")
            m = len(new) // lam
        npr = np.ones(m, bool) if new_point_rows is None else np.asarray(new_point_rows, bool).reshape(m)
        self.evaluations += lam
        keep_mask = np.ones(self.n_viewpoints, bool)
        keep_mask[remove] = False
        keep = np.flatnonzero(keep_mask)
        n_keep = len(keep)
        n_total = n_keep + m
        new_vis = new.visible.reshape(lam, m, n_pt)

        # ---- point part: only points seen by a removed or an added row change
        touched = new_vis.any(axis=(0, 1))
        if len(remove):
            touched |= self.obs.visible[remove].any(axis=0)
        cols = np.flatnonzero(touched)
        r_point = np.full(lam, self._weighted_sum(self.point_score))
        if len(cols):
            r_point += self._weighted_sum(self._touched_point_scores(cols, keep_mask, new, lam, m, npr), cols)
            r_point -= self._weighted_sum(self.point_score[cols], cols)

        # ---- viewpoint-set part
        if n_total == 0:
            zero = np.zeros(lam)
            return Proposal(r_point.copy(), r_point, zero, zero, zero)
        nv_cols = new_vis[:, :, cols].astype(np.float32)  # (L, m, T)
        n_new = nv_cols.sum(axis=2).astype(np.int64)  # (L, m)
        n_keep_vis = self.n_visible[keep]
        s_vis = (n_keep_vis.sum() + n_new.sum(axis=1)) / (n_total * n_pt)

        k = int(self.params.top_k)
        f_kk = self._pair_scores(self.common[np.ix_(keep, keep)], n_keep_vis, n_keep_vis) * self._match(
            keep, keep
        )
        np.fill_diagonal(f_kk, 0.0)
        a_keep = self.obs.visible[np.ix_(keep, cols)].astype(np.float32)  # (K, T)
        # one 2-D product: numpy's stacked matmul does not reach BLAS
        c_nk = np.rint(nv_cols.reshape(lam * m, len(cols)) @ a_keep.T).reshape(lam, m, n_keep)
        c_nn = np.rint(nv_cols @ np.swapaxes(nv_cols, 1, 2))  # (L, m, m)
        f_nk = self._pair_scores(c_nk, n_new, np.broadcast_to(n_keep_vis, (lam, n_keep)))
        f_nn = self._pair_scores(c_nn, n_new, n_new)
        if self.params.matchable_overlap and m:
            centre_n, look_n = (a.reshape(lam, m, 3) for a in self._geometry(new))
            p = self.params
            f_nk = f_nk * pair_matchability(
                centre_n[:, :, None], look_n[:, :, None], self._centre[keep], self._look[keep], p
            )
            f_nn = f_nn * pair_matchability(
                centre_n[:, :, None], look_n[:, :, None], centre_n[:, None], look_n[:, None], p
            )
        f_nn[:, np.arange(m), np.arange(m)] = 0.0
        # kept rows: their own top-k among kept rows, merged with the m new columns
        top_kk = _topk_values(f_kk, k)  # (K, k)
        merged = np.concatenate(
            [np.broadcast_to(top_kk, (lam, n_keep, top_kk.shape[1])), np.swapaxes(f_nk, 1, 2)], axis=2
        )
        ovl = _topk_sum(merged, k).sum(axis=1)
        ovl += _topk_sum(np.concatenate([f_nk, f_nn], axis=2), k).sum(axis=1)
        s_ovl = ovl / (k * n_total)

        s_conn = self._largest_component(f_kk, f_nk, f_nn) / n_total
        r_vp = (s_vis + s_ovl + s_conn) / 3.0
        return Proposal(r_point + n_pt * r_vp, r_point, s_vis, s_ovl, s_conn)

    def evaluate_removal(self, row: int) -> float:
        """R after removing the single viewpoint ``row`` (= ``evaluate([row]).R[0]``, faster).

        Per set, each row's top-(k+1) pair scores and the overlap graph are cached: dropping one
        viewpoint then changes a row's top-k sum only when the dropped pair was in it (the (k+1)-th
        score takes its place), and the components come from the cached graph minus one node.
        """
        row = int(row)
        n, n_pt, k = self._n, self.n_points, int(self.params.top_k)
        if n <= 1:
            return float(self.evaluate([row]).R[0])
        cache = self._removal_cache
        if cache is None:
            nv = self.n_visible
            f = self._pair_scores(self.common, nv, nv) * self._match(np.arange(n), np.arange(n))
            np.fill_diagonal(f, 0.0)
            width = min(k + 1, n)
            part = -np.partition(-f, width - 1, axis=1)[:, :width] if width < n else f
            top = -np.sort(-part, axis=1)  # descending
            top = np.pad(top[:, :width], ((0, 0), (0, k + 1 - width)))
            cache = self._removal_cache = {
                "f": f,
                "topk_sum": top[:, :k].sum(axis=1),
                "kth": top[:, k - 1],
                "next": top[:, k],
                "edges": coo_matrix(f > self.params.tau_edge).tocsr(),
                "n_visible": nv,
            }
        self.evaluations += 1
        keep_mask = np.ones(n, bool)
        keep_mask[row] = False
        cols = np.flatnonzero(self._vis[row, :n_pt] if n else np.zeros(n_pt, bool))
        r_point = self._weighted_sum(self.point_score)
        if len(cols):
            empty = Observations.empty(n_pt)
            touched = self._touched_point_scores(cols, keep_mask, empty, 1, 0, np.zeros(0, bool))
            r_point += float(self._weighted_sum(touched, cols)[0])
            r_point -= self._weighted_sum(self.point_score[cols], cols)
        n_total = n - 1
        nv = cache["n_visible"]
        s_vis = (nv.sum() - nv[row]) / (n_total * n_pt)
        f_col = cache["f"][:, row]
        in_top = f_col >= cache["kth"]
        sums = cache["topk_sum"] - np.where(in_top, f_col - cache["next"], 0.0)
        s_ovl = float(sums[keep_mask].sum() / (k * n_total))
        keep = np.flatnonzero(keep_mask)
        sub = cache["edges"][keep][:, keep]
        _, labels = connected_components(sub, directed=False)
        s_conn = float(np.bincount(labels).max() / n_total)
        return r_point + n_pt * (s_vis + s_ovl + s_conn) / 3.0

    def _touched_point_scores(self, cols, keep_mask, new: Observations, lam, m, npr) -> np.ndarray:
        """New point scores (L, T) of the touched columns under each alternative."""
        if self.per_view:
            return self._touched_per_view(cols, keep_mask, new, lam, m, npr)
        t = len(cols)
        count, dmax, fmax, usum, ci, u = self._point_terms(cols, keep_mask)
        if m and npr.any():
            rows = np.flatnonzero(np.tile(npr, lam))  # rows of ``new`` counting for points
            ix = np.ix_(rows, cols)
            nvis = new.visible[ix].reshape(lam, -1, t)
            p = self.params
            dsc_n = np.where(
                nvis,
                distance_score(new.distance[ix], p.target_lo_m, p.target_hi_m, p.d_margin_m).reshape(
                    lam, -1, t
                ),
                0.0,
            )
            count_l = count[None] + nvis.sum(axis=1)
            dmax_l = np.maximum(dmax[None], dsc_n.max(axis=1))
        else:
            nvis = None
            count_l = np.broadcast_to(count, (lam, t))
            dmax_l = np.broadcast_to(dmax, (lam, t))
        if self.mode == "coverage":
            return self._combine(count_l, dmax_l.astype(float), None, None)
        if nvis is not None:
            front_n = np.where(nvis, np.maximum(new.cos_incidence[ix].reshape(lam, -1, t), 0.0), 0.0)
            fmax_l = np.maximum(fmax[None], front_n.max(axis=1))
            ndir = new.direction[ix].reshape(lam, -1, t, 3) * nvis[..., None]
            usum_l = usum[None] + ndir.sum(axis=1, dtype=np.float64)
        else:
            fmax_l = np.broadcast_to(fmax, (lam, t))
            usum_l = np.broadcast_to(usum, (lam, t, 3))
        u_bar = usum_l / np.maximum(np.linalg.norm(usum_l, axis=2, keepdims=True), 1e-300)
        # kept pairs against each alternative's mean direction
        dots = _dot3(u_bar[:, ci], u[None])
        ang2 = np.arccos(np.clip(dots, -1.0, 1.0)) ** 2
        flat = (np.arange(lam)[:, None] * t + ci[None]).ravel()
        sq = np.bincount(flat, ang2.ravel(), minlength=lam * t).reshape(lam, t)
        if nvis is not None:
            dn = _dot3(ndir, u_bar[:, None])
            sq += np.where(nvis, np.arccos(np.clip(dn, -1.0, 1.0)) ** 2, 0.0).sum(axis=1)
        return self._combine(count_l, dmax_l.astype(float), fmax_l.astype(float), sq)

    def _touched_per_view(self, cols, keep_mask, new: Observations, lam, m, npr) -> np.ndarray:
        """``_touched_point_scores`` for the per-view point score."""
        t, k = len(cols), int(self.params.k_count)
        count, top, usum, ci, u = self._per_view_terms(cols, keep_mask)
        top_l = np.broadcast_to(top.T, (lam, k, t))
        if m and npr.any():
            rows = np.flatnonzero(np.tile(npr, lam))  # rows of ``new`` counting for points
            ix = np.ix_(rows, cols)
            q_n = view_quality(new.visible[ix], new.distance[ix], new.cos_incidence[ix], self.params)
            q_n = q_n.reshape(lam, -1, t)
            good_n = q_n > 0
            count_l = count[None] + good_n.sum(axis=1)
            top_l = _topk_values(np.swapaxes(np.concatenate([top_l, q_n], axis=1), 1, 2), k)
            top_sum = top_l.sum(axis=2, dtype=np.float64)
            ndir = new.direction[ix].reshape(lam, -1, t, 3) * good_n[..., None]
            usum_l = usum[None] + ndir.sum(axis=1, dtype=np.float64)
        else:
            good_n = None
            count_l = np.broadcast_to(count, (lam, t))
            top_sum = top_l.sum(axis=1, dtype=np.float64)
            usum_l = np.broadcast_to(usum, (lam, t, 3))
        u_bar = usum_l / np.maximum(np.linalg.norm(usum_l, axis=2, keepdims=True), 1e-300)
        ang2 = np.arccos(np.clip(_dot3(u_bar[:, ci], u[None]), -1.0, 1.0)) ** 2
        flat = (np.arange(lam)[:, None] * t + ci[None]).ravel()
        sq = np.bincount(flat, ang2.ravel(), minlength=lam * t).reshape(lam, t)
        if good_n is not None:
            dn = _dot3(ndir, u_bar[:, None])
            sq += np.where(good_n, np.arccos(np.clip(dn, -1.0, 1.0)) ** 2, 0.0).sum(axis=1)
        return self._per_view_combine(count_l, top_sum, sq)

    def _largest_component(self, f_kk, f_nk, f_nn) -> np.ndarray:
        """Size (L,) of the largest connected component after each alternative."""
        tau = self.params.tau_edge
        lam, m, n_keep = f_nk.shape
        if n_keep:
            n_comp, labels = connected_components(coo_matrix(f_kk > tau).tocsr(), directed=False)
            comp_size = np.bincount(labels, minlength=n_comp)
        else:
            n_comp, labels, comp_size = 0, np.zeros(0, np.intp), np.zeros(0, np.int64)
        if m == 0:
            return np.full(lam, comp_size.max() if n_comp else 0, dtype=float)
        one_hot = np.zeros((n_keep, n_comp), np.float32)
        one_hot[np.arange(n_keep), labels] = 1.0
        touches = ((f_nk > tau).astype(np.float32) @ one_hot) > 0  # (L, m, n_comp)
        # All alternatives in one graph: alternative i owns nodes [i * g, (i + 1) * g), g = n_comp + m
        # (the kept components first, then its new viewpoints).
        g = n_comp + m
        li, ni, ci = np.nonzero(touches)
        lj, a, b = np.nonzero(np.triu(f_nn > tau, 1))
        rows = np.concatenate([li * g + n_comp + ni, lj * g + n_comp + a])
        cols = np.concatenate([li * g + ci, lj * g + n_comp + b])
        graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(lam * g, lam * g)).tocsr()
        n_lab, lab = connected_components(graph, directed=False)
        sizes = np.tile(np.concatenate([comp_size, np.ones(m, np.int64)]), lam)
        label_size = np.bincount(lab, weights=sizes, minlength=n_lab)
        out = np.zeros(lam)
        np.maximum.at(out, np.repeat(np.arange(lam), g), label_size[lab])
        return out


def _topk_values(f: np.ndarray, k: int) -> np.ndarray:
    """The k largest values of each row of (..., n) (all of them when n <= k), unordered."""
    n = f.shape[-1]
    if n <= k:
        return f
    return -np.partition(-f, k - 1, axis=-1)[..., :k]


def _topk_sum(f: np.ndarray, k: int) -> np.ndarray:
    """Sum of the k largest values along the last axis (missing values count as 0)."""
    return _topk_values(f, k).sum(axis=-1)


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over a last axis of length 3 (broadcasting); cheaper than einsum here."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
