"""experiments.depth_errors: ground-truth depth by ray casting, pair angles and error rows."""

from __future__ import annotations

import numpy as np
import trimesh

from experiments.depth_errors import depth_error_row, ground_truth_depth, seen_by, triangulation_angle_deg
from reconstruct.workspace import View
from scene.enclosure import raycasting_scene


def _view(center, rotation, width=64, height=48, f=50.0) -> View:
    rotation = np.asarray(rotation, float)
    K = np.array([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return View("v.png", K, rotation, -rotation @ np.asarray(center, float), width, height)


# A camera looking straight down (camera z = world -z; camera x = world x).
NADIR = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _ground():
    return raycasting_scene(
        trimesh.creation.box(
            extents=(400.0, 400.0, 1.0), transform=trimesh.transformations.translation_matrix((0, 0, -0.5))
        )
    )


def test_ground_truth_depth_of_a_plane_is_the_height_for_a_nadir_view():
    depth, points, normals = ground_truth_depth(_ground(), _view((3.0, -2.0, 20.0), NADIR))
    np.testing.assert_allclose(depth, 20.0, atol=1e-4)
    np.testing.assert_allclose(points[..., 2], 0.0, atol=1e-4)
    np.testing.assert_allclose(np.abs(normals[..., 2]), 1.0, atol=1e-6)


def test_ground_truth_depth_is_along_the_optical_axis_for_a_tilted_view():
    tilt = np.radians(30.0)
    # Nadir turned 30 deg about the world x axis: the axis leans towards +y.
    turn = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    view = _view((0.0, 0.0, 20.0), NADIR @ turn.T, width=65, height=49)  # pixel (24, 32) on the axis
    depth, points, _ = ground_truth_depth(_ground(), view)
    np.testing.assert_allclose(points[..., 2], 0.0, atol=1e-3)
    np.testing.assert_allclose(depth, (points - view.center) @ view.forward, rtol=1e-5)
    # The central ray meets the ground 20 / cos(30 deg) away.
    assert abs(depth[24, 32] - 20.0 / np.cos(tilt)) < 0.05


def test_triangulation_angle_of_two_cameras_over_a_point():
    a, b = _view((-5.0, 0.0, 20.0), NADIR), _view((5.0, 0.0, 20.0), NADIR)
    points = np.zeros((1, 1, 3))
    angle = triangulation_angle_deg(points, a, b, np.ones((1, 1), bool))
    assert abs(angle - np.degrees(2 * np.arctan(5.0 / 20.0))) < 1e-9  # 28.07 deg


def test_error_row_on_constructed_maps():
    gt = np.full((10, 10), 20.0)
    gt[0] = np.nan  # 90 ground-truth pixels
    depth = gt.copy()
    depth[1:4] += 0.10  # 30 pixels 10 cm off
    depth[9] = np.nan  # 10 pixels without depth
    walls = np.zeros((10, 10), bool)
    walls[1:3] = True  # 20 wall pixels, all 10 cm off
    row = depth_error_row(depth, gt, walls)
    assert row["gt_pixels"] == 90 and abs(row["valid_share"] - 80 / 90) < 1e-12
    assert row["n_all"] == 80 and abs(row["over5cm_all"] - 30 / 80) < 1e-12
    assert abs(row["err50_all_m"]) < 1e-9 and abs(row["err90_all_m"] - 0.10) < 1e-6
    assert row["n_walls"] == 20 and abs(row["err50_walls_m"] - 0.10) < 1e-6 and row["over5cm_walls"] == 1.0
    assert row["valid_share_walls"] == 1.0  # every wall pixel with a ground truth has a depth


def test_seen_by_a_partner_is_the_shared_footprint_less_what_it_sees_occluded():
    scene = _ground()
    ref = _view((0.0, 0.0, 20.0), NADIR)
    ref_gt, points, _ = ground_truth_depth(scene, ref)
    has_gt = np.isfinite(ref_gt)
    # 64 px at f = 50 and 20 m cover 25.6 m of ground; a partner 12.8 m along x sees half of it.
    src = _view((12.8, 0.0, 20.0), NADIR)
    seen = seen_by(points, has_gt, src, ground_truth_depth(scene, src)[0])
    assert seen[:, 32:].all() and not seen[:, :32].any()
    # The same partner whose ground-truth depth says something stands 1 m in front everywhere.
    blocked = seen_by(points, has_gt, src, ground_truth_depth(scene, src)[0] - 1.0)
    assert not blocked.any()
