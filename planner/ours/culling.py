"""Viewpoint culling (paper Sec. III-F).

1. Viewpoints that see no sampled point are dropped.
2. Pairs whose overlap ratio r_ij is at least ``overlap_threshold`` are redundancy candidates,
   most overlapping first. For each pair whose two viewpoints are both still present, removing
   either one is scored; the better removal is accepted when R stays at or above
   ``R_reference - tolerance`` (R_reference: R after step 1), so the whole culling pass lowers R by
   at most ``tolerance``.

With a flight-time term (``ours_plus``) the pass works on R minus the flight-time cost: a removal
that loses a little R but saves its stop and detour can pass the floor.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from planner.objective import ObjectiveState


def cull(
    state: ObjectiveState,
    cullable: np.ndarray,
    overlap_threshold: float,
    tolerance: float,
    desc: str = "culling",
    time_term=None,
    viewpoints: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Cull viewpoints among the ``cullable`` (V,) rows of ``state``; the state is updated.

    Args:
        state: objective state of the current set.
        cullable: (V,) bool, rows that may be removed.
        overlap_threshold: pairs with r_ij >= this are redundancy candidates.
        tolerance: largest accepted drop of R (objective units) over the pass.
        time_term: a ``planner.ours.flight_time_term.FlightTimeTerm``, with ``viewpoints`` (V, 5) the rows'
            viewpoints; None: R alone (the paper).

    Returns:
        kept: (V,) bool over the input rows; statistics (removed empty, removed redundant,
        R before and after, pairs tried, time).
    """
    t0 = time.perf_counter()
    if not (0.0 < float(overlap_threshold) <= 1.0) or float(tolerance) < 0.0:
        raise ValueError(
            f"need 0 < overlap_threshold <= 1 and tolerance >= 0, got {overlap_threshold}, {tolerance}"
        )
    n0 = state.n_viewpoints
    cullable = np.asarray(cullable, bool).reshape(n0)
    ids = np.arange(n0)  # current row -> input row
    r_before = state.R
    empty = np.flatnonzero(cullable & (state.n_visible == 0))
    if len(empty):
        state.commit(empty)
        ids = np.delete(ids, empty)
    if time_term is not None:
        viewpoints = np.asarray(viewpoints, float).reshape(n0, 5)
        order = time_term.order(viewpoints)

    def time_cost(without: int | None = None) -> float:
        """Flight-time cost of the present rows (minus input row ``without``) in the pass's order."""
        if time_term is None:
            return 0.0
        visit = [i for i in order if present[i] and i != without]
        return float(time_term.cost(viewpoints[visit]))

    present = np.zeros(n0, bool)
    present[ids] = True
    r_reference = state.R - time_cost()
    floor = r_reference - float(tolerance)

    n = state.n_visible
    smaller = np.minimum(n[:, None], n[None, :])
    ratio = np.where(smaller > 0, state.common / np.maximum(smaller, 1), 0.0)
    ok = np.triu(ratio >= overlap_threshold, 1) & (cullable[ids][:, None] | cullable[ids][None, :])
    ii, jj = np.nonzero(ok)
    pair_order = np.lexsort((jj, ii, -ratio[ii, jj]))
    pairs = [(int(ids[ii[k]]), int(ids[jj[k]])) for k in pair_order]
    removed = tried = 0
    row_of = np.full(n0, -1)
    row_of[ids] = np.arange(len(ids))
    removal_score: dict[int, float] = {}
    for a, b in tqdm(pairs, desc=desc, leave=False, disable=None):
        if not (present[a] and present[b]):
            continue
        options = [x for x in (a, b) if cullable[x]]
        # R without a viewpoint only changes when the set does: score each one once per set
        for x in options:
            if x not in removal_score:
                removal_score[x] = state.evaluate_removal(row_of[x]) - time_cost(without=x)
        scores = [removal_score[x] for x in options]
        tried += 1
        best = int(np.argmax(scores))
        if scores[best] >= floor:
            victim = options[best]
            state.commit([row_of[victim]])
            present[victim] = False
            removal_score.clear()
            row_of[present] = np.arange(int(present.sum()))
            row_of[~present] = -1
            removed += 1
    return present, {
        "removed_empty": int(len(empty)),
        "removed_redundant": removed,
        "pairs_tried": tried,
        "R_before": r_before,
        "R_reference": r_reference,
        "R_after": state.R,
        **({} if time_term is None else {"flight_time_cost_after": time_cost()}),
        "time_s": time.perf_counter() - t0,
    }
