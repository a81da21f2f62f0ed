"""The dense stage rewards redundancy: the oracle's depth, its noise model, edge filtering and the
fusion along rays on a box world whose views all have the same quality."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from reconstruct.dense import fuse
from reconstruct.dense_settings import FusionSettings, SgbmSettings
from reconstruct.depth_filter import edge_pixels, geometric_support
from reconstruct.fusion_support import supported_points
from reconstruct.oracle import oracle_view
from reconstruct.stereo.matching import normals_from_depth
from reconstruct.stereo_noise import stereo_depth_sigma
from reconstruct.workspace import View, write_maps
from scene.camera import Intrinsics, cam_from_world, look_at
from scene.enclosure import raycasting_scene
from tests.test_reconstruct import box_world_mesh, dense_settings, reconstruct_cfg
from tests.workspaces import shared_point_model

INTR = Intrinsics(320, 240, 60.0)


def opencv_view(name: str, viewpoint) -> View:
    K = INTR.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    rot, t = cam_from_world(np.asarray(viewpoint, float))
    return View(name, K, rot, t, INTR.width, INTR.height)


# ----------------------------------------------------------------------------- the oracle


GROUND = trimesh.Trimesh(
    [[-200, -200, 0], [200, -200, 0], [200, 200, 0], [-200, 200, 0]], [[0, 1, 2], [0, 2, 3]]
)


def oracle_of_ground(view: View, baseline_m: float, sigma_px: float, seed: int = 0):
    """The oracle's depth and normals of the ground plane z = 0 seen by ``view``."""
    return oracle_view(
        raycasting_scene(GROUND),
        view.center,
        view.K,
        view.rotation,
        (view.width, view.height),
        baseline_m,
        sigma_px,
        np.random.default_rng(seed),
    )


def test_the_oracle_depth_of_a_plane_is_the_analytic_depth():
    """The ground plane z = 0 seen from 20 m at a 45 deg pitch: depth z(v) along the axis."""
    view = opencv_view("a", [0.0, 0.0, 20.0, 90.0, -45.0])
    depth, normals = oracle_of_ground(view, 1.0, 0.0)
    u, v = np.meshgrid(np.arange(view.width, dtype=float), np.arange(view.height, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view.K).T @ view.rotation
    truth = -view.center[2] / rays[..., 2]  # rays have unit camera depth: t is the depth
    hit = truth > 0
    assert np.isfinite(depth[hit]).all() and np.isnan(depth[~hit]).all()
    np.testing.assert_allclose(depth[hit], truth[hit], rtol=1e-5)
    # The plane's normal +z in the camera frame, facing the camera: R @ (0, 0, 1) (pointing up, at it).
    np.testing.assert_allclose(
        normals[hit], np.broadcast_to(view.rotation[:, 2], normals[hit].shape), atol=1e-6
    )


def test_the_oracle_noise_is_the_stereo_model_sigma():
    """Nadir over a plane 20 m below, baseline 2 m, 0.5 px: sigma_z = 20^2 / (277.13 x 2) x 0.5 m."""
    view = opencv_view("a", [0.0, 0.0, 20.0, 90.0, -90.0])
    f = 0.5 * 320 / math.tan(math.radians(30.0))
    assert f == pytest.approx(277.128, abs=1e-3)
    hand = 20.0**2 / (f * 2.0) * 0.5
    assert hand == pytest.approx(0.36084, abs=1e-5)
    assert stereo_depth_sigma(20.0, f, 2.0, 0.5) == pytest.approx(hand)
    depth, _ = oracle_of_ground(view, 2.0, 0.5, seed=1)
    residual = depth - 20.0  # a nadir view of a level plane: every pixel's depth is the height
    assert np.std(residual) == pytest.approx(hand, rel=0.01)
    assert abs(np.mean(residual)) < 0.01


def test_the_oracle_without_a_ground_truth_is_refused_before_any_work(tmp_path):
    from reconstruct.dense import dense_reconstruct

    settings = dense_settings(**{"dense.backend": "oracle"})
    with pytest.raises(ValueError, match="backend=oracle needs the ground truth"):
        dense_reconstruct(tmp_path / "sparse", tmp_path / "images", tmp_path / "out", settings)
    assert not (tmp_path / "out").exists()


def test_the_dense_stage_refuses_a_raw_config_mapping(tmp_path):
    from reconstruct.dense import dense_reconstruct

    cfg = reconstruct_cfg().dense
    with pytest.raises(TypeError, match=r"DenseSettings\.from_config"):
        dense_reconstruct(tmp_path / "sparse", tmp_path / "images", tmp_path / "out", cfg)
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- redundancy


def fattened(depth: np.ndarray, px: int) -> np.ndarray:
    """Block matching's foreground fattening: background pixels within ``px`` of a nearer surface
    (5 % nearer) take its depth."""
    near = cv2.erode(
        np.where(np.isfinite(depth), depth, np.inf).astype(np.float32), np.ones((2 * px + 1,) * 2, np.uint8)
    )
    out = depth.copy()
    grow = np.isfinite(near) & (near < 0.95 * np.nan_to_num(depth, nan=np.inf))
    out[grow] = near[grow]
    return out


def box_flight(n_views: int) -> list[View]:
    """``n_views`` views 12 m from the box world's centre, 7 m up, spread over the same 70 deg arc."""
    angles = np.radians(np.linspace(-35.0, 35.0, n_views)) - np.pi / 2
    return [
        opencv_view(
            f"{i:06d}.png", look_at([12 * np.cos(a), 12 * np.sin(a), 7.0], [0.0, 0.0, 2.0]).as_array()
        )
        for i, a in enumerate(angles)
    ]


def fused_error_p90(tmp_path: Path, n_views: int, edge_margin: int, method: str) -> float:
    """90th percentile distance (m) of the fused cloud to the true boxes: views of one quality
    (oracle depth, 0.05 px at a 3 m baseline, 3 px fattening), ``edge_margin`` filtering, fusion
    ``method``."""
    mesh = box_world_mesh()
    workspace = tmp_path / f"ws_{n_views}_{edge_margin}_{method}"
    shutil.rmtree(workspace, ignore_errors=True)
    (workspace / "images").mkdir(parents=True)
    views = box_flight(n_views)
    points = trimesh.sample.sample_surface(mesh, 3000, seed=1)[0]
    points = points[(np.abs(points[:, 0]) < 6) & (np.abs(points[:, 1]) < 6)]
    rec = shared_point_model(
        [v.name for v in views], [v.rotation for v in views], [v.translation for v in views], points, INTR
    )
    (workspace / "sparse").mkdir()
    rec.write(workspace / "sparse")
    scene = raycasting_scene(mesh)
    rng = np.random.default_rng(0)
    for view in views:
        cv2.imwrite(
            str(workspace / "images" / view.name), np.full((INTR.height, INTR.width, 3), 128, np.uint8)
        )
        depth, _ = oracle_view(
            scene, view.center, view.K, view.rotation, (view.width, view.height), 3.0, 0.05, rng
        )
        depth = fattened(depth, 3)
        depth[edge_pixels(depth, edge_margin)] = np.nan
        write_maps(workspace, view.name, depth, normals_from_depth(depth, view.K, 5))
    settings = dense_settings(**{"dense.fusion.method": method})
    fuse(workspace, workspace / "fused.ply", settings, [v.name for v in views], deterministic=True)
    cloud = trimesh.load(workspace / "fused.ply").vertices
    sample = cloud[np.random.default_rng(0).choice(len(cloud), min(len(cloud), 20000), replace=False)]
    return float(np.percentile(trimesh.proximity.closest_point(mesh, sample)[1], 90))


def test_coordinate_median_fusion_gets_worse_as_views_are_added(tmp_path):
    """The former stage: COLMAP fusion of fattened maps, 3 then 12 views of the same quality."""
    few, many = fused_error_p90(tmp_path, 3, 0, "colmap"), fused_error_p90(tmp_path, 12, 0, "colmap")
    assert few == pytest.approx(0.0220, abs=0.002)
    assert many == pytest.approx(0.0392, abs=0.003)


def test_edge_filtered_ray_fusion_gets_no_worse_as_views_are_added(tmp_path):
    few, mid, many = (fused_error_p90(tmp_path, n, 3, "rays") for n in (3, 6, 12))
    assert few == pytest.approx(0.0051, abs=0.001)
    assert many <= mid <= few  # 5.1, 4.9, 4.1 mm when measured
    assert many == pytest.approx(0.0041, abs=0.001)


# ----------------------------------------------------------------------------- filters


def test_edge_pixels_lie_within_the_margin_of_a_depth_jump():
    depth = np.full((20, 30), 10.0, np.float32)
    depth[:, 15:] = 12.0  # a 20 % jump between columns 14 and 15
    edge = edge_pixels(depth, 2)
    assert edge[:, 13:17].all() and not edge[:, :13].any() and not edge[:, 17:].any()
    assert not edge_pixels(depth, 0).any()
    small = np.full((20, 30), 10.0, np.float32)
    small[:, 15:] = 10.3  # 3 %: a slanted surface, not an occlusion edge
    assert not edge_pixels(small, 2).any()


def test_geometric_support_counts_the_views_that_measured_the_point():
    views = [opencv_view(str(i), [x, 0.0, 20.0, 90.0, -90.0]) for i, x in enumerate((0.0, 2.0, 4.0))]
    maps = [oracle_of_ground(v, 1.0, 0.0)[0] for v in views]
    wrong = maps[2] * 1.05  # the third view measured 5 % too far everywhere
    support = geometric_support(views[0], maps[0], [(views[1], maps[1]), (views[2], wrong)], 0.01)
    seen_by_1 = np.isfinite(maps[0])
    assert support.max() == 1  # the second view agrees where it sees the point, the third never does
    assert support[seen_by_1].mean() > 0.8


def test_the_support_filter_drops_weakly_supported_points_beside_strong_ones():
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [1.0, 0.0, 0.0], [1.01, 0.0, 0.0]])
    support = np.array([12, 3, 3, 2])
    keep = supported_points(points, support, 0.03, 0.5)
    # 3 of a neighbour's 12 is dropped; a sparse flight's 3 and 2 views (no better neighbour) stay.
    assert keep.tolist() == [True, False, True, True]
    assert supported_points(points, support, 0.03, 0.0).all()


def test_the_conditioning_filter_keeps_a_plane_as_accurate_when_poor_views_are_added():
    """A plane z = 0 measured by good views (depth sigma 1 cm) over x in [0, 2) m, and poor ones
    (6 cm: far or narrow-baseline) over x in [0, 3) m; each point's error is its sigma times a
    normal draw. Without the filter the poor views' points raise the 90th percentile from 1.64 cm
    (1.645 sigma) to 8.3 cm (0.6 P(|N| > t / 6 cm) = 0.1: t = 1.383 x 6 cm); with it (ratio 2,
    10 cm cells) the poor points within a cell of good ones go, those where no good view reached
    stay, and the good views' area is as accurate as they made it."""
    from reconstruct.fusion_rays import well_conditioned

    rng = np.random.default_rng(0)

    def plane_points(n, x_max, sigma):
        xy = rng.uniform([0.0, 0.0], [x_max, 1.0], (n, 2))
        return np.column_stack([xy, sigma * rng.standard_normal(n)]), np.full(n, sigma)

    good, good_sigma = plane_points(20000, 2.0, 0.01)
    poor, poor_sigma = plane_points(30000, 3.0, 0.06)
    cloud = {
        "points": np.vstack([good, poor]),
        "depth_sigma": np.concatenate([good_sigma, poor_sigma]),
        "support": np.full(50000, 3),
    }

    def p90(points):
        return float(np.percentile(np.abs(points[:, 2]), 90))

    assert p90(good) == pytest.approx(0.0164, abs=0.001)
    assert p90(cloud["points"]) == pytest.approx(0.0830, abs=0.002)
    kept = well_conditioned(cloud, 0.1, 2.0)
    where_good = kept["points"][:, 0] < 2.0
    # Poor points left there: only those more than 20 cm off (beyond the good cells' neighbours).
    far_off = (poor[:, 0] < 2.0) & (np.abs(poor[:, 2]) >= 0.2)
    assert where_good.sum() - len(good) == far_off.sum()
    assert p90(kept["points"][where_good]) == pytest.approx(p90(good), abs=5e-4)
    # Beyond x = 2.1 m (a cell past the good views' reach) only poor views measured: all kept.
    beyond = kept["points"][:, 0] >= 2.1
    assert beyond.sum() == (poor[:, 0] >= 2.1).sum()
    assert well_conditioned(cloud, 0.1, 0.0)["points"].shape == (50000, 3)


# ----------------------------------------------------------------------------- the normal tolerance


def fused_points_with_one_tilted_normal_map(tmp_path: Path, max_normal_error: float, tilt_deg: float) -> int:
    """Points fused from four nadir views 1 m apart at 20 m over the ground (exact oracle depth), the
    last view's normals turned ``tilt_deg`` about its x axis (SGBM's depth-derived normals are that
    far off on slanted walls), with ``fusion.max_normal_error`` and three views per point."""
    workspace = tmp_path / f"ws_{max_normal_error}_{tilt_deg}"
    (workspace / "images").mkdir(parents=True)
    positions = (-1.5, -0.5, 0.5, 1.5)
    views = [opencv_view(f"{i:06d}.png", [x, 0.0, 20.0, 90.0, -90.0]) for i, x in enumerate(positions)]
    points = np.random.default_rng(0).uniform([-5.0, -5.0, 0.0], [5.0, 5.0, 0.0], (50, 3))
    rec = shared_point_model(
        [v.name for v in views], [v.rotation for v in views], [v.translation for v in views], points, INTR
    )
    (workspace / "sparse").mkdir()
    rec.write(workspace / "sparse")
    t = math.radians(tilt_deg)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
    for i, view in enumerate(views):
        cv2.imwrite(
            str(workspace / "images" / view.name), np.full((INTR.height, INTR.width, 3), 128, np.uint8)
        )
        depth, normals = oracle_of_ground(view, 1.0, 0.0)
        if i == len(views) - 1:
            normals = normals @ turn.T
        write_maps(workspace, view.name, depth, normals)
    settings = dense_settings(
        **{"dense.fusion.max_normal_error": max_normal_error, "dense.fusion.conditioning_ratio": 0.0}
    )
    return fuse(workspace, workspace / "fused.ply", settings, [v.name for v in views], deterministic=True)


def test_normals_off_by_20_deg_confirm_each_other_at_the_default_tolerance(tmp_path):
    # One point a ground pixel seen by three views. At 20 m a metre is f / 20 = 13.86 px: three of
    # the four views share 320 - 13.86 columns, three adjacent ones 320 - 27.7, of 240 rows.
    exact = fused_points_with_one_tilted_normal_map(tmp_path, 30.0, 0.0)
    assert exact == pytest.approx(240 * (320 - 13.86), rel=0.005)
    assert fused_points_with_one_tilted_normal_map(tmp_path, 30.0, 20.0) == exact
    # COLMAP's 10 deg: the tilted view confirms nothing, so only the first three views' common
    # footprint is fused.
    colmap = fused_points_with_one_tilted_normal_map(tmp_path, 10.0, 20.0)
    assert colmap == pytest.approx(240 * (320 - 27.7), rel=0.005)


# ----------------------------------------------------------------------------- slanted surfaces


def test_the_slant_sigma_is_the_window_depth_spread():
    """A 3 px window at 20 m, f 1000 px, on a surface 60 deg to the ray: 3 x 20 / 1000 x tan 60."""
    from reconstruct.stereo_noise import slant_depth_sigma

    assert slant_depth_sigma(20.0, 1000.0, 0.5, 3.0) == pytest.approx(0.06 * math.sqrt(3.0), rel=1e-12)
    assert slant_depth_sigma(20.0, 1000.0, 1.0, 3.0) == 0.0
    # Past 84 deg the tangent plane is not trusted: the spread stops at tan(acos 0.1) = 9.95.
    assert slant_depth_sigma(20.0, 1000.0, 0.0, 3.0) == pytest.approx(0.06 * math.sqrt(0.99) / 0.1)


# Fusion along rays with 12 neighbours, three views a point, 1 % depth and 30 deg normal tolerance;
# no slant term, no gate (max_reproj_error is COLMAP's fusion's only).
RAY_FUSION = FusionSettings(
    min_num_pixels=3, max_reproj_error=2.0, max_depth_error=0.01, max_normal_error=30.0, ray_neighbours=12
)


def fused_height_error_of_a_grazing_pixel(tmp_path: Path, slant_px: float) -> tuple[float, float]:
    """A grazing view of the ground (6 m up, 20 deg down, its depth 0.5 % long) and three nadir views
    20 m up, exact; the ground point under the grazing view's pixel (160, 120) is fused along that
    pixel's ray. Returns the fused point's height (m) and the one the weights predict by hand."""
    from reconstruct.fusion_rays import fuse_along_rays

    workspace = tmp_path / f"slant_{slant_px}"
    grazing = opencv_view("000000.png", [-20.0, 0.0, 6.0, 0.0, -20.0])
    nadirs = [
        opencv_view(f"00000{i + 1}.png", [x, 0.0, 20.0, 90.0, -90.0])
        for i, x in enumerate((-4.0, -3.0, -2.0))
    ]
    views = {v.name: v for v in [grazing, *nadirs]}
    for view in views.values():
        depth, normals = oracle_of_ground(view, 1.0, 0.0)
        write_maps(workspace, view.name, depth * (1.005 if view is grazing else 1.0), normals)
    names = sorted(views)
    neighbours = {n: [m for m in names if m != n] for n in names}
    fusion = dataclasses.replace(RAY_FUSION, slant_window_px=slant_px)
    cloud = fuse_along_rays(workspace, names, views, neighbours, dict.fromkeys(names, 5.0), fusion)
    ray = np.array([160.0, 120.0, 1.0]) @ np.linalg.inv(grazing.K).T @ grazing.rotation
    t_true = -grazing.center[2] / ray[2]
    truth = grazing.center + t_true * ray
    direction = (cloud["points"] - grazing.center) / np.linalg.norm(cloud["points"] - grazing.center, axis=1)[
        :, None
    ]
    fused = cloud["points"][np.argmax(direction @ (ray / np.linalg.norm(ray)))]
    # By hand: precision 1 / ((z^2 / (f B))^2 + (w z tan(theta) / f)^2) at B = 5 m, z the depth the
    # view measured: the grazing view t_true x 1.005; each nadir view exactly 20 m, from its own
    # angle to the point.
    f = grazing.K[0, 0]

    def precision(z, cos):
        return 1.0 / ((z * z / (f * 5.0)) ** 2 + (slant_px * z / f * math.sqrt(1 - cos * cos) / cos) ** 2)

    cos_grazing = abs(ray[2]) / np.linalg.norm(ray)
    w_grazing = precision(1.005 * t_true, cos_grazing)
    w_nadirs = sum(precision(20.0, 20.0 / np.linalg.norm(truth - v.center)) for v in nadirs)
    share = w_grazing / (w_grazing + w_nadirs)
    hand_height = 0.005 * t_true * share * ray[2]
    return float(fused[2]), float(hand_height)


def test_a_grazing_view_weighs_less_on_the_ground_with_the_slant_term(tmp_path):
    # Without the term the grazing view, nearer (17.5 against 20 m), outweighs each nadir view
    # (precision ~ z^-4): 1.69 of 4.69; its 0.5 % error (8.8 cm along the ray) leaves the point
    # 1.08 cm under the ground. A 3 px window spreads its depth by 3 x 17.5 / 277 x tan 70 = 52 cm
    # against the stereo model's 22 cm, so it weighs 0.08 of the whole and the point is 0.24 cm under.
    former, former_hand = fused_height_error_of_a_grazing_pixel(tmp_path, 0.0)
    slant, slant_hand = fused_height_error_of_a_grazing_pixel(tmp_path, 3.0)
    assert former == pytest.approx(former_hand, rel=0.01, abs=2e-5)
    assert slant == pytest.approx(slant_hand, rel=0.01, abs=2e-5)
    assert former_hand == pytest.approx(-0.0108, abs=0.0001)
    assert slant_hand == pytest.approx(-0.0024, abs=0.0001)


def fused_height_with_one_long_view(tmp_path: Path, gate_px: float) -> float:
    """Five nadir views 20 m up, 1 m apart; the fourth measured the ground 0.8 % long (16 cm, inside
    fusion's 1 % band), the others exactly. Returns the height (m) of the point fused on the first
    view's centre pixel, each view's stereo baseline 50 m (sigma 2.9 cm at one pixel)."""
    from reconstruct.fusion_rays import fuse_along_rays

    workspace = tmp_path / f"gate_{gate_px}"
    views = {
        v.name: v
        for v in (opencv_view(f"00000{i}.png", [float(i), 0.0, 20.0, 90.0, -90.0]) for i in range(5))
    }
    for i, view in enumerate(views.values()):
        depth, normals = oracle_of_ground(view, 1.0, 0.0)
        write_maps(workspace, view.name, depth * (1.008 if i == 3 else 1.0), normals)
    names = sorted(views)
    neighbours = {n: [m for m in names if m != n] for n in names}
    fusion = dataclasses.replace(RAY_FUSION, gate_disparity_px=gate_px)
    cloud = fuse_along_rays(workspace, names, views, neighbours, dict.fromkeys(names, 50.0), fusion)
    reference = views[names[0]]
    ray = np.array([160.0, 120.0, 1.0]) @ np.linalg.inv(reference.K).T @ reference.rotation
    direction = cloud["points"] - reference.center
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    return float(cloud["points"][np.argmax(direction @ (ray / np.linalg.norm(ray))), 2])


def test_the_gate_drops_a_measurement_many_sigmas_from_the_fused_depth(tmp_path):
    # The long view's point lies 16 cm under the ground (nadir: depth x 1.008 at 20 m), and so does
    # its tangent plane. Weighted by (f B / z^2)^2, it counts 1.008^-4 of an exact view: without the
    # gate the point sits 16 cm x w / (4 + w) under the ground. Its first fused depth is ~3.2 cm
    # long: the exact views are 1.1 sigma from it, the long one 4.4 sigma. A 3 px gate drops the
    # long one, and the point is fused from the exact four.
    w = 1.008**-4
    assert fused_height_with_one_long_view(tmp_path, 0.0) == pytest.approx(-0.16 * w / (4 + w), rel=0.01)
    assert fused_height_with_one_long_view(tmp_path, 3.0) == pytest.approx(0.0, abs=1e-6)
    # A gate wider than the long view's 4.4 sigma keeps it.
    assert fused_height_with_one_long_view(tmp_path, 5.0) == pytest.approx(-0.16 * w / (4 + w), rel=0.01)


def test_the_oracle_is_fused_by_the_stereo_model_alone():
    # Its depth has the stereo model's noise only, and no matching window: no slant term.
    from reconstruct.dense import fusion_config

    settings = dense_settings(**{"dense.fusion.slant_window_px": 3.0})
    oracle = fusion_config("oracle", settings)
    assert oracle.fusion.slant_window_px == 0.0
    assert dataclasses.replace(oracle.fusion, slant_window_px=3.0) == settings.fusion
    assert dataclasses.replace(oracle, fusion=settings.fusion) == settings
    assert fusion_config("cpu", settings) is settings


# ----------------------------------------------------------------------------- writing the cloud


def test_a_cloud_the_disk_cannot_hold_leaves_no_file(tmp_path, monkeypatch):
    import collections

    import open3d as o3d

    from reconstruct import dense

    rng = np.random.default_rng(0)
    cloud = {"points": rng.normal(size=(1000, 3)), "normals": np.tile([0.0, 0.0, 1.0], (1000, 1))}
    cloud["colors"] = np.full((1000, 3), 0.5)
    written = tmp_path / "dense.ply"
    assert dense._write_cloud(written, cloud, None) == 1000
    # 51 bytes a point (six doubles, three bytes) and Open3D's header.
    assert 1000 * 51 < written.stat().st_size < 1000 * 51 + 400
    # Too little room: refused before writing.
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(dense.shutil, "disk_usage", lambda _: usage(10**9, 10**9 - 20_000, 20_000))
    with pytest.raises(OSError, match=r"full\.ply: the fused cloud needs 0\.00 GB, the disk has 0\.00 GB"):
        dense._write_cloud(tmp_path / "full.ply", cloud, None)
    assert not (tmp_path / "full.ply").exists()
    monkeypatch.undo()

    # Open3D reports success on a file a full disk cut short: removed and refused.
    def short_write(path, _cloud):
        Path(path).write_bytes(b"ply\n" + b"\0" * 100)
        return True

    monkeypatch.setattr(o3d.io, "write_point_cloud", short_write)
    with pytest.raises(OSError, match=r"short\.ply: wrote 104 bytes of the fused cloud's 51000"):
        dense._write_cloud(tmp_path / "short.ply", cloud, None)
    assert not (tmp_path / "short.ply").exists()


# ----------------------------------------------------------------------------- SGBM's scan direction


# The back-end's SGBM settings (conf/reconstruct/default.yaml) with OpenCV's P1 and P2.
SGBM = SgbmSettings(
    block_size=5,
    disp12_max_diff=1,
    uniqueness_ratio=10,
    speckle_window_size=100,
    speckle_range=2,
    p1_per_block_pixel=8.0,
    p2_per_block_pixel=32.0,
)


def slanted_pair_disparity_error(gradient_px_per_row: float, mirror_pass: bool) -> float:
    """Median disparity error (px) of SGBM (3-way, the back-end's parameters) on a rectified pair of
    a textured surface whose disparity is 30 px at mid-height and changes by ``gradient`` a row."""
    from reconstruct.stereo.matching import sgbm_disparity, sgbm_matcher

    rng = np.random.default_rng(0)
    height, width = 240, 320
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (height, width + 200)).astype(np.float32), (0, 0), 1.2)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    rows = np.arange(height, dtype=np.float32)
    truth = 30.0 + gradient_px_per_row * (rows - height / 2)
    left = texture[:, 100 : 100 + width].astype(np.uint8)
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), rows)
    right = cv2.remap(texture, xs + 100 + truth[:, None], ys, cv2.INTER_LINEAR).astype(np.uint8)
    disparity = sgbm_disparity(sgbm_matcher(SGBM, 64), left, right, mirror_pass)
    matched = disparity >= 0
    matched[:, :80] = False  # SGBM leaves the first numDisparities columns unmatched
    return float(np.median((disparity - truth[:, None])[matched]))


def test_the_mirror_pass_takes_out_the_bias_of_the_scan_direction():
    # One pass: the surface's disparity is read late down the image, one way when it grows, the
    # other when it shrinks (-0.06 and +0.13 px at 0.2 px a row). Upside down too, the two agree.
    down, up = slanted_pair_disparity_error(0.2, False), slanted_pair_disparity_error(-0.2, False)
    assert down < -0.05 and up > 0.1
    down, up = slanted_pair_disparity_error(0.2, True), slanted_pair_disparity_error(-0.2, True)
    assert abs(down - up) < 0.01
    assert abs(down) < 0.04 and abs(up) < 0.04
    # A surface level with the image: nothing to lag behind, exact either way.
    assert slanted_pair_disparity_error(0.0, False) == 0.0
    assert slanted_pair_disparity_error(0.0, True) == 0.0


def foreshortened_pair_held(gradient: float, p1_per_block_pixel: float) -> float:
    """Share of a rectified pair's pixels SGBM (both passes) matches within 0.5 px, on a faint, noisy
    texture (20 grey levels, noise 2) whose disparity grows by ``gradient`` px a px along the rows:
    the partner sees the surface foreshortened by 1 - gradient (it stands nearer to it)."""
    from reconstruct.stereo.matching import sgbm_disparity, sgbm_matcher

    rng = np.random.default_rng(0)
    height, width = 240, 320
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (height, width + 400)).astype(np.float32), (0, 0), 1.2)
    texture = cv2.normalize(texture, None, 100, 120, cv2.NORM_MINMAX)
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    truth = 20.0 + gradient * xs  # disparity of left pixel x: the right image shows it at x - truth

    def noisy(image):
        return np.clip(image + rng.normal(0.0, 2.0, image.shape), 0, 255).astype(np.uint8)

    left = noisy(texture[:, 100 : 100 + width])
    right = noisy(cv2.remap(texture, (xs + 20.0) / (1.0 - gradient) + 100, ys, cv2.INTER_LINEAR))
    settings = dataclasses.replace(SGBM, p1_per_block_pixel=p1_per_block_pixel)
    disparity = sgbm_disparity(sgbm_matcher(settings, 128), left, right, True)
    matched = np.zeros(disparity.shape, bool)
    matched[:, 140:] = True  # past the unmatched first numDisparities columns and the largest shift
    return float(np.mean(np.abs(disparity - truth)[matched] <= 0.5))


def test_a_smaller_p1_holds_a_foreshortened_surface_and_loses_a_level_one():
    # OpenCV's P1 (8 a block pixel) charges every one-px disparity step: at 0.4 px a px it holds
    # 13 % of the faint surface, a tenth of it 45 %. Seen alike by both views (0 px a px), the
    # smaller P1 lets the noise through: 98 -> 78 %.
    assert foreshortened_pair_held(0.4, 8.0) == pytest.approx(0.131, abs=0.005)
    assert foreshortened_pair_held(0.4, 0.8) == pytest.approx(0.452, abs=0.005)
    assert foreshortened_pair_held(0.0, 8.0) == pytest.approx(0.976, abs=0.005)
    assert foreshortened_pair_held(0.0, 0.8) == pytest.approx(0.783, abs=0.005)
