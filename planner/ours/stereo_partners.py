"""The stereo partners a plan's views will find in the dense stage, forecast on the planning samples.

The CPU dense stage (``reconstruct.workspace.select_partners``) gives every view up to
``num_partners`` partners: views that share sparse points with it, whose median triangulation angle
at those points lies in [``min_triangulation_angle_deg``, ``max_triangulation_angle_deg``] and whose
baseline makes at least ``min_baseline_axis_angle_deg`` with both optical axes. A view with fewer
partners gets fewer depth maps, and fusion (three agreeing maps) keeps less of what it sees. The same
test on the planner's samples (shared visible samples in place of shared sparse points) forecasts
those partners before the flight; the budget prune (``planner.ours.ours_budget``) uses it so that the
views it keeps keep their partners. Measured on the tomb's 100-image plan (archive/pre_p1/planner_ours.md):
forecast against the dense stage's own choice, per view, agreed within one partner for 92 of 100 views.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from scene.camera import forward_vectors
from scene.config import setting, typed_settings


@dataclass(frozen=True)
class PartnerRule:
    """``budget_partners`` of ``conf/planner/ours.yaml``: the dense stage's partner test, and how much
    the budget prune values a partner (``weight``)."""

    weight: float = setting(0.5, low=0)
    min_shared_samples: int = setting(10, low=1)
    num_partners: int = setting(4, low=1)
    min_triangulation_angle_deg: float = setting(3.0, low=0, high=180)
    max_triangulation_angle_deg: float = setting(40.0, low=0, high=180)
    min_baseline_axis_angle_deg: float = setting(50.0, low=0, high=90)

    @classmethod
    def from_config(cls, node: Mapping | None, prefix: str = "planner ours: budget_partners") -> PartnerRule:
        """From the ``budget_partners`` mapping; ``ValueError`` names a bad setting."""
        rule = typed_settings(cls, node or {}, prefix)
        if rule.min_triangulation_angle_deg > rule.max_triangulation_angle_deg:
            raise ValueError(
                f"{prefix}: min_triangulation_angle_deg={rule.min_triangulation_angle_deg:g} is above "
                f"max_triangulation_angle_deg={rule.max_triangulation_angle_deg:g}"
            )
        return rule


def partner_matrix(
    visible: np.ndarray, direction: np.ndarray, viewpoints: np.ndarray, rule: PartnerRule
) -> np.ndarray:
    """(V, V) bool: which pairs of views pass the dense stage's partner test (symmetric, no diagonal).

    Args:
        visible: (V, P) bool, the samples each view sees.
        direction: (V, P, 3) unit vectors from each sample to the camera centre.
        viewpoints: (V, 5) ``x, y, z`` (m), ``yaw_deg``, ``pitch_deg``.
        rule: the test's thresholds.
    """
    visible = np.asarray(visible, bool)
    vps = np.asarray(viewpoints, dtype=float)
    n = len(vps)
    shared = visible.astype(np.int32) @ visible.T.astype(np.int32)
    median_deg = np.full((n, n), np.nan)
    for a in range(n - 1):
        cols = np.flatnonzero(visible[a])
        others = np.arange(a + 1, n)
        others = others[shared[a, others] >= rule.min_shared_samples]
        if not len(cols) or not len(others):
            continue
        cos = np.einsum("pk,vpk->vp", direction[a, cols], direction[np.ix_(others, cols)])
        angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        angles[~visible[np.ix_(others, cols)]] = np.nan
        median_deg[a, others] = np.nanmedian(angles, axis=1)  # every row has >= min_shared values
    median_deg = np.fmin(median_deg, median_deg.T)
    baseline = vps[None, :, :3] - vps[:, None, :3]
    length = np.linalg.norm(baseline, axis=-1)
    length[length == 0] = np.inf
    forward = forward_vectors(vps[:, 3], vps[:, 4])
    cos_ref = np.abs(np.einsum("ak,abk->ab", forward, baseline)) / length
    cos_axis = np.maximum(cos_ref, cos_ref.T)  # the pair's smaller angle between baseline and an axis
    axis_ok = np.degrees(np.arccos(np.clip(cos_axis, 0.0, 1.0))) >= rule.min_baseline_axis_angle_deg
    with np.errstate(invalid="ignore"):
        angle_ok = (median_deg >= rule.min_triangulation_angle_deg) & (
            median_deg <= rule.max_triangulation_angle_deg
        )
    out = angle_ok & axis_ok & (shared >= rule.min_shared_samples)
    np.fill_diagonal(out, False)
    return out


def partner_counts(eligible: np.ndarray, num_partners: int) -> np.ndarray:
    """(V,) the partners each view gets: its eligible views, at most ``num_partners``."""
    return np.minimum(np.asarray(eligible, bool).sum(axis=1), int(num_partners))


def added_shortfall(eligible: np.ndarray, alive: np.ndarray, num_partners: int) -> np.ndarray:
    """(V,) how much removing each view adds to the plan's partner shortfall.

    The shortfall is the sum over the ``alive`` views of the partners each lacks of
    ``num_partners``. Removing view v costs one for every alive view that counts v among its
    partners and has no spare one; v's own shortfall leaves with it (a view no pair can use is
    the first to go). Entries of views not alive are meaningless.
    """
    live = np.asarray(eligible, bool) & alive[None, :] & alive[:, None]
    count = live.sum(axis=1)
    lacking = np.maximum(int(num_partners) - count, 0)
    no_spare = count <= int(num_partners)
    return (live & no_spare[:, None]).sum(axis=0) - lacking


def forecast(eligible: np.ndarray, num_partners: int) -> dict:
    """What ``plan.json`` records: the mean partners a view and the views with 0 .. num_partners."""
    counts = partner_counts(eligible, num_partners)
    return {
        "mean_partners": float(counts.mean()) if len(counts) else 0.0,
        "views_by_partners": np.bincount(counts, minlength=int(num_partners) + 1).tolist(),
    }
