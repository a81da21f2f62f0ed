"""Smith et al. baseline: hand-computed heuristic values, the Nelder-Mead core, the optimisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from planner.smith import smith
from planner.smith.smith_directions import DirectionSearch
from planner.smith.smith_heuristic import objective_terms, pair_terms, reconstructability
from planner.visibility import VisibilityLimits, VisibilityModel
from scene.base import Box
from scene.camera import Intrinsics, forward_vectors, look_at, project_points
from scene.plan import read_viewpoints, write_plan

CAMERA = Intrinsics(1024, 768, 60.0)
D_MAX = 50.0


def hand_pair(alpha_deg, d_a, d_b, theta_a_deg, theta_b_deg):
    """The pair term written out with the published constants."""
    a = math.radians(alpha_deg)
    w1 = 1.0 / (1.0 + math.exp(-32.0 * (a - math.pi / 16.0)))
    w3 = 1.0 - 1.0 / (1.0 + math.exp(-8.0 * (a - math.pi / 4.0)))
    w2 = 1.0 - max(d_a, d_b) / D_MAX
    return w1 * w2 * w3 * math.cos(math.radians(max(theta_a_deg, theta_b_deg)))


def ray(theta_deg):
    """Unit direction tilted theta from +z towards +x (theta < 0: towards -x)."""
    t = math.radians(theta_deg)
    return np.array([math.sin(t), 0.0, math.cos(t)])


# Three views of a sample at the origin with normal +z: (tilt from the normal in deg, distance in m).
VIEWS = [(0.0, 10.0), (30.0, 20.0), (-45.0, 30.0)]


def test_pair_term_equals_hand_value():
    (ta, da), (tb, db) = VIEWS[0], VIEWS[1]
    got = pair_terms(
        ray(ta), 1 - da / D_MAX, math.cos(0.0), ray(tb), 1 - db / D_MAX, math.cos(math.radians(tb))
    )
    assert float(got) == pytest.approx(hand_pair(30.0, da, db, 0.0, 30.0), rel=1e-12)


@pytest.mark.parametrize("n_views", [2, 3])
def test_h_equals_sum_of_hand_computed_pairs(n_views):
    views = VIEWS[:n_views]
    dirs = np.array([ray(t) for t, _ in views])[None]
    scales = np.array([1 - d / D_MAX for _, d in views])[None]
    coss = np.array([math.cos(math.radians(t)) for t, _ in views])[None]
    h = reconstructability(dirs, scales, coss, np.ones((1, n_views), bool))
    expected = sum(
        hand_pair(
            abs(views[i][0] - views[j][0]), views[i][1], views[j][1], abs(views[i][0]), abs(views[j][0])
        )
        for i in range(n_views)
        for j in range(i + 1, n_views)
    )
    assert h[0] == pytest.approx(expected, rel=1e-12)
    assert objective_terms(h)[0] == pytest.approx((3.0 - expected) ** 2, rel=1e-12)


def test_unobserved_sample_has_h_minus_one_and_single_view_zero():
    dirs = np.zeros((2, 3, 3))
    dirs[1, 0] = [0, 0, 1]
    valid = np.array([[False] * 3, [True, False, False]])
    h = reconstructability(dirs, np.ones((2, 3)), np.ones((2, 3)), valid)
    np.testing.assert_array_equal(h, [-1.0, 0.0])
    np.testing.assert_array_equal(objective_terms(h), [16.0, 9.0])


def flat_ground(size=200.0):
    h = size / 2
    v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_objective_on_a_real_visibility_model_matches_hand_value():
    """Three cameras aimed at one ground sample: h from visibility + ray geometry equals the hand value."""
    model = VisibilityModel(
        flat_ground(),
        np.zeros((1, 3)),
        np.array([[0.0, 0.0, 1.0]]),
        CAMERA,
        VisibilityLimits(0.0, D_MAX, 85.0),
    )
    vps = np.array([look_at(ray(t) * d, np.zeros(3)).as_array() for t, d in VIEWS])
    vps[0, 3] = 0.0  # nadir: any yaw sees the sample
    objective = smith.SmithObjective(model, vps, D_MAX)
    expected = hand_pair(30, 10, 20, 0, 30) + hand_pair(45, 10, 30, 0, 45) + hand_pair(75, 20, 30, 30, 45)
    assert objective.h[0] == pytest.approx(expected, rel=1e-5)
    assert objective.objective() == pytest.approx((3.0 - expected) ** 2, rel=1e-5)


def test_nelder_mead_step_minimises_a_quadratic():
    centre = np.array([1.0, -2.0, 3.0])

    def evaluate(points):
        v = np.sum((points - centre) ** 2, axis=1)
        return v, np.zeros(len(points)), np.zeros(len(points))

    stepper = smith.NelderMeadStepper(evaluate)
    rng = np.random.default_rng(0)
    simplices = np.stack(
        [smith.initial_simplex(np.zeros(3), 0.25, rng), smith.initial_simplex(centre + 5, 0.5, rng)]
    )
    for _ in range(150):
        best, value, _, _ = stepper.step(simplices)
    np.testing.assert_allclose(best, np.stack([centre, centre]), atol=1e-3)
    assert np.all(value < 1e-6)


def test_direction_search_finds_the_direction_of_a_single_gain():
    search = DirectionSearch(CAMERA, n_yaw=64, n_pitch=23)
    target = forward_vectors(40.0, -30.0)
    gains = np.zeros((1, search.n_bins))
    gains[0, search.bin_of(target[None])[0]] = -2.5
    value, yaw, pitch = search.best(gains)
    assert value[0] == pytest.approx(-2.5)
    # The winning direction (the first of the tied ones) holds the gain's bin inside its image.
    bin_dir = search.bins[search.bin_of(target[None])[0]]
    pixels, depth = project_points(bin_dir[None], np.array([[0, 0, 0, yaw[0], pitch[0]]]), CAMERA)
    assert depth[0, 0] > 0
    assert 0 <= pixels[0, 0, 0] <= CAMERA.width and 0 <= pixels[0, 0, 1] <= CAMERA.height
    # A gain nobody's frustum can hold (straight up) gives value 0.
    up = np.zeros((1, search.n_bins))
    up[0, search.bin_of(np.array([[0.0, 0.0, 1.0]]))[0]] = -1.0
    assert search.best(up)[0][0] == 0.0


def test_nelder_mead_stage_lowers_objective_on_a_toy_proxy(tmp_path):
    building = trimesh.creation.box(extents=(12.0, 8.0, 6.0))
    building.apply_translation((0, 0, 3.0))
    proxy = trimesh.util.concatenate([flat_ground(60.0), building])
    params = {
        "n_samples": 400,
        "max_iters": 3,
        "n_yaw": 64,
        "n_pitch": 23,
        "progress": False,
        "grid_altitude_above_top_m": 5.0,
        "overlap_reference": "ground",
    }
    plan = smith.plan(proxy, CAMERA, params, seed=0)
    info = plan.info
    assert info["optimisation"]["steps"] > 0
    assert info["objective_final"] < info["objective_initial"] - 0.05
    assert len(plan.viewpoints) == info["n_initial_views"]
    # Constraints of the optimisation hold for every final view.
    model = VisibilityModel(
        proxy, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), CAMERA, VisibilityLimits(0, 50, 85)
    )
    assert np.all(plan.viewpoints[:, 2] >= 5.0 - 1e-6)
    assert np.all(model.clearance(plan.viewpoints[:, :3]) >= 5.0 - 0.01)
    assert np.all(plan.viewpoints[:, 4] <= 0.0)
    # The plan round-trips through the run directory's plan files.
    write_plan(plan, tmp_path)
    read_back, kinds = read_viewpoints(tmp_path / "viewpoints.csv")
    np.testing.assert_allclose(read_back, plan.viewpoints, atol=1e-6)
    assert kinds == plan.kinds


@pytest.mark.parametrize("reference", ["top", "ground"])
def test_initial_grid_flies_at_the_target_gsd_with_the_overlap_on_the_reference(reference):
    bounds = Box((-20.0, -15.0, 0.0), (20.0, 15.0, 12.0))
    params = smith._merged({"target_gsd_m": 0.02, "overlap_reference": reference})
    vps, kinds = smith.initial_grid(bounds, CAMERA, params)
    d_t = 0.02 * CAMERA.focal_px
    np.testing.assert_allclose(vps[:, 2], 12.0 + d_t)
    distance = d_t if reference == "top" else 12.0 + d_t
    along = distance * CAMERA.height / CAMERA.focal_px  # nadir footprint along the lines (m)
    across = distance * CAMERA.width / CAMERA.focal_px
    nadir = vps[np.array(kinds) == "nadir"]
    lines = np.unique(np.round(nadir[:, 1], 6))
    first_line = np.sort(nadir[np.isclose(nadir[:, 1], lines[0]), 0])
    front = 1.0 - np.diff(first_line).max() / along
    side = 1.0 - np.diff(lines).max() / across
    assert 0.8 - 1e-6 <= front <= 0.82 and 0.8 - 1e-6 <= side <= 0.82
    assert kinds.count("oblique") > kinds.count("nadir")


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="front_overlap"):
        smith._merged({"front_overlap": 1.0})
    with pytest.raises(ValueError, match="side_overlap"):
        smith._merged({"side_overlap": 0.0})
    with pytest.raises(ValueError, match="n_samples"):
        smith._merged({"n_samples": 0})
    with pytest.raises(ValueError, match="min_distance_m"):
        smith._merged({"min_distance_m": 60.0})
    with pytest.raises(ValueError, match="unknown"):
        smith._merged({"h_targt": 3})
    with pytest.raises(ValueError, match="overlap_reference"):
        smith._merged({"overlap_reference": "roof"})
    with pytest.raises(ValueError, match="target_gsd_m"):
        smith._merged({"target_gsd_m": 0.0})


def test_views_far_above_a_wall_come_down_to_its_best_positions():
    # One wall (its -x face, 20 m wide, 10 m tall) and three views 40 m up, 5 m in front of it: from
    # there they see the wall at grazing incidence and 35-40 m away. Each view's value at a position
    # is the gain of its best viewing direction there; the optimisation must bring the objective
    # down and each view close to the best value an exhaustive search over positions finds.
    wall = trimesh.creation.box(extents=(0.5, 20.0, 10.0))
    wall.apply_translation((0.25, 0.0, 5.0))
    points, normals = smith.sample_surface(wall, 2000, 0)
    front = normals[:, 0] < -0.9
    limits = VisibilityLimits(0.0, D_MAX, math.degrees(math.acos(0.087)))
    model = VisibilityModel(wall, points[front], normals[front], CAMERA, limits)
    start = np.array([look_at([-5.0, y, 40.0], [0.0, y, 5.0]).as_array() for y in (-6.0, 0.0, 6.0)])
    objective = smith.SmithObjective(model, start, D_MAX)
    initial = objective.objective()
    params = smith._merged({"progress": False, "n_yaw": 64, "n_pitch": 23})
    search = DirectionSearch(CAMERA, 64, 23, 3, 2.0)
    smith.optimise(objective, search, params, np.array([0.0, 0.0, 5.0]), np.random.default_rng(0))
    assert objective.objective() < 0.5 * initial
    final = objective.viewpoints
    assert np.all(final[:, 0] < -5.0) and np.all(final[:, 2] < 25.0)  # down in front of the wall
    # The exhaustive search: the middle view's value on a 2.5 m grid, the other two where they ended.
    objective.set_active(np.array([1]), False)
    x, y, z = np.meshgrid(np.arange(-30.0, -4.0, 2.5), np.arange(-8.0, 8.1, 4.0), np.arange(5.0, 40.1, 2.5))
    grid = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    best_on_grid = objective.position_gains(grid, search)[0].min()
    reached = objective.position_gains(final[1:2, :3], search)[0][0]
    assert reached <= 0.9 * best_on_grid  # values are negative: at least 90 % of the grid's best gain


def test_a_view_that_contributes_nothing_restarts_like_the_public_code():
    building = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    building.apply_translation((0.0, 0.0, 5.0))
    model = VisibilityModel(
        building, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), CAMERA, VisibilityLimits(0, D_MAX, 85)
    )
    centre = np.array([0.0, 0.0, 5.0])
    # In the open: min_distance (5 m) towards (0, 0, 0.9 d_max = 45 m).
    far = smith.restart_positions(np.array([[-30.0, 0.0, 45.0]]), centre, D_MAX, 5.0, 5.0, model)
    np.testing.assert_allclose(far, [[-25.0, 0.0, 45.0]], atol=1e-9)
    # Moved next to the box's side (clearance < 5 m): lifted by 5 m until clear of its top.
    side = smith.restart_positions(np.array([[-10.0, 0.0, 1.0]]), centre, D_MAX, 5.0, 5.0, model)
    step = np.array([10.0, 0.0, 44.0]) / np.hypot(10.0, 44.0) * 5.0
    first = np.array([-10.0, 0.0, 1.0]) + step
    # x = -8.9 m, 3.9 m from the side: one lift leaves it 4.0 m from the top edge, two 7.1 m.
    np.testing.assert_allclose(side, [first + [0.0, 0.0, 10.0]], atol=1e-6)
    assert model.clearance(side)[0] >= 5.0


def test_incremental_updates_equal_a_fresh_objective():
    # A box on the ground seen by 40 random views, with max_rays 6 so that samples overflow their
    # kept rays: after removals, moves and re-additions the incrementally kept rays and h must equal
    # those of an objective built from scratch on the final poses.
    building = trimesh.creation.box(extents=(10.0, 8.0, 6.0))
    building.apply_translation((0.0, 0.0, 3.0))
    proxy = trimesh.util.concatenate([flat_ground(40.0), building])
    points, normals = smith.sample_surface(proxy, 400, 0)
    model = VisibilityModel(proxy, points, normals, CAMERA, VisibilityLimits(0.0, D_MAX, 85.0))
    rng = np.random.default_rng(1)

    def random_views(n):
        eyes = np.column_stack([rng.uniform(-25, 25, n), rng.uniform(-25, 25, n), rng.uniform(8, 30, n)])
        targets = rng.uniform(-4, 4, (n, 3)) + [0.0, 0.0, 3.0]
        return np.array([look_at(e, t).as_array() for e, t in zip(eyes, targets, strict=True)])

    objective = smith.SmithObjective(model, random_views(40), D_MAX, max_rays=6)
    assert (objective.ray_valid.sum(axis=1) == 6).mean() > 0.3  # many samples overflow
    for _ in range(15):
        chosen = rng.choice(40, size=3, replace=False)
        objective.set_active(chosen, False)
        objective.move(chosen, random_views(3))
    objective.set_active(np.array([5, 6]), False)
    fresh = smith.SmithObjective(model, objective.viewpoints, D_MAX, max_rays=6)
    fresh.set_active(np.array([5, 6]), False)
    np.testing.assert_allclose(objective.h, fresh.h, rtol=1e-5, atol=1e-6)
    assert objective.objective() == pytest.approx(fresh.objective(), rel=1e-6)
    kept = [set(row[row >= 0].tolist()) for row in objective.ray_view]
    assert kept == [set(row[row >= 0].tolist()) for row in fresh.ray_view]


def hall(extents=(40.0, 40.0, 30.0)):
    """A closed box on the ground, 40 x 40 x 30 m: inside it, most positions are farther than 5 m from it."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation((0.0, 0.0, extents[2] / 2))
    limits = VisibilityLimits(0, D_MAX, 85)
    return box, VisibilityModel(box, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), CAMERA, limits)


def test_position_penalty_is_the_missing_height_distance_or_depth():
    _, model = hall()
    points = np.array(
        [
            [0.0, 0.0, 10.0],  # inside, 10 m above the floor, 20 m from the sides, 20 m below the roof
            [0.0, 0.0, 27.0],  # inside, 3 m below the roof: within min_distance, missing 2 m
            [0.0, 0.0, 33.0],  # above the roof, 3 m from it: missing 2 m
            [0.0, 0.0, 36.0],  # above the roof, 6 m from it: flyable
            [-30.0, 0.0, 3.0],  # in the open, 10 m from the side but 2 m below min_altitude
        ]
    )
    penalty = smith.position_penalty(points, model, 5.0, 5.0)
    np.testing.assert_allclose(penalty, [10.0, 2.0, 2.0, 0.0, 2.0], atol=1e-5)


def test_a_restart_deep_inside_a_closed_volume_is_lifted_out_of_it():
    # A view 11 m up in the middle of the hall: 11 m from the floor, 19 m from the roof, so clear of
    # the surface by more than min_distance. It moves 5 m towards (0, 0, 45) and is lifted by 5 m
    # while inside (16, 21, 26 m) or within 5 m of the roof (31 m): it ends at 36 m, 6 m above it.
    _, model = hall()
    moved = smith.restart_positions(np.array([[0.0, 0.0, 11.0]]), np.zeros(3), D_MAX, 5.0, 5.0, model)
    np.testing.assert_allclose(moved, [[0.0, 0.0, 36.0]], atol=1e-6)
    assert not model.enclosed(moved)[0]
