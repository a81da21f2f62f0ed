"""Eq. 1-9 on hand-computed cases, and the incremental objective against the dense reference."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from planner.heuristics import (
    HeuristicParams,
    angular_spread,
    connectivity_score,
    coverage_point_scores,
    distance_score,
    global_score,
    overlap_pair_scores,
    overlap_ratios,
    pair_matchability,
    point_scores,
    smith_w1,
    smith_w3,
    view_geometry,
    view_quality,
    viewpoint_set_scores,
)
from planner.objective import ObjectiveState
from planner.visibility import Observations
from scene.plan import PlanningError

PARAMS = HeuristicParams(  # Eq. 1-5 as printed: the hand-computed values below
    k_count=3,
    target_lo_m=8.0,
    target_hi_m=12.0,
    d_margin_m=4.0,
    r_min=0.1,
    r_max=0.5,
    top_k=2,
    tau_edge=0.25,
    point_score="literal",
    matchable_overlap=False,
)


def _obs_for_point(normal, view_dirs, distances) -> Observations:
    """Observations of one point at the origin seen along unit ``view_dirs`` at ``distances``."""
    u = np.asarray(view_dirs, dtype=np.float32).reshape(-1, 1, 3)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    n = np.asarray(normal, dtype=np.float32)
    return Observations(
        visible=np.ones((len(u), 1), bool),
        distance=np.asarray(distances, dtype=np.float32).reshape(-1, 1),
        direction=u,
        cos_incidence=(u @ n).reshape(-1, 1),
    )


def test_smith_constants():
    assert smith_w1(math.pi / 16) == pytest.approx(0.5)
    assert smith_w3(math.pi / 4) == pytest.approx(0.5)
    assert smith_w1(0.0) == pytest.approx(1.0 / (1.0 + math.exp(32 * math.pi / 16)))
    assert smith_w3(0.0) == pytest.approx(1.0 - 1.0 / (1.0 + math.exp(8 * math.pi / 4)))


def test_one_frontal_view_at_target_distance():
    obs = _obs_for_point([0, 0, 1], [[0, 0, 1]], [10.0])
    s = point_scores(obs.visible, obs.distance, obs.direction, obs.cos_incidence, PARAMS)
    w = 1.0 / (1.0 + math.exp(2.0 * math.pi))  # w1(0) = 1 - w3(0) = 1 / (1 + e^{2 pi})
    assert s["front"][0] == pytest.approx(1.0)
    assert s["distance"][0] == pytest.approx(1.0)
    assert s["sigma"][0] == pytest.approx(0.0, abs=1e-6)
    assert s["parallax"][0] == pytest.approx(w * (1.0 - w))
    assert s["count"][0] == pytest.approx(1.0 / 3.0)
    assert s["R_point"][0] == pytest.approx(w * (1.0 - w) / 3.0)


def test_two_views_with_known_angular_spread():
    theta = math.radians(20.0)
    dirs = [[math.sin(theta), 0, math.cos(theta)], [-math.sin(theta), 0, math.cos(theta)]]
    obs = _obs_for_point([0, 0, 1], dirs, [10.0, 14.0])  # second view 2 m past the range: 0.5
    s = point_scores(obs.visible, obs.distance, obs.direction, obs.cos_incidence, PARAMS)
    assert s["sigma"][0] == pytest.approx(theta, rel=1e-5)
    assert s["front"][0] == pytest.approx(math.cos(theta), rel=1e-6)
    assert s["distance"][0] == pytest.approx(1.0)  # the best observation
    expected = math.cos(theta) * 1.0 * smith_w1(theta) * smith_w3(theta) * (2.0 / 3.0)
    assert s["R_point"][0] == pytest.approx(expected, rel=1e-5)


def test_three_views_spread_and_count_saturates():
    a = math.radians(30.0)
    dirs = [[0, 0, 1], [math.sin(a), 0, math.cos(a)], [-math.sin(a), 0, math.cos(a)]]
    obs = _obs_for_point([0, 0, 1], dirs, [9.0, 10.0, 11.0])
    sigma = angular_spread(obs.direction, obs.visible)[0]
    assert sigma == pytest.approx(a * math.sqrt(2.0 / 3.0), rel=1e-5)
    s = point_scores(obs.visible, obs.distance, obs.direction, obs.cos_incidence, PARAMS)
    assert s["count"][0] == 1.0 and s["front"][0] == pytest.approx(1.0)


def test_distance_ramp():
    d = np.array([4.0, 6.0, 8.0, 10.0, 12.0, 13.0, 16.0, 30.0])
    np.testing.assert_allclose(
        distance_score(d, 8.0, 12.0, 4.0), [0.0, 0.5, 1, 1, 1, 0.75, 0.0, 0.0], atol=1e-6
    )


def test_disconnected_viewpoint_graph():
    vis = np.zeros((5, 12), bool)
    vis[0:3, 0:4] = True  # component A: views 0, 1, 2 share points 0-3
    vis[3:5, 6:10] = True  # component B: views 3, 4 share points 6-9
    r = overlap_ratios(vis)
    assert r[0, 1] == 1.0 and r[0, 3] == 0.0 and r[3, 4] == 1.0 and r[0, 0] == 0.0
    f = overlap_pair_scores(r, 0.1, 0.5)
    assert connectivity_score(f, 0.25) == pytest.approx(3.0 / 5.0)
    v = viewpoint_set_scores(vis, PARAMS)
    assert v["visibility"] == pytest.approx(20.0 / 60.0)
    assert v["overlap"] == pytest.approx((3 * 1.0 + 2 * 0.5) / 5.0)  # top-2: A (1, 1), B (1, 0)
    assert v["connectivity"] == pytest.approx(0.6)
    assert v["R_viewpoint"] == pytest.approx((1.0 / 3.0 + 0.8 + 0.6) / 3.0)


def test_overlap_ramp_and_partial_ratio():
    vis = np.zeros((2, 10), bool)
    vis[0, :10] = True
    vis[1, 7:10] = True  # 3 common of min(10, 3) = 3 -> r = 1
    vis2 = np.zeros((2, 10), bool)
    vis2[0, :5] = True
    vis2[1, 3:10] = True  # 2 common / min(5, 7) -> r = 0.4 -> f = 0.75
    assert overlap_ratios(vis)[0, 1] == pytest.approx(1.0)
    assert overlap_pair_scores(overlap_ratios(vis2), 0.1, 0.5)[0, 1] == pytest.approx(0.75)


def test_global_score_is_point_sum_plus_P_times_viewpoint_score():
    obs = _random_obs(np.random.default_rng(0), 6, 20)
    g = global_score(obs.visible, obs.distance, obs.direction, obs.cos_incidence, PARAMS)
    pts = point_scores(obs.visible, obs.distance, obs.direction, obs.cos_incidence, PARAMS)
    assert g["R"] == pytest.approx(pts["R_point"].sum() + 20 * g["R_viewpoint"])


def _points(n_pt: int) -> np.ndarray:
    """The same (P, 3) ground samples (upward normals) for every call with ``n_pt``."""
    xy = np.random.default_rng(n_pt).uniform(-10.0, 10.0, (n_pt, 2))
    return np.column_stack([xy, np.zeros(n_pt)])


def _random_obs(rng, n_vp: int, n_pt: int, density: float = 0.3) -> Observations:
    """Observations of ``_points(n_pt)`` from cameras 4-14 m above them; visibility in blocks
    (several components). Directions and distances follow the cameras' true positions."""
    vis = rng.random((n_vp, n_pt)) < density
    block = rng.integers(0, 3, n_vp)  # viewpoints of a block see mostly the same third of the points
    third = np.arange(n_pt) * 3 // n_pt
    vis &= (block[:, None] == third[None]) | (rng.random((n_vp, n_pt)) < 0.05)
    centres = np.column_stack([rng.uniform(-10.0, 10.0, (n_vp, 2)), rng.uniform(4.0, 14.0, n_vp)])
    offset = centres[:, None] - _points(n_pt)[None]
    distance = np.linalg.norm(offset, axis=-1)
    u = offset / distance[..., None]
    return Observations(
        visible=vis,
        distance=distance.astype(np.float32),
        direction=np.where(vis[..., None], u, 0.0).astype(np.float32),
        cos_incidence=u[..., 2].astype(np.float32),
    )


def _reference(obs: Observations, params, mode="detail", point_rows=None):
    points = _points(obs.visible.shape[1])
    if mode == "detail":
        return global_score(obs.visible, obs.distance, obs.direction, obs.cos_incidence, params, points)
    rows = np.ones(len(obs), bool) if point_rows is None else point_rows
    pts = coverage_point_scores(obs.visible[rows], obs.distance[rows], params)
    geometry = view_geometry(obs.visible, obs.distance, obs.direction, points)
    vset = viewpoint_set_scores(obs.visible, params, geometry)
    return {"R": pts.sum() + obs.visible.shape[1] * vset["R_viewpoint"], **vset}


@pytest.mark.parametrize(("point_score", "matchable"), [("literal", False), ("per_view", True)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_incremental_objective_matches_reference(seed, point_score, matchable):
    rng = np.random.default_rng(seed)
    n_pt = 60
    PARAMS = dataclasses.replace(globals()["PARAMS"], point_score=point_score, matchable_overlap=matchable)
    base = _random_obs(rng, 14, n_pt)
    state = ObjectiveState(PARAMS, n_pt, points=_points(n_pt))
    state.reset(base)
    assert state.R == pytest.approx(_reference(base, PARAMS)["R"], rel=1e-7, abs=1e-9)
    cluster = np.array([1, 4, 5, 9])
    alts = _random_obs(rng, 3 * len(cluster), n_pt)
    prop = state.evaluate(cluster, alts, 3)
    for i in range(3):
        rows = np.arange(14)
        new_rows = Observations.concatenate(
            [base.take(np.setdiff1d(rows, cluster)), alts.take(np.arange(4 * i, 4 * i + 4))], n_pt
        )
        ref = _reference(new_rows, PARAMS)
        assert prop.R[i] == pytest.approx(ref["R"], rel=1e-7)
        assert prop.connectivity[i] == pytest.approx(ref["connectivity"])
        assert prop.overlap[i] == pytest.approx(ref["overlap"])
    # commit the second alternative in place: rows keep their order
    state.commit(cluster, alts.take(np.arange(4, 8)))
    current = base.take(np.arange(14))
    for k, row in enumerate(cluster):
        current.visible[row] = alts.visible[4 + k]
        current.distance[row] = alts.distance[4 + k]
        current.direction[row] = alts.direction[4 + k]
        current.cos_incidence[row] = alts.cos_incidence[4 + k]
    assert state.R == pytest.approx(prop.R[1], rel=1e-7)
    assert state.R == pytest.approx(_reference(current, PARAMS)["R"], rel=1e-7)
    # removal and addition
    prop = state.evaluate([3, 7])
    kept = current.take(np.setdiff1d(np.arange(14), [3, 7]))
    assert prop.R[0] == pytest.approx(_reference(kept, PARAMS)["R"], rel=1e-7)
    state.commit([3, 7])
    extra = _random_obs(rng, 2, n_pt)
    prop = state.evaluate([], extra)
    state.commit([], extra)
    grown = Observations.concatenate([kept, extra], n_pt)
    assert prop.R[0] == pytest.approx(state.R, rel=1e-12)
    assert state.R == pytest.approx(_reference(grown, PARAMS)["R"], rel=1e-7)
    if point_score == "literal":
        np.testing.assert_array_equal(state.count, grown.visible.sum(axis=0))
    else:
        good = view_quality(grown.visible, grown.distance, grown.cos_incidence, PARAMS) > 0
        np.testing.assert_array_equal(state.count, good.sum(axis=0))


def test_incremental_coverage_objective_with_rows_not_counting_for_points():
    rng = np.random.default_rng(5)
    n_pt = 50
    params = HeuristicParams(
        k_count=2, target_lo_m=10.0, target_hi_m=14.0, d_margin_m=6.0, top_k=3, coverage_closeness_weight=0.1
    )
    base = _random_obs(rng, 10, n_pt)
    point_rows = np.r_[np.zeros(6, bool), np.ones(4, bool)]  # six detail rows, four coverage rows
    state = ObjectiveState(params, n_pt, mode="coverage", points=_points(n_pt))
    state.reset(base, point_rows=point_rows)
    assert state.R == pytest.approx(_reference(base, params, "coverage", point_rows)["R"], rel=1e-7)
    alts = _random_obs(rng, 4, n_pt)
    prop = state.evaluate([6, 8], alts, 2)
    for i in range(2):
        new = Observations.concatenate(
            [base.take([0, 1, 2, 3, 4, 5, 7, 9]), alts.take([2 * i, 2 * i + 1])], n_pt
        )
        ref = _reference(new, params, "coverage", np.r_[np.zeros(6, bool), np.ones(4, bool)])
        assert prop.R[i] == pytest.approx(ref["R"], rel=1e-7)


@pytest.mark.parametrize(("n_vp", "top_k"), [(14, 2), (30, 3), (4, 4), (2, 1)])
def test_single_removal_shortcut_matches_general_evaluation(n_vp, top_k):
    rng = np.random.default_rng(n_vp)
    params = HeuristicParams(top_k=top_k, target_lo_m=8.0, target_hi_m=12.0, d_margin_m=4.0)
    obs = _random_obs(rng, n_vp, 60)
    state = ObjectiveState(params, 60, points=_points(60))
    state.reset(obs)
    for i in range(n_vp):
        kept = obs.take(np.setdiff1d(np.arange(n_vp), [i]))
        expected = _reference(kept, params)["R"]
        assert state.evaluate_removal(i) == pytest.approx(expected, rel=1e-7)
        assert state.evaluate_removal(i) == pytest.approx(state.evaluate([i]).R[0], rel=1e-12)


def _wall_point(view_angles_deg, distances, params):
    """R_point of a wall point (normal +x) seen from horizontal views at ``view_angles_deg`` off
    the normal and ``distances`` (m)."""
    a = np.radians(np.asarray(view_angles_deg, dtype=float))
    obs = _obs_for_point([1, 0, 0], np.stack([np.cos(a), np.sin(a), 0 * a], axis=1), distances)
    return point_scores(obs.visible, obs.distance, obs.direction, obs.cos_incidence, params)


def test_per_view_score_needs_several_close_frontal_views():
    per_view = dataclasses.replace(PARAMS, point_score="per_view")
    # One close frontal view, one far (15 m: distance score 0.25) and one grazing (70 deg) view.
    weak_views, weak_dist = [0.0, 20.0, 70.0], [10.0, 15.0, 10.0]
    # Three close views 0 and +-20 deg off the normal.
    good_views, good_dist = [0.0, 20.0, -20.0], [10.0, 10.0, 10.0]

    literal_weak = _wall_point(weak_views, weak_dist, PARAMS)
    sigma = literal_weak["sigma"][0]
    # The literal form takes the best frontality (1) and distance (1) from any view, counts all 3.
    assert literal_weak["R_point"][0] == pytest.approx(smith_w1(sigma) * smith_w3(sigma))
    assert literal_weak["R_point"][0] > 0.85  # 0.898: only the parallax of the 0/20/70 deg spread costs

    weak = _wall_point(weak_views, weak_dist, per_view)
    # q = [1, F(20 deg) * 0.25 = 0.25, F(70 deg) = 0]: S_quality = 1.25 / 3; parallax over the
    # two good views (0 and 20 deg apart: sigma = 10 deg).
    assert weak["quality"][0] == pytest.approx(1.25 / 3.0)
    assert weak["sigma"][0] == pytest.approx(math.radians(10.0), abs=1e-6)
    w = smith_w1(math.radians(10.0)) * smith_w3(math.radians(10.0))
    assert weak["R_point"][0] == pytest.approx(1.25 / 3.0 * w, rel=1e-6)

    good = _wall_point(good_views, good_dist, per_view)
    sigma_good = math.sqrt((2 * math.radians(20.0) ** 2) / 3)  # mean direction along the normal
    assert good["quality"][0] == pytest.approx(1.0)
    assert good["sigma"][0] == pytest.approx(sigma_good, abs=1e-6)
    assert good["R_point"][0] == pytest.approx(smith_w1(sigma_good) * smith_w3(sigma_good), rel=1e-6)
    assert good["R_point"][0] > 0.9 > 0.4 > weak["R_point"][0]


def test_frontality_is_full_to_30_deg_and_gone_at_60():
    params = dataclasses.replace(PARAMS, point_score="per_view")
    scores = _wall_point([0.0, 30.0, 45.0, 60.0, 75.0], [10.0] * 5, params)
    cos45 = math.cos(math.radians(45.0))
    lo, hi = math.cos(math.radians(60.0)), math.cos(math.radians(30.0))
    a = np.radians([0.0, 30.0, 45.0, 60.0, 75.0])
    obs = _obs_for_point([1, 0, 0], np.stack([np.cos(a), np.sin(a), 0 * a], axis=1), [10.0] * 5)
    q = view_quality(obs.visible, obs.distance, obs.cos_incidence, params)[:, 0]
    np.testing.assert_allclose(q, [1.0, 1.0, (cos45 - lo) / (hi - lo), 0.0, 0.0], atol=1e-6)
    assert scores["quality"][0] == pytest.approx((2.0 + (cos45 - lo) / (hi - lo)) / 3.0, rel=1e-6)
    with pytest.raises(PlanningError, match="frontal_full_deg < frontal_cone_deg"):
        dataclasses.replace(params, frontal_full_deg=60.0, frontal_cone_deg=30.0)
    with pytest.raises(PlanningError, match="point_score"):
        dataclasses.replace(params, point_score="best")


def test_matchable_overlap_of_two_views_of_a_plane():
    """Two downward views of a ground plane 10 m below: 4 m apart they link fully, 8 m apart they
    meet at 2 atan(0.4) = 43.6 deg (g = (45 - 43.6) / 15), and one 1.75x farther has g = 0.5."""
    params = dataclasses.replace(PARAMS, point_score="per_view", matchable_overlap=True, top_k=1)
    xy = np.stack(np.meshgrid(np.linspace(-6, 14, 21), np.linspace(-5, 5, 11)), axis=-1).reshape(-1, 2)
    points = np.column_stack([xy, np.zeros(len(xy))])

    def observe(centre, radius):
        offset = np.asarray(centre, dtype=float)[None] - points
        distance = np.linalg.norm(offset, axis=1)
        visible = np.linalg.norm(points[:, :2] - np.asarray(centre[:2]), axis=1) <= radius
        return visible, distance, offset / distance[:, None]

    def g_and_overlap(a, b, radius=4.5):
        vis, dist, dirs = (np.stack(x) for x in zip(observe(a, radius), observe(b, radius), strict=True))
        centre, look = view_geometry(vis, dist, dirs, points)
        np.testing.assert_allclose(centre, [a, b], atol=1e-9)  # the camera centres are recovered
        g = pair_matchability(centre[0], look[0], centre[1], look[1], params)
        plain = dataclasses.replace(params, matchable_overlap=False)
        f = viewpoint_set_scores(vis, plain)["overlap"]
        return g, f, viewpoint_set_scores(vis, params, (centre, look))["overlap"]

    g, f, matched = g_and_overlap([0.0, 0.0, 10.0], [4.0, 0.0, 10.0])
    assert g == pytest.approx(1.0) and matched == pytest.approx(f) and f > 0
    g, f, matched = g_and_overlap([0.0, 0.0, 10.0], [8.0, 0.0, 10.0], radius=6.0)
    expected = (45.0 - math.degrees(2 * math.atan(0.4))) / 15.0
    assert g == pytest.approx(expected, abs=1e-9) and matched == pytest.approx(f * expected)
    g, _, _ = g_and_overlap([0.0, 0.0, 10.0], [0.0, 0.0, 17.5])
    assert g == pytest.approx(0.5)
