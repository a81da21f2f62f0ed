"""Reconstruction stage: SfM with GNSS priors, alignment, CPU stereo + fusion, proxy, caching, failure.

The test flight is ray-cast here (textured axis-aligned boxes on a textured ground plane), so the
tests depend on nothing but numpy/OpenCV and the reconstruction package itself.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pycolmap
import pytest
import trimesh
from omegaconf import OmegaConf

from reconstruct.align import align_to_gnss, deregister_gnss_outliers, merge_model, pose_errors
from reconstruct.cache_keys import flight_content_key
from reconstruct.dense import fuse, fusion_budget_gb, fusion_chunk_size
from reconstruct.dense_settings import DenseSettings
from reconstruct.errors import ReconstructionError
from reconstruct.flight import Flight, read_flight, simulate_gnss
from reconstruct.fusion_chunks import owning_chunk, plan_chunks, read_visibility
from reconstruct.pipeline import build_proxy, reconstruct_flight
from reconstruct.proxy import degraded_ground_truth, oriented_cloud, poisson_proxy
from reconstruct.rectify import RectifiedPair, rectify_pair
from reconstruct.settings import ReconstructSettings, proxy_flight_config
from reconstruct.sfm import map_reconstruction, pose_prior_pairs, sfm_options, write_pose_priors
from reconstruct.sfm_settings import COLMAP_ABS_POSE, COLMAP_LOCAL_BA, SfmSettings
from reconstruct.stereo.depth_maps import reference_views
from reconstruct.stereo.matching import (
    consistent_depth,
    disparity_search_range,
    matchable_window,
    normals_from_depth,
    pair_depth,
    textured_pixels,
)
from reconstruct.timing import stage_time
from reconstruct.workspace import View, prepare_workspace, select_partners, write_maps
from scene.base import Box, MeshPart, Scene
from scene.camera import Intrinsics, cam_from_world, look_at
from tests.workspaces import shared_point_model

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "conf" / "reconstruct" / "default.yaml"


def reconstruct_cfg(**overrides):
    """The default ``reconstruct`` config with dotted-key overrides."""
    cfg = OmegaConf.load(CONFIG)
    for key, value in overrides.items():
        OmegaConf.update(cfg, key, value, merge=False)
    return cfg


def exploration_values(cfg) -> dict:
    """The exploratory flight's ``reconstruct`` values (``proxy_flight_config`` of the plain mapping)."""
    return proxy_flight_config(OmegaConf.to_container(cfg, resolve=True))


def recon_settings(cfg) -> ReconstructSettings:
    """A ``reconstruct`` mapping typed as the stage takes it."""
    return ReconstructSettings.from_config(cfg)


def sfm_settings(cfg) -> SfmSettings:
    """The ``sfm`` block of a ``reconstruct`` mapping, typed."""
    return SfmSettings.from_config(cfg.sfm)


def dense_settings(**overrides) -> DenseSettings:
    """The default ``reconstruct.dense`` settings, typed, with ``reconstruct_cfg``'s dotted-key overrides."""
    return DenseSettings.from_config(reconstruct_cfg(**overrides).dense)


# ----------------------------------------------------------------------------- a ray-cast box world

GROUND_HALF_SIZE_M = 20.0


def noise_texture(size: int, seed: int) -> np.ndarray:
    """(size, size) float32 texture in [0, 1]: band-limited noise summed over octaves (tileable)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size), np.float32)
    for octave, weight in ((4, 1.0), (8, 0.7), (16, 0.5), (32, 0.35), (64, 0.25), (128, 0.2)):
        coarse = rng.random((octave, octave)).astype(np.float32)
        tiled = np.tile(coarse, (3, 3))
        big = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        out += weight * big[size : 2 * size, size : 2 * size]
    out -= out.min()
    return out / out.max()


def raycast_box_world(boxes, texture, texel_m, rot, t, intr: Intrinsics) -> np.ndarray:
    """Render a grey image (H, W) uint8 of textured boxes on a textured ground plane z = 0.

    Args:
        boxes: list of (lo (3,), hi (3,)) axis-aligned boxes in metres.
        texture: (S, S) float texture in [0, 1], tiled over every face.
        texel_m: texture texel size in metres.
        rot, t: COLMAP cam_from_world.
        intr: the camera.
    """
    h, w = intr.height, intr.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays_cam = np.stack([(u - intr.cx) / intr.focal_px, (v - intr.cy) / intr.focal_px, np.ones_like(u)], -1)
    dirs = rays_cam.reshape(-1, 3) @ rot  # world directions = R^T d
    origin = -rot.T @ t
    best_t = np.full(len(dirs), np.inf)
    coords = np.zeros((len(dirs), 2))
    shade = np.zeros(len(dirs))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = -origin[2] / dirs[:, 2]
    hit = (t_ground > 0) & np.isfinite(t_ground)
    p = origin + t_ground[:, None] * dirs
    hit &= np.all(np.abs(p[:, :2]) <= GROUND_HALF_SIZE_M, axis=1)
    best_t[hit] = t_ground[hit]
    coords[hit] = p[hit][:, :2]
    shade[hit] = 0.8
    face_shade = np.array([0.65, 0.9, 0.75, 0.55, 0.6, 1.0])  # -x, +x, -y, +y, -z, +z
    for k, (lo, hi) in enumerate(boxes):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - origin) / dirs
            t2 = (hi - origin) / dirs
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        axis = np.nanargmax(np.minimum(t1, t2), axis=1)
        ok = (tmax >= tmin) & (tmin > 0) & (tmin < best_t)
        if not ok.any():
            continue
        p = origin + tmin[ok, None] * dirs[ok]
        ax = axis[ok]
        side = dirs[ok, ax] > 0  # entering through the low face when moving in +axis
        uv_axes = np.array([[1, 2], [0, 2], [0, 1]])[ax]
        offset = 3.7 * k + 1.3 * ax
        coords[ok] = np.take_along_axis(p, uv_axes, axis=1) + offset[:, None]
        shade[ok] = face_shade[2 * ax + (~side).astype(int)]
        best_t[ok] = tmin[ok]
    size = texture.shape[0]
    tex_uv = (coords / texel_m) % size
    sampled = cv2.remap(
        texture,
        tex_uv[:, 0].reshape(h, w).astype(np.float32),
        tex_uv[:, 1].reshape(h, w).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    ).reshape(-1)
    value = np.where(np.isfinite(best_t), (0.15 + 0.85 * sampled) * shade, 0.55)
    return np.clip(value * 255.0, 0, 255).astype(np.uint8).reshape(h, w)


def ring_viewpoints(
    n_ring: int, radius: float, height: float, target, n_nadir_side: int, nadir_height: float
):
    """Viewpoints (V, 5): a ring aimed at ``target`` plus a nadir grid (metres, degrees)."""
    rows = []
    for a in np.linspace(0.0, 2 * np.pi, n_ring, endpoint=False):
        rows.append(look_at([radius * np.cos(a), radius * np.sin(a), height], target).as_array())
    for x in np.linspace(-4.0, 4.0, n_nadir_side):
        for y in np.linspace(-4.0, 4.0, n_nadir_side):
            rows.append([x, y, nadir_height, 90.0, -90.0])
    return np.array(rows)


BOXES = [((-3.0, -2.0, 0.0), (3.0, 2.0, 3.0)), ((-1.0, -1.0, 3.0), (1.5, 1.0, 4.5))]


def write_box_world_flight(image_dir: Path, viewpoints: np.ndarray, intr: Intrinsics, seed=0) -> Path:
    """Ray-cast the box world from ``viewpoints`` into ``image_dir`` in the renderer's format.

    ``seed`` is the texture's seed, one for all views or one per view (views of different seeds
    see differently painted worlds of the same shape and share no image content).
    """
    image_dir.mkdir(parents=True, exist_ok=True)
    seeds = np.broadcast_to(np.asarray(seed), (len(viewpoints),))
    textures = {int(s): noise_texture(1024, int(s)) for s in np.unique(seeds)}
    images = []
    for i, vp in enumerate(viewpoints):
        rot, t = cam_from_world(vp)
        gray = raycast_box_world(BOXES, textures[int(seeds[i])], 0.02, rot, t, intr)
        name = f"{i:06d}.png"
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
        images.append(
            {
                "name": name,
                "viewpoint": vp.tolist(),
                "kind": "test",
                "cam_from_world": {"rotation": rot.tolist(), "translation": t.tolist()},
            }
        )
    record = {"intrinsics": intr.as_dict(), "images": images}
    (image_dir / "cameras.json").write_text(json.dumps(record, indent=1))
    return image_dir


def box_world_mesh() -> trimesh.Trimesh:
    """The ray-cast world as one mesh (boxes + a thin ground slab whose top is z = 0)."""
    parts = [trimesh.creation.box(bounds=np.array(b)) for b in BOXES]
    h = GROUND_HALF_SIZE_M
    parts.append(trimesh.creation.box(bounds=np.array([[-h, -h, -1.0], [h, h, 0.0]])))
    return trimesh.util.concatenate(parts)


def plane_views(intr: Intrinsics, positions, height: float) -> list[View]:
    """Nadir views (yaw 90) at ``positions`` (x, y) and ``height`` metres as OpenCV-convention views."""
    K = intr.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    views = []
    for i, (x, y) in enumerate(positions):
        rot, t = cam_from_world(np.array([x, y, height, 90.0, -90.0]))
        views.append(View(f"{i:06d}.png", K, rot, t, intr.width, intr.height))
    return views


def plane_depth(view: View, plane_z: float) -> np.ndarray:
    """Exact depth (H, W) along the optical axis of the plane z = plane_z seen by ``view``."""
    u, v = np.meshgrid(np.arange(view.width, dtype=float), np.arange(view.height, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view.K).T
    rays_world = rays @ view.rotation
    return ((plane_z - view.center[2]) / rays_world[..., 2]).astype(np.float32)


# ----------------------------------------------------------------------------- tests


def test_png_writing_survives_every_pipeline_import(tmp_path):
    """pycolmap 4.1/4.2 CPU wheels abort PNG writing after import; 4.0.4 must not (fresh process)."""
    script = textwrap.dedent(
        f"""
        import numpy as np, pycolmap, open3d, mujoco, trimesh, cv2, scipy, tqdm
        from PIL import Image
        import reconstruct.pipeline, reconstruct.dense, reconstruct.proxy, reconstruct.sfm
        image = (np.arange(48 * 64 * 3) % 251).astype(np.uint8).reshape(48, 64, 3)
        Image.fromarray(image).save("{tmp_path}/pil.png")
        cv2.imwrite("{tmp_path}/cv.png", image)
        a = np.asarray(Image.open("{tmp_path}/cv.png"))[..., ::-1]  # OpenCV writes BGR
        b = cv2.imread("{tmp_path}/pil.png")[..., ::-1]
        print(int(np.abs(a.astype(int) - image).max()), int(np.abs(b.astype(int) - image).max()))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["0", "0"]


def test_consistent_depth_keeps_agreeing_partners():
    nan = np.nan
    depths = np.array([[[10.0, 10.0, 5.0, nan]], [[10.05, 12.0, nan, nan]], [[9.95, 14.0, nan, nan]]])
    out = consistent_depth(depths, min_consistent=2, rel_tol=0.01)
    assert out[0, 0] == pytest.approx(10.0, abs=1e-5)  # three agree: their mean
    assert np.isnan(out[0, 1])  # 10, 12, 14: only the median agrees with itself
    assert np.isnan(out[0, 2])  # one partner only, two needed
    assert np.isnan(out[0, 3])
    single = consistent_depth(depths[:1], min_consistent=2, rel_tol=0.01)  # one partner: it suffices
    assert single[0, 2] == pytest.approx(5.0)


def test_consistent_depth_weights_each_partner_by_its_precision():
    """Two agreeing partners, baselines 1 and 2 m: weights 1 and 4 (B^2)."""
    depths = np.array([[[10.0]], [[10.05]]])
    weighted = consistent_depth(depths, 1, 0.01, weights=np.square([1.0, 2.0]))
    assert weighted[0, 0] == pytest.approx((10.0 + 4 * 10.05) / 5, abs=1e-5)  # 10.04
    assert consistent_depth(depths, 1, 0.01)[0, 0] == pytest.approx(10.025, abs=1e-5)


def test_stereo_baselines_combine_the_partners_as_their_depths_are_combined():
    from reconstruct.workspace import stereo_baselines

    views = {
        name: SimpleNamespace(center=np.array(center, float))
        for name, center in {"a": (0, 0, 0), "b": (3, 0, 0), "c": (0, 4, 0)}.items()
    }
    partners = {"a": ["b", "c"], "b": [], "c": ["a"]}
    assert stereo_baselines(views, partners, "precision") == pytest.approx({"a": 5.0, "c": 4.0})
    assert stereo_baselines(views, partners, "equal") == pytest.approx({"a": 3.0, "c": 4.0})


def test_disparity_window_holds_the_structure_when_the_span_exceeds_the_cap():
    pair = RectifiedPair(np.eye(3), np.eye(3), np.diag([100.0, 100.0, 1.0]), np.eye(3), 2.0, (640, 480))
    # f * B = 200 px m. A wall at 0.5-0.6 m (disparity 333-400 px) with 90 % of the points, ground
    # running out to 2 m (100 px) and a far background at 20 m (10 px): the 2nd-98th percentile span,
    # widened by 25 % each way, is ~80-500 px.
    rng = np.random.default_rng(0)
    wall = rng.uniform(0.5, 0.6, 900)
    depth = np.concatenate([wall, rng.uniform(0.6, 2.0, 80), np.full(20, 20.0)])
    lo, num = disparity_search_range(pair, depth, 1024)
    assert 70 <= lo <= 80 and 400 * 1.25 <= lo + num <= 400 * 1.25 + 16
    lo, num = disparity_search_range(pair, depth, 128)
    assert num == 128
    # The window holds the wall's disparities (not the far end's 8 + 128).
    assert lo <= 200.0 / 0.6 and 200.0 / 0.5 <= lo + num
    held = np.mean((200.0 / depth >= lo) & (200.0 / depth <= lo + num))
    assert held >= 0.9


def oblique_views(intr: Intrinsics, positions, pitch_deg: float = -45.0) -> list[View]:
    """Views at ``positions`` (x, y, z), all heading +y (yaw 90) and pitched ``pitch_deg``."""
    K = intr.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    views = []
    for i, position in enumerate(positions):
        rot, t = cam_from_world(np.array([*position, 90.0, pitch_deg]))
        views.append(View(f"{i:06d}.png", K, rot, t, intr.width, intr.height))
    return views


def test_a_partner_the_matcher_cannot_rectify_gets_no_slot(tmp_path):
    """A view 45 deg down over the ground; one partner 4 m to its side, one 3 m aside and 4 m
    ahead. Both pass the angle tests (the second's baseline is 55.6 deg from the axes, over the
    50 deg minimum), but turning the second pair to face across its baseline stretches the canvas
    past 4 images: the matcher drops it, so with partners_must_rectify it is not chosen at all."""
    intr = Intrinsics(320, 240, 60.0)
    views = oblique_views(intr, [(0.0, 0.0, 20.0), (4.0, 0.0, 20.0), (3.0, 4.0, 20.0)])
    ref, side, ahead = views
    assert rectify_pair(ref, side) is not None and rectify_pair(ref, ahead) is None
    baseline = (ahead.center - ref.center) / np.linalg.norm(ahead.center - ref.center)
    assert np.degrees(np.arccos(abs(ref.forward @ baseline))) == pytest.approx(55.6, abs=0.1)
    points = np.random.default_rng(0).uniform([-4.0, 17.0, 0.0], [4.0, 23.0, 0.0], (60, 3))
    rec = shared_point_model(
        [v.name for v in views], [v.rotation for v in views], [v.translation for v in views], points, intr
    )
    workspace = tmp_path / "ws"
    (workspace / "sparse").mkdir(parents=True)
    (workspace / "images").mkdir()
    rec.write(workspace / "sparse")
    for view in views:
        cv2.imwrite(str(workspace / "images" / view.name), np.full((intr.height, intr.width), 128, np.uint8))
    by_name = {v.name: v for v in views}
    former = select_partners(workspace, by_name, dense_settings())  # the default: angles alone
    assert sorted(former[ref.name]) == [side.name, ahead.name]
    rectifying = dense_settings(**{"dense.partners_must_rectify": True})
    assert select_partners(workspace, by_name, rectifying)[ref.name] == [side.name]
    # A looser canvas limit (the setting) lets the pair back in.
    rectifying = dataclasses.replace(rectifying, max_rectified_area_ratio=8.0)
    assert sorted(select_partners(workspace, by_name, rectifying)[ref.name]) == [side.name, ahead.name]


def test_normals_from_depth_of_a_tilted_plane():
    intr = Intrinsics(160, 120, 60.0)
    K = intr.K
    normal_cam = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])  # facing the camera
    offset = 8.0  # plane: n . X = -offset
    u, v = np.meshgrid(np.arange(160.0), np.arange(120.0))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    depth = (-offset / (rays @ normal_cam)).astype(np.float32)
    normals = normals_from_depth(depth, K, window=5)
    defined = np.any(normals != 0, axis=-1)
    assert defined.mean() > 0.9
    angle = np.degrees(np.arccos(np.clip(normals[defined] @ normal_cam, -1, 1)))
    assert angle.max() < 0.05


def textured_plane_pair(partner_xy: tuple[float, float]):
    """Two nadir 320 x 240 views 12 m over a textured plane, the partner at ``partner_xy`` (m), their
    images and 50 sparse points on the plane: (ref, src, images, points)."""
    intr = Intrinsics(320, 240, 60.0)
    ref, src = plane_views(intr, [(0.0, 0.0), partner_xy], height=12.0)
    texture = noise_texture(1024, seed=3)
    images = [
        raycast_box_world([], texture, 0.02, view.rotation, view.translation, intr) for view in (ref, src)
    ]
    points = np.random.default_rng(0).uniform([-3, -2, 0], [3, 2, 0], (50, 3))
    return ref, src, images, points


def test_sgbm_pair_depth_of_a_textured_plane():
    """Rectification + SGBM + back-projection recover a plane's depth from a sideways pair."""
    ref, src, images, points = textured_plane_pair((3.0, 1.0))
    settings = dense_settings()
    depth = pair_depth(ref, src, images[0], images[1], points, settings)
    truth = plane_depth(ref, 0.0)
    valid = np.isfinite(depth)
    # The partner sees about 3/4 of the reference at this baseline.
    assert valid.mean() > 0.6
    rel = np.abs(depth[valid] - truth[valid]) / truth[valid]
    assert np.median(rel) < 0.002
    assert np.percentile(rel, 95) < 0.01


def test_the_matchable_window_of_constructed_masks():
    """A reference block in rows 10-29, columns 40-99; the partner's pixels in columns 0-59 of rows
    15-49. With a 16 px search a reference pixel matches up to column 59 + 15 = 74, so the window
    is rows 15-29 and columns 40 - 16 = 24 (the search's padding) to 74."""
    left = np.zeros((60, 120), bool)
    left[10:30, 40:100] = True
    right = np.zeros((60, 120), bool)
    right[15:50, 0:60] = True
    assert matchable_window(left, right, 16) == (slice(15, 30), slice(24, 75))
    # No partner pixel within reach of any reference pixel: nothing to match.
    far = np.zeros_like(right)
    far[:, 110:] = True
    assert matchable_window(left, far, 8) is None
    # A window narrower than the search is widened: SGBM matches nothing in its first n columns.
    narrow = np.zeros_like(left)
    narrow[10:30, 2:6] = True
    assert matchable_window(narrow, right, 16) == (slice(15, 30), slice(0, 17))


def test_matching_the_window_keeps_the_depth_of_the_whole_canvas():
    """A diagonal pair over a textured plane: rectification turns the reference by 45 deg, so a
    third of the canvas is empty. Matching only the window that can match gives the same depth at
    all but a few pixels."""
    ref, src, images, points = textured_plane_pair((2.5, 2.5))
    settings = dense_settings()
    assert settings.sgbm.crop_to_overlap
    uncropped = dataclasses.replace(settings, sgbm=dataclasses.replace(settings.sgbm, crop_to_overlap=False))
    whole = pair_depth(ref, src, *images, points, uncropped)
    cropped = pair_depth(ref, src, *images, points, settings)
    has_whole, has_cropped = np.isfinite(whole), np.isfinite(cropped)
    assert has_whole.mean() > 0.5
    assert (has_whole != has_cropped).mean() < 0.002
    both = has_whole & has_cropped
    # 86 % bit for bit; SGBM's paths from above start at the window's top row instead of the
    # canvas's, which moves a few depths by a fraction of their sub-pixel fit.
    assert (whole[both] == cropped[both]).mean() > 0.8
    assert np.percentile(np.abs(cropped[both] - whole[both]) / whole[both], 99) < 1e-3
    truth = plane_depth(ref, 0.0)
    errors = [np.abs(depth[both] - truth[both]) / truth[both] for depth in (whole, cropped)]
    assert np.median(errors[1]) < 0.005
    assert np.median(errors[1]) == pytest.approx(np.median(errors[0]), abs=1e-5)


def test_sgbm_gives_the_uniform_sky_no_depth():
    """A uniform band (rendered sky) above a textured plane: SGBM alone fills it with depth; the
    texture mask leaves it empty and keeps the plane."""
    ref, src, images, points = textured_plane_pair((3.0, 1.0))
    for image in images:
        image[:100] = 200  # the top 100 rows of both views: sky
    settings = dense_settings()
    assert settings.min_texture_std > 0
    unmasked = pair_depth(
        ref, src, images[0], images[1], points, dataclasses.replace(settings, min_texture_std=0.0)
    )
    depth = pair_depth(ref, src, images[0], images[1], points, settings)
    sky, plane = slice(0, 100 - settings.texture_window_px), slice(100 + settings.texture_window_px, None)
    assert np.isfinite(unmasked[sky]).mean() > 0.5  # the defect the mask exists for
    assert not np.isfinite(depth[sky]).any()
    assert np.isfinite(depth[plane]).mean() == pytest.approx(np.isfinite(unmasked[plane]).mean(), abs=0.02)
    valid = np.isfinite(depth[plane])
    truth = plane_depth(ref, 0.0)[plane]
    assert np.median(np.abs(depth[plane][valid] - truth[valid]) / truth[valid]) < 0.002
    with pytest.raises(ValueError, match="min_texture_std"):
        DenseSettings.from_config(reconstruct_cfg(**{"dense.min_texture_std": -1}).dense)
    with pytest.raises(ValueError, match="min_texture_std"):  # settings built around the check
        pair_depth(
            ref, src, images[0], images[1], points, dataclasses.replace(settings, min_texture_std=-1.0)
        )


def test_textured_pixels_by_local_deviation():
    gray = np.full((40, 60), 120, np.uint8)
    gray[:, 30:] = np.random.default_rng(1).integers(0, 256, (40, 30))
    mask = textured_pixels(gray, 7, 2.0)
    assert not mask[:, :27].any()  # uniform, farther than half a window from the noise
    assert mask[:, 30:].all()
    with pytest.raises(ValueError, match="texture_window_px"):
        textured_pixels(gray, 0, 2.0)


def test_fusion_of_plane_depth_maps_lies_on_the_plane(tmp_path):
    """Exact depth maps of z = 0.5 from a 3x3 nadir grid, normals from depth, COLMAP fusion."""
    intr = Intrinsics(160, 120, 60.0)
    plane_z = 0.5
    positions = [(x, y) for x in (-1.5, 0.0, 1.5) for y in (-1.0, 0.0, 1.0)]
    views = plane_views(intr, positions, height=10.0)
    workspace = tmp_path / "ws"
    texture = noise_texture(256, seed=1)
    (workspace / "images").mkdir(parents=True)
    # Sparse points on the plane seen by every view: fusion picks overlapping views by shared points.
    grid = np.stack(np.meshgrid(np.linspace(-1.0, 1.0, 5), np.linspace(-1.0, 1.0, 5)), -1).reshape(-1, 2)
    sparse_points = np.column_stack([grid, np.full(len(grid), plane_z)])
    rec = shared_point_model(
        [v.name for v in views],
        [v.rotation for v in views],
        [v.translation for v in views],
        sparse_points,
        intr,
    )
    for view in views:
        gray = raycast_box_world([], texture, 0.02, view.rotation, view.translation, intr)
        cv2.imwrite(str(workspace / "images" / view.name), gray)
        depth = plane_depth(view, plane_z)
        write_maps(workspace, view.name, depth, normals_from_depth(depth, view.K, window=5))
    (workspace / "sparse").mkdir()
    rec.write(workspace / "sparse")
    n_points = fuse(workspace, tmp_path / "fused.ply", dense_settings(), [v.name for v in views])
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(tmp_path / "fused.ply"))
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    assert n_points == len(points) > 5000
    assert np.abs(points[:, 2] - plane_z).max() < 1e-3
    assert np.abs(normals[:, 2]).min() > 0.999
    # The cloud spans the union of the footprints (about 5.8 m x 4.6 m at 9.5 m with a 60 deg lens).
    extent = points.max(0) - points.min(0)
    assert extent[0] > 6.0 and extent[1] > 4.5


def synthetic_dataset(tmp_path: Path) -> tuple[Path, pycolmap.Reconstruction]:
    """pycolmap's synthetic 30-image, 300-point pinhole dataset in ``tmp_path/database.db``, and its truth."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 1, 1, 30
    options.num_points3D = 300
    options.camera_model_id = pycolmap.CameraModelId.PINHOLE
    options.camera_params = [1000.0, 1000.0, 512.0, 384.0]
    options.sensor_from_rig_translation_stddev = 0.0
    options.sensor_from_rig_rotation_stddev = 0.0
    database_path = tmp_path / "database.db"
    pycolmap.set_random_seed(0)
    with pycolmap.Database.open(database_path) as db:
        truth = pycolmap.synthesize_dataset(options, db)
    return database_path, truth


def synthetic_flight(image_dir: Path, truth: pycolmap.Reconstruction) -> Flight:
    """The true poses of ``synthetic_dataset``'s images as a Flight (image id order)."""
    names, rotations, translations = [], [], []
    for image_id in sorted(truth.reg_image_ids()):
        image = truth.image(image_id)
        names.append(image.name)
        rotations.append(image.cam_from_world().rotation.matrix())
        translations.append(np.asarray(image.cam_from_world().translation))
    return Flight(
        image_dir,
        Intrinsics(1024, 768, 60.0),
        tuple(names),
        np.array(rotations),
        np.array(translations),
        ("test",) * len(names),
    )


def test_mapping_and_alignment_on_a_synthetic_dataset(tmp_path):
    """pycolmap.synthesize_dataset -> mapper -> similarity to noisy GNSS -> pose errors."""
    database_path, truth = synthetic_dataset(tmp_path)
    flight = synthetic_flight(tmp_path, truth)
    sigma = 0.005 * float(np.ptp(flight.positions, axis=0).max())  # GNSS noise: 0.5 % of the extent
    gnss = simulate_gnss(flight.positions, sigma, seed=1)
    gnss_error_median = float(np.median(np.linalg.norm(gnss - flight.positions, axis=1)))
    cfg = reconstruct_cfg(**{"sfm.mapping.use_prior_position": False})
    for method in ("incremental", "global"):
        cfg.sfm.mapping.method = method
        rec = map_reconstruction(
            database_path,
            tmp_path,
            sfm_options(sfm_settings(cfg), seed=0),
        )[0]
        align_to_gnss(rec, flight.names, gnss, sigma, recon_settings(cfg).align, seed=0)
        errors = pose_errors(rec, flight)
        assert errors["n_registered"] == 30, method
        # 30 noisy positions fix the 7 similarity parameters: the aligned cameras are much closer to
        # the truth than the GNSS positions themselves (the relative poses are exact).
        assert errors["position_error_median_m"] < 0.5 * gnss_error_median, method
        assert errors["rotation_error_max_deg"] < 0.5, method
    # Ten of the cameras cut out as a model of their own: every point (seen by all 30) keeps its
    # observations in those ten.
    part = pycolmap.Reconstruction()
    assert len(merge_model(part, rec, sorted(rec.reg_image_ids())[:10])) == 10
    assert part.num_reg_images() == 10 and part.num_points3D() == rec.num_points3D()
    assert part.compute_mean_track_length() == pytest.approx(10.0)
    assert part.compute_mean_reprojection_error() == pytest.approx(
        rec.compute_mean_reprojection_error(), abs=0.05
    )
    # A camera 5 m from its GNSS fix (here: a gross fix) is de-registered; the others stay.
    moved = gnss.copy()
    moved[7] += [5.0, 0.0, 0.0]
    threshold = 20.0 * sigma
    assert np.linalg.norm(gnss - flight.positions, axis=1).max() + 0.5 * gnss_error_median < threshold < 5.0
    assert deregister_gnss_outliers(rec, flight.names, moved, threshold) == [flight.names[7]]
    assert rec.num_reg_images() == 29
    assert flight.names[7] not in {rec.image(i).name for i in rec.reg_image_ids()}


def test_a_weakly_linked_image_registers_at_the_survey_threshold(tmp_path):
    """The last of 30 synthetic images keeps verified matches for only 20 of its keypoints (a close
    wall view linked to the views above it by a few SIFT inliers): at COLMAP's 30 inliers it stays
    out of the model, at the default 10 it registers where it was taken."""
    database_path, truth = synthetic_dataset(tmp_path)
    weak = max(truth.reg_image_ids())
    with pycolmap.Database.open(database_path) as db:
        for other in truth.reg_image_ids():
            if other == weak:
                continue
            geometry = db.read_two_view_geometry(other, weak)
            matches = np.asarray(geometry.inlier_matches)
            geometry.inlier_matches = matches[matches[:, 1] < 20]
            db.delete_two_view_geometry(other, weak)
            db.delete_matches(other, weak)
            db.write_matches(other, weak, geometry.inlier_matches)
            db.write_two_view_geometry(other, weak, geometry)
    flight = synthetic_flight(tmp_path, truth)
    sigma = 0.001 * float(np.ptp(flight.positions, axis=0).max())
    colmap = {f"sfm.mapping.{k}": v for k, v in COLMAP_ABS_POSE.items()}
    registered = {}
    for label, overrides in (("colmap", colmap), ("default", {})):
        cfg = reconstruct_cfg(**{"sfm.mapping.use_prior_position": False, **overrides})
        models = map_reconstruction(
            database_path,
            tmp_path,
            sfm_options(sfm_settings(cfg), seed=0, deterministic=True),
        )
        registered[label] = weak in set(models[0].reg_image_ids())
        if label == "default":
            assert models[0].num_reg_images() == 30
            align_to_gnss(models[0], flight.names, flight.positions, sigma, recon_settings(cfg).align, seed=0)
            errors = pose_errors(models[0], flight)
            # The synthetic matches are exact: every camera, the weak one too, lands on its pose.
            assert errors["position_error_max_m"] < 1e-3 * float(np.ptp(flight.positions, axis=0).max())
            assert errors["rotation_error_max_deg"] < 0.05
    assert registered == {"colmap": False, "default": True}
    # P3P needs 4 points; a share is a fraction.
    with pytest.raises(ValueError, match="abs_pose_min_num_inliers must be >= 4"):
        sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.abs_pose_min_num_inliers": 3})))
    with pytest.raises(ValueError, match="abs_pose_min_inlier_ratio must be"):
        sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.abs_pose_min_inlier_ratio": 0.0})))


@pytest.fixture(scope="module")
def box_flight(tmp_path_factory):
    """33 ray-cast 320x240 views (a ring at 11 m, a 3x3 nadir grid) of two stacked textured boxes."""
    intr = Intrinsics(320, 240, 60.0)
    viewpoints = ring_viewpoints(24, 11.0, 7.0, [0.0, 0.0, 1.5], 3, 14.0)
    return write_box_world_flight(tmp_path_factory.mktemp("flight"), viewpoints, intr, seed=0)


@pytest.fixture(scope="module")
def box_reconstruction(box_flight, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("recon")
    return out_dir, reconstruct_flight(box_flight, out_dir, recon_settings(reconstruct_cfg()), seed=0)


def test_reconstruct_flight_registers_aligns_and_densifies(box_reconstruction):
    out_dir, record = box_reconstruction
    assert record["status"] == "ok" and record["cached"] is False
    assert record["n_images"] == 33 and record["n_registered"] == 33
    assert record["registered_fraction"] == 1.0
    # 0.05 m GNSS noise; 320x240 images with ~450 SIFT features each.
    assert record["position_error_median_m"] < 0.05
    assert record["position_error_p90_m"] < 0.08
    assert record["rotation_error_median_deg"] < 0.3
    assert record["align_time_s"] == pytest.approx(
        record["extraction_time_s"] + record["matching_time_s"] + record["mapping_time_s"]
    )
    assert record["align_cpu_s"] == pytest.approx(
        record["extraction_cpu_s"] + record["matching_cpu_s"] + record["mapping_cpu_s"]
    )
    # CPU time (process + children) is at most every core busy for the stage's wall time (plus the
    # 10 ms clock tick), and SfM and dense keep more than one core busy part of the time.
    for stage in ("extraction", "matching", "mapping", "dense"):
        assert 0 < record[f"{stage}_cpu_s"] <= os.cpu_count() * record[f"{stage}_time_s"] + 0.02, stage
    for name in ("database.db", "sparse/images.bin", "dense.ply", "recon.json"):
        assert (out_dir / name).exists(), name
    # No temporary left behind (fusion's <ply>.vis sidecar used to stay under the temporary name).
    assert not [p.name for p in out_dir.iterdir() if p.name.startswith(".")]
    assert Path(record["colmap_log"]).stat().st_size > 1000
    assert "Registering image" in Path(record["colmap_log"]).read_text()
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(record["dense_ply"]).points)
    assert len(points) == record["n_dense_points"] > 5000
    distance = trimesh.proximity.closest_point(box_world_mesh(), points)[1]
    # GSD about 4 cm/px at 11 m, and the cameras themselves sit 3 cm (median) off after alignment to
    # 5 cm GNSS: 90 % of the fused points within 2 GSD of the true surface, half within 1 GSD.
    assert np.percentile(distance, 90) < 0.08
    assert np.median(distance) < 0.04


def test_a_flight_split_in_two_models_is_georeferenced_and_merged(tmp_path):
    """The ring of the box flight painted with one texture on one half and another on the other: the
    halves share no content, so SfM finds two models; both are aligned to their own GNSS fixes and
    merged before dense matching."""
    intr = Intrinsics(320, 240, 60.0)
    viewpoints = ring_viewpoints(32, 11.0, 7.0, [0.0, 0.0, 1.5], 0, 0.0)
    flight = write_box_world_flight(tmp_path / "flight", viewpoints, intr, seed=np.repeat([3, 4], 16))
    # RTK fixes of 2 cm: each half-ring's similarity comes from its own 16 fixes only.
    cfg = reconstruct_cfg(**{"gnss.sigma_m": 0.02})
    record = reconstruct_flight(flight, tmp_path / "recon", recon_settings(cfg), seed=0)
    assert record["n_models"] == 2 and record["model_sizes"] == "16+16"
    assert record["n_models_merged"] == 1 and record["n_images_merged"] == 16
    assert record["n_images_dropped"] == 0
    assert record["n_registered"] == 32
    assert record["position_error_max_m"] < 0.05
    merged = pycolmap.Reconstruction(record["sparse_dir"])
    assert merged.num_reg_images() == 32
    # Each half keeps its points, and their tracks still fit the moved cameras (reprojection < 1 px).
    first_half = {f"{i:06d}.png" for i in range(16)}
    halves = [merged.image(p.track.elements[0].image_id).name in first_half for p in merged.points3D.values()]
    assert 300 < sum(halves) < len(halves) - 300
    assert merged.compute_mean_reprojection_error() < 1.0
    # Dense matching used both models: the box face only the first half sees (y = +2, ring angles
    # 0-180 deg) and the one only the second half sees (y = -2) both get fused points within 1 GSD.
    import open3d as o3d

    dense = np.asarray(o3d.io.read_point_cloud(record["dense_ply"]).points)
    on_face = (np.abs(dense[:, 0]) < 2.5) & (dense[:, 2] > 0.5) & (dense[:, 2] < 2.5)
    for face_y in (2.0, -2.0):
        assert (on_face & (np.abs(dense[:, 1] - face_y) < 0.04)).sum() > 1000, face_y
    # With a merge threshold above 16 images the second model is dropped and counted, not merged.
    dropped = reconstruct_flight(
        flight,
        tmp_path / "recon_dropped",
        recon_settings(reconstruct_cfg(**{"gnss.sigma_m": 0.02, "align.merge_min_images": 17})),
        seed=0,
    )
    assert dropped["n_models_merged"] == 0 and dropped["n_images_dropped"] == 16
    assert dropped["n_registered"] == 16


def test_prior_position_settings_reach_the_mapper():
    options = sfm_options(sfm_settings(reconstruct_cfg()))
    assert options.incremental.use_prior_position and options.incremental.use_robust_loss_on_prior_position
    strict = sfm_options(
        sfm_settings(reconstruct_cfg(**{"sfm.mapping.robust_loss_on_prior_position": False}))
    )
    assert strict.incremental.use_prior_position and not strict.incremental.use_robust_loss_on_prior_position
    # No priors at all: no robust loss on them either.
    none = sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.use_prior_position": False})))
    assert not none.incremental.use_prior_position and not none.incremental.use_robust_loss_on_prior_position


def test_global_mapper_models_come_back_in_the_gnss_frame_with_the_prior_ba(tmp_path):
    """The global mapper has no GNSS term; the pose-prior bundle adjustment after it puts the model
    in the priors' frame (no similarity fit of ours), cameras closer to the truth than the fixes."""
    database_path, truth = synthetic_dataset(tmp_path)
    ids = sorted(truth.reg_image_ids())
    names = [truth.image(i).name for i in ids]
    positions = np.array([truth.image(i).projection_center() for i in ids])
    sigma = 0.005 * float(np.ptp(positions, axis=0).max())
    gnss = simulate_gnss(positions, sigma, seed=1)
    write_pose_priors(database_path, names, gnss, sigma)
    gnss_error_median = float(np.median(np.linalg.norm(gnss - positions, axis=1)))
    cfg = reconstruct_cfg(**{"sfm.mapping.method": "global"})
    rec = map_reconstruction(
        database_path,
        tmp_path,
        sfm_options(sfm_settings(cfg), seed=0),
    )[0]
    assert rec.num_reg_images() == 30
    centre = {rec.image(i).name: rec.image(i).projection_center() for i in rec.reg_image_ids()}
    error = np.linalg.norm(np.array([centre[n] for n in names]) - positions, axis=1)
    assert np.median(error) < 0.5 * gnss_error_median
    # Without it the model stays in the mapper's own frame, nowhere near the fixes.
    cfg.sfm.mapping.global_prior_ba = False
    raw = map_reconstruction(
        database_path,
        tmp_path,
        sfm_options(sfm_settings(cfg), seed=0),
    )[0]
    centre = {raw.image(i).name: raw.image(i).projection_center() for i in raw.reg_image_ids()}
    assert np.median(np.linalg.norm(np.array([centre[n] for n in names]) - positions, axis=1)) > 10 * sigma


def test_fusion_chunks_cover_every_view_once_within_the_budget():
    # Ten views in a row, each overlapping the next and the previous one.
    neighbours = [np.array([u for u in (v - 1, v + 1) if 0 <= u < 10]) for v in range(10)]
    chunks = plan_chunks(neighbours, max_views=4)
    assert [(c.own.tolist(), c.neighbours.tolist()) for c in chunks] == [
        ([0, 1, 2], [3]),
        ([3, 4], [2, 5]),
        ([5, 6], [4, 7]),
        ([7, 8, 9], [6]),  # view 9 adds no view the chunk does not hold already
    ]
    assert sorted(np.concatenate([c.own for c in chunks]).tolist()) == list(range(10))
    assert max(len(c.views) for c in chunks) <= 4
    with pytest.raises(ValueError, match="max_views 2 cannot hold a view and its neighbours"):
        plan_chunks(neighbours, 2)


def test_a_fused_point_belongs_to_the_chunk_owning_most_of_its_views(tmp_path):
    visibility = [[0, 1, 3], [3, 4, 0], [0, 3], [5, 2, 4], [1]]
    words = [w for v in visibility for w in (len(v), *v)]
    path = tmp_path / "cloud.ply.vis"
    path.write_bytes(np.uint64(len(visibility)).tobytes() + np.array(words, dtype=np.uint32).tobytes())
    counts, indices = read_visibility(path)
    assert counts.tolist() == [3, 3, 2, 3, 1]
    assert indices.tolist() == [w for v in visibility for w in v]
    # Workspace images 0-2 are chunk 0's own views, 3-4 chunk 1's, 5 chunk 2's.
    chunk_of = np.array([0, 0, 0, 1, 1, 2])
    # 2 of 3 in chunk 0; 2 of 3 in chunk 1; a tie (the earlier chunk); one view each (the
    # earlier); chunk 0's alone.
    assert owning_chunk(counts, indices, chunk_of, 3).tolist() == [0, 1, 0, 0, 0]
    path.write_bytes(path.read_bytes()[:-4])
    with pytest.raises(ValueError, match="account for"):
        read_visibility(path)


# COLMAP's fusion walking to 6 neighbours of each view: the fusion that holds every view, and chunks.
COLMAP_FUSION = {"dense.fusion.check_num_images": 6, "dense.fusion.method": "colmap"}


def with_fusion_budget(settings: DenseSettings, max_memory_gb: float) -> DenseSettings:
    """``settings`` with ``fusion.max_memory_gb`` (GB) replaced."""
    return dataclasses.replace(
        settings, fusion=dataclasses.replace(settings.fusion, max_memory_gb=max_memory_gb)
    )


def test_an_auto_fusion_budget_chunks_to_the_memory_free(box_reconstruction, tmp_path, monkeypatch):
    """``max_memory_gb: auto`` is half the memory free: with 33 views' worth free, 16 a chunk."""
    import psutil

    from reconstruct.dense import fuse_report

    out_dir, _ = box_reconstruction
    workspace = out_dir / "dense"
    names = sorted(p.name for p in (workspace / "images").iterdir())
    view_bytes = 20 * 320 * 240
    free = type("Free", (), {"available": 33.5 * view_bytes})()
    monkeypatch.setattr(psutil, "virtual_memory", lambda: free)
    # COLMAP's fusion (the proxy's) holds every view and chunks; the ray fusion holds a few.
    settings = dense_settings(**COLMAP_FUSION)
    assert fusion_chunk_size(workspace, names, fusion_budget_gb("auto")) == 16
    report = fuse_report(workspace, tmp_path / "auto.ply", settings, names, deterministic=True)
    assert report.n_chunks >= 3 and report.max_memory_gb == pytest.approx(0.5 * 33.5 * view_bytes / 1e9)
    single = fuse(
        workspace,
        tmp_path / "one.ply",
        dense_settings(**{**COLMAP_FUSION, "dense.fusion.max_memory_gb": None}),
        names,
        deterministic=True,
    )
    # The chunked cloud covers the one-pass cloud: as many points within half, at most half again.
    assert single <= report.n_points < 1.5 * single


def test_fusion_in_chunks_covers_the_single_pass_cloud(box_reconstruction, tmp_path):
    """The 33 box views, fusion walking to 6 neighbours of each, fused in chunks of at most 16 views:
    the surfaces of one pass, as close to the truth, a few of them twice (chunk boundaries)."""
    out_dir, _ = box_reconstruction
    workspace = out_dir / "dense"
    names = sorted(p.name for p in (workspace / "images").iterdir())
    settings = dense_settings(**COLMAP_FUSION)
    # The default budget, half the memory free (auto), holds these 33 small views at once.
    assert settings.fusion.max_memory_gb == "auto"
    assert fusion_chunk_size(workspace, names, fusion_budget_gb("auto")) is None
    single = fuse(workspace, tmp_path / "single.ply", settings, names, deterministic=True)
    view_gb = 20 * 320 * 240 / 1e9  # image, depth, normal and mask bytes of one 320 x 240 view
    settings = with_fusion_budget(settings, 16.5 * view_gb)
    assert fusion_chunk_size(workspace, names, settings.fusion.max_memory_gb) == 16
    chunked = fuse(workspace, tmp_path / "chunked.ply", settings, names, deterministic=True)
    a = trimesh.load(tmp_path / "single.ply").vertices
    b = trimesh.load(tmp_path / "chunked.ply").vertices
    assert (len(a), len(b)) == (single, chunked)
    assert single <= chunked < 1.5 * single
    from scipy.spatial import cKDTree

    # GSD about 4 cm at 11 m: 95 % of the single pass's points have a chunked point within 1 GSD.
    assert np.mean(cKDTree(b).query(a)[0] < 0.04) > 0.95
    # And the chunked points are as close to the true boxes (90 % within 2 GSD, as one pass).
    sample = b[np.random.default_rng(0).choice(len(b), 20000, replace=False)]
    assert np.percentile(trimesh.proximity.closest_point(box_world_mesh(), sample)[1], 90) < 0.08
    with pytest.raises(ValueError, match="holds fewer than two views"):
        fuse(workspace, tmp_path / "none.ply", with_fusion_budget(settings, 1.5 * view_gb), names)


def test_global_ba_schedule_reaches_the_mapper():
    options = sfm_options(sfm_settings(reconstruct_cfg())).incremental
    assert (options.ba_global_frames_ratio, options.ba_global_points_ratio) == (1.3, 1.3)
    assert options.ba_global_max_num_iterations == 25
    assert not options.mapper.ba_global_ignore_redundant_points3D
    skip = sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.global_ba_skip_redundant_points": True})))
    assert skip.incremental.mapper.ba_global_ignore_redundant_points3D
    with pytest.raises(ValueError, match="global_ba_growth_ratio must be > 1"):
        sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.global_ba_growth_ratio": 1.0})))
    rounds = "sfm.mapping.global_ba_max_refinements"
    assert options.ba_global_max_refinements == reconstruct_cfg().sfm.mapping.global_ba_max_refinements
    assert (
        sfm_options(sfm_settings(reconstruct_cfg(**{rounds: 2}))).incremental.ba_global_max_refinements == 2
    )
    with pytest.raises(ValueError, match="global_ba_max_refinements must be >= 1"):
        sfm_options(sfm_settings(reconstruct_cfg(**{rounds: 0})))
    # The local BA after each registration: 4 images, 10 iterations, 1 round by default; COLMAP's
    # 6, 25, 2 one setting away.
    local = (
        options.mapper.ba_local_num_images,
        options.ba_local_max_num_iterations,
        options.ba_local_max_refinements,
    )
    assert local == (4, 10, 1)
    colmap = sfm_options(
        SfmSettings.from_config(
            reconstruct_cfg(**{f"sfm.mapping.{k}": v for k, v in COLMAP_LOCAL_BA.items()}).sfm
        )
    ).incremental
    assert (
        colmap.mapper.ba_local_num_images,
        colmap.ba_local_max_num_iterations,
        colmap.ba_local_max_refinements,
    ) == (6, 25, 2)
    with pytest.raises(ValueError, match="local_ba_num_images must be >= 1"):
        sfm_options(sfm_settings(reconstruct_cfg(**{"sfm.mapping.local_ba_num_images": 0})))


def test_pose_prior_pairs_skip_views_back_to_back():
    """Four cameras facing +y and four facing -y at the same places on a line: with a 75 deg axis
    limit only same-facing cameras pair (each with its 3 nearest), and a distance cut-off of 1.5 m
    leaves only neighbours 1 m apart."""
    positions = np.array([[x, 0.0, 10.0] for x in range(4)] * 2, float)
    axes = np.array([[0.0, 1.0, 0.0]] * 4 + [[0.0, -1.0, 0.0]] * 4)
    pairs = pose_prior_pairs(positions, axes, 3, 0.0, 75.0)
    same_facing = {(i, j) for group in (range(4), range(4, 8)) for i in group for j in group if i < j}
    assert {tuple(p) for p in pairs} == same_facing
    near = pose_prior_pairs(positions, axes, 3, 1.5, 75.0)
    assert {tuple(p) for p in near} == {(0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (6, 7)}
    # Without the axis limit, back-to-back cameras at the same place are each other's nearest.
    assert {(0, 4), (3, 7)} <= {tuple(p) for p in pose_prior_pairs(positions, axes, 3, 0.0, 180.0)}


def test_pose_prior_matching_registers_the_box_flight(box_flight, tmp_path):
    cfg = reconstruct_cfg(**{"sfm.matching.method": "pose_prior", "sfm.matching.pose_prior_max_neighbors": 8})
    record = reconstruct_flight(box_flight, tmp_path / "recon", recon_settings(cfg), seed=0)
    assert record["matching_method"] == "pose_prior"
    # 33 views, at most 8 neighbours each: fewer than the 528 exhaustive pairs, all registered.
    assert 33 * 8 / 2 <= record["n_image_pairs"] <= 33 * 8
    assert record["n_registered"] == 33
    assert record["position_error_median_m"] < 0.05


def test_the_prior_check_drops_only_spurious_pairs_of_the_box_flight(box_flight, tmp_path):
    """The box's plain walls give RANSAC some spurious pairs (15-60 inliers, relative rotations 10-100
    deg off the true ones: 30 of the 528 exhaustive pairs at seed 0). The check drops those and no
    view is lost: all 33 register as accurately as without it."""
    cfg = reconstruct_cfg(**{"sfm.matching.prior_check.enabled": True})
    record = reconstruct_flight(box_flight, tmp_path / "recon", recon_settings(cfg), seed=0)
    assert 0 < record["n_pairs_rejected_by_priors"] <= 0.1 * record["n_image_pairs"]
    assert record["n_registered"] == 33
    assert record["position_error_median_m"] < 0.05


def test_stage_time_counts_threads_and_children():
    """A child process busy for 0.4 s CPU and a numpy thread pool both count; the CPU time never
    exceeds every core busy for the wall time."""
    with stage_time() as clock:
        subprocess.run(
            [
                sys.executable,
                "-c",
                "import time\nt = time.process_time()\nwhile time.process_time() < t + 0.4: pass",
            ],
            check=True,
        )
    assert clock.cpu_s >= 0.4
    assert clock.cpu_s <= os.cpu_count() * clock.wall_s + 0.02


def image_size_settings(max_image_size: int) -> DenseSettings:
    """The default dense settings with ``max_image_size`` (px, longest side)."""
    return dataclasses.replace(dense_settings(), max_image_size=max_image_size)


def test_downsized_workspace_cameras_match_their_images(box_flight, box_reconstruction, tmp_path):
    """The undistorter downsizes images to max_image_size; the workspace's cameras must follow."""
    _, record = box_reconstruction
    workspace = prepare_workspace(
        Path(record["sparse_dir"]), box_flight, tmp_path / "ws", image_size_settings(200)
    )
    rec = pycolmap.Reconstruction(workspace / "sparse")
    focal_320 = Intrinsics(320, 240, 60.0).focal_px
    for image in rec.images.values():
        camera = rec.camera(image.camera_id)
        height, width = cv2.imread(str(workspace / "images" / image.name)).shape[:2]
        assert (camera.width, camera.height) == (width, height) == (200, 150)
        assert camera.params[0] == pytest.approx(focal_320 * 200 / 320, rel=1e-3)
        assert camera.params[2] == pytest.approx(100.0, abs=0.5)


def test_full_size_pinhole_workspace_is_linked_and_equals_the_undistorters(
    box_flight, box_reconstruction, tmp_path
):
    """PINHOLE images within max_image_size are linked, not re-encoded: same cameras, poses, stereo
    config and pixels as COLMAP's undistorter writes (bar the border it blacks out)."""
    _, record = box_reconstruction
    sparse = Path(record["sparse_dir"])
    linked = prepare_workspace(sparse, box_flight, tmp_path / "linked", image_size_settings(1024))
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = 1024
    pycolmap.undistort_images(
        tmp_path / "colmap", sparse, box_flight, output_type="COLMAP", undistort_options=options
    )
    ours, theirs = (pycolmap.Reconstruction(ws / "sparse") for ws in (linked, tmp_path / "colmap"))
    assert ours.num_reg_images() == theirs.num_reg_images() == 33
    for image_id in theirs.reg_image_ids():
        a, b = ours.image(image_id), theirs.image(image_id)
        assert a.name == b.name
        np.testing.assert_allclose(a.cam_from_world().matrix(), b.cam_from_world().matrix(), atol=1e-12)
        np.testing.assert_allclose(a.camera.params, b.camera.params)
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
        assert (linked / "images" / a.name).stat().st_ino == (box_flight / a.name).stat().st_ino
        mine, colmaps = (cv2.imread(str(ws / "images" / a.name)) for ws in (linked, tmp_path / "colmap"))
        # The undistorter resamples to the same pixels but blacks out a thin border (about 1 %).
        painted = colmaps.any(axis=-1)
        assert painted.mean() > 0.97
        assert np.array_equal(mine[painted], colmaps[painted])
    config = "stereo/patch-match.cfg"
    assert (linked / config).read_text().split() == (tmp_path / "colmap" / config).read_text().split()


def test_downscaled_workspace_undistorts_a_lens_like_colmaps_undistorter(
    box_flight, box_reconstruction, tmp_path
):
    """A photo flight's lens (SIMPLE_RADIAL, k1 = -0.1, the round trip's): downsizing before
    undistorting gives COLMAP's undistorted cameras and poses, images within JPEG-and-filter noise of
    the undistorter's, and keypoints where the workspace camera projects their 3D points."""
    from experiments.photo_roundtrip import radial_warp

    _, record = box_reconstruction
    rec = pycolmap.Reconstruction(Path(record["sparse_dir"]))
    k1 = -0.1
    camera_id = next(iter(rec.cameras))
    pinhole = rec.camera(camera_id)
    focal, cx, cy = pinhole.params[0], pinhole.params[2], pinhole.params[3]
    lens = pycolmap.Camera(
        model="SIMPLE_RADIAL",
        width=pinhole.width,
        height=pinhole.height,
        params=[focal, cx, cy, k1],
        camera_id=camera_id,
    )
    photos = tmp_path / "photos"
    photos.mkdir()
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        rgb = cv2.imread(str(box_flight / image.name))[:, :, ::-1]
        cv2.imwrite(str(photos / image.name), np.ascontiguousarray(radial_warp(rgb, k1, focal)[:, :, ::-1]))
        xy = np.array([p.xy for p in image.points2D])
        for point, moved in zip(
            image.points2D,
            lens.img_from_cam(np.column_stack([pinhole.cam_from_img(xy), np.ones(len(xy))])),
            strict=True,
        ):
            point.xy = moved
    rec.cameras[camera_id] = lens
    sparse = tmp_path / "sparse"
    sparse.mkdir()
    rec.write(sparse)

    ours = prepare_workspace(
        sparse, photos, tmp_path / "ours", image_size_settings(200), downscale_first=True
    )
    colmap = prepare_workspace(sparse, photos, tmp_path / "colmap", image_size_settings(200))
    a, b = (pycolmap.Reconstruction(ws / "sparse") for ws in (ours, colmap))
    assert a.camera(camera_id).model == pycolmap.CameraModelId.PINHOLE
    assert (a.camera(camera_id).width, a.camera(camera_id).height) == (
        b.camera(camera_id).width,
        b.camera(camera_id).height,
    )
    small = pycolmap.Camera(model="SIMPLE_RADIAL", width=320, height=240, params=[focal, cx, cy, k1])
    small.rescale(200, 150)
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = 200
    np.testing.assert_allclose(a.camera(camera_id).params, pycolmap.undistort_camera(options, small).params)
    # COLMAP finds the undistorted frame at 320 px and rounds it to whole pixels there, we at 200:
    # the focal lengths agree to a pixel of the 150 px side.
    np.testing.assert_allclose(a.camera(camera_id).params, b.camera(camera_id).params, rtol=1 / 150)
    reprojection = []
    for image_id in b.reg_image_ids():
        mine, theirs = a.image(image_id), b.image(image_id)
        np.testing.assert_allclose(
            mine.cam_from_world().matrix(), theirs.cam_from_world().matrix(), atol=1e-12
        )
        x, y = (cv2.imread(str(ws / "images" / mine.name)).astype(float) for ws in (ours, colmap))
        assert x.shape == y.shape
        # Two resamplings of one photo (area average then bilinear, against bilinear then the
        # undistorter's downsizing), each saved as JPEG: grey levels of 255.
        assert np.abs(x - y)[4:-4, 4:-4].mean() < 2.0  # measured 1.1
        for point in mine.points2D:
            if point.has_point3D():
                projected = a.camera(camera_id).img_from_cam(
                    mine.cam_from_world() * a.point3D(point.point3D_id).xyz
                )
                reprojection.append(np.linalg.norm(projected - point.xy))
    # SfM's reprojection error at 320 px (below a pixel) scaled to the 200 px workspace.
    assert np.median(reprojection) < 0.2  # measured 0.09
    config = "stereo/patch-match.cfg"
    assert (ours / config).read_text().split() == (colmap / config).read_text().split()


def test_reconstruct_flight_reuses_unchanged_outputs(box_flight, box_reconstruction):
    out_dir, record = box_reconstruction
    again = reconstruct_flight(box_flight, out_dir, recon_settings(reconstruct_cfg()), seed=0)
    assert again["cached"] is True
    assert again["content_key"] == record["content_key"]
    assert again["position_error_median_m"] == record["position_error_median_m"]

    flight = read_flight(box_flight)
    key = flight_content_key(box_flight, flight, reconstruct_cfg(), 0)
    assert key == record["content_key"]
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{"gnss.sigma_m": 2.0}), 0) != key
    assert flight_content_key(box_flight, flight, reconstruct_cfg(), 1) != key
    # The proxy settings do not touch the flight's reconstruction.
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{"proxy.face_budget": 10}), 0) == key
    # Fusing the 33 views of 320 x 240 holds 51 MB: a budget above that changes nothing, one below does.
    # Reference views for a cover only: off (null) it leaves the key as before it existed.
    cover = "dense.reference_views_per_point"
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{cover: None}), 0) == key
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{cover: 12}), 0) != key
    budget = "dense.fusion.max_memory_gb"
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{budget: 0.06}), 0) == key
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{budget: None}), 0) == key
    assert flight_content_key(box_flight, flight, reconstruct_cfg(**{budget: 0.04}), 0) != key
    # A mapper setting added after the records: at COLMAP's own value it leaves the key alone.
    rounds = "sfm.mapping.global_ba_max_refinements"
    colmap_local = {f"sfm.mapping.{k}": v for k, v in {**COLMAP_LOCAL_BA, **COLMAP_ABS_POSE}.items()}
    keys = {
        n: flight_content_key(box_flight, flight, reconstruct_cfg(**{rounds: n, **colmap_local}), 0)
        for n in (1, 2, 5)
    }
    assert len(set(keys.values())) == 3
    without = reconstruct_cfg()
    without.sfm.mapping.pop("global_ba_max_refinements")
    for local in (*COLMAP_LOCAL_BA, *COLMAP_ABS_POSE):
        without.sfm.mapping.pop(local)
    assert flight_content_key(box_flight, flight, without, 0) == keys[5]
    # The lighter local BA and the survey registration threshold of the defaults make a new key.
    assert flight_content_key(box_flight, flight, reconstruct_cfg(), 0) != keys[5]


def test_dense_settings_added_after_the_records_leave_legacy_keys_alone(box_flight):
    # A config from before the depth filters and the ray fusion existed, and one that sets them
    # to their legacy values, key the same flight alike; each one switched on makes a new key.
    flight = read_flight(box_flight)
    legacy = {
        "dense.edge_margin_px": 0,
        "dense.geometric_consistency.min_views": 0,
        "dense.fusion.method": "colmap",
        "dense.fusion.support_share": 0.0,
        "dense.partner_weights": "equal",
        "dense.fusion.conditioning_ratio": 0.0,
        "dense.fusion.slant_window_px": 0.0,
        "dense.fusion.gate_disparity_px": 0.0,
        "dense.sgbm.mirror_pass": False,
        "dense.sgbm.crop_to_overlap": False,
        "dense.sgbm.p1_per_block_pixel": 8.0,
        "dense.sgbm.p2_per_block_pixel": 32.0,
    }
    explicit = reconstruct_cfg(**legacy)
    before = reconstruct_cfg(**legacy)
    for key in ("edge_margin_px", "geometric_consistency", "partner_weights"):
        before.dense.pop(key)
    for key in ("method", "ray_neighbours", "ray_voxel_m", "support_share", "support_radius_m"):
        before.dense.fusion.pop(key)
    for key in ("conditioning_ratio", "conditioning_cell_m", "slant_window_px", "gate_disparity_px"):
        before.dense.fusion.pop(key)
    for key in ("mirror_pass", "crop_to_overlap", "p1_per_block_pixel", "p2_per_block_pixel"):
        before.dense.sgbm.pop(key)
    key = flight_content_key(box_flight, flight, before, 0)
    assert flight_content_key(box_flight, flight, explicit, 0) == key
    rays_only = reconstruct_cfg(**{**legacy, "dense.fusion.ray_neighbours": 3})  # unread by COLMAP's fusion
    assert flight_content_key(box_flight, flight, rays_only, 0) == key
    switched = {
        "dense.edge_margin_px": 3,
        "dense.geometric_consistency.min_views": 2,
        "dense.fusion.method": "rays",
        "dense.fusion.support_share": 0.3,
        "dense.partner_weights": "precision",
        "dense.sgbm.mirror_pass": True,
        "dense.sgbm.crop_to_overlap": True,
        "dense.sgbm.p1_per_block_pixel": 0.8,
        "dense.sgbm.p2_per_block_pixel": 64.0,
    }
    keys = {
        flight_content_key(box_flight, flight, reconstruct_cfg(**{**legacy, key: value}), 0)
        for key, value in switched.items()
    }
    conditioned = {**legacy, "dense.fusion.method": "rays", "dense.fusion.conditioning_ratio": 2.0}
    keys.add(flight_content_key(box_flight, flight, reconstruct_cfg(**conditioned), 0))
    slanted = {**conditioned, "dense.fusion.slant_window_px": 3.0}
    keys.add(flight_content_key(box_flight, flight, reconstruct_cfg(**slanted), 0))
    gated = {**conditioned, "dense.fusion.gate_disparity_px": 3.0}
    keys.add(flight_content_key(box_flight, flight, reconstruct_cfg(**gated), 0))
    assert len(keys) == 12 and flight_content_key(box_flight, flight, before, 0) not in keys


def test_a_run_killed_after_sfm_resumes_from_its_sparse_model(box_flight, box_reconstruction, tmp_path):
    out_dir, record = box_reconstruction
    killed = tmp_path / "recon"
    shutil.copytree(out_dir, killed)
    # Killed during dense matching: no cloud, no record, half a workspace.
    for name in ("recon.json", "dense.ply"):
        (killed / name).unlink()
    (killed / "dense" / "stereo" / "depth_maps").mkdir(parents=True, exist_ok=True)
    stage = json.loads((killed / "sfm.json").read_text())
    assert stage["content_key"] == record["content_key"] and "dense_time_s" not in stage

    resumed = reconstruct_flight(box_flight, killed, recon_settings(reconstruct_cfg()), seed=0)
    assert resumed["resumed_after_sfm"] is True and resumed["cached"] is False
    # SfM's record is the first run's (its times included), the sparse model untouched.
    for key in ("n_registered", "position_error_median_m", "mapping_time_s", "align_cpu_s", "n_image_pairs"):
        assert resumed[key] == record[key]
    assert pycolmap.Reconstruction(killed / "sparse").num_reg_images() == record["n_registered"]
    # Dense ran again on the same model: the same cloud up to fusion's thread order.
    assert resumed["n_depth_maps"] == record["n_depth_maps"]
    assert resumed["n_dense_points"] == pytest.approx(record["n_dense_points"], rel=0.02)
    assert json.loads((killed / "recon.json").read_text())["status"] == "ok"

    # Another seed is another flight key: SfM runs again, no stage is reused.
    other = tmp_path / "other_seed"
    shutil.copytree(killed, other)
    (other / "recon.json").unlink()
    again = reconstruct_flight(box_flight, other, recon_settings(reconstruct_cfg()), seed=1)
    assert "resumed_after_sfm" not in again
    assert json.loads((other / "sfm.json").read_text())["content_key"] == again["content_key"]
    assert again["content_key"] != record["content_key"]


def test_build_proxy_covers_the_boxes_and_refuses_partial_models(box_flight, box_reconstruction, tmp_path):
    out_dir, _ = box_reconstruction
    # No proxy-only dense settings: the exploratory flight's reconstruction is the fixture's, reused.
    cfg = reconstruct_cfg(**{"proxy.face_budget": 20000, "proxy.dense": {}})
    mesh, record = build_proxy(box_flight, out_dir, recon_settings(cfg), seed=0)
    assert record["cached"] is True and record["proxy_cached"] is False
    assert len(mesh.faces) <= 20000
    again, record2 = build_proxy(box_flight, out_dir, recon_settings(cfg), seed=0)
    assert record2["proxy_cached"] is True and len(again.faces) == len(mesh.faces)
    # The big box's walls and roof: most of the true surface lies within 15 cm of the proxy.
    lo, hi = np.array(BOXES[0][0]), np.array(BOXES[0][1])
    rng = np.random.default_rng(0)
    samples = []
    for axis, value in ((0, lo[0]), (0, hi[0]), (1, lo[1]), (1, hi[1]), (2, hi[2])):
        s = rng.uniform(lo, hi, (500, 3))
        s[:, axis] = value
        samples.append(s)
    samples = np.concatenate(samples)
    samples = samples[~Box(BOXES[1][0], BOXES[1][1]).expanded(0.01, 0.01, 0.01).contains(samples)]
    distance = trimesh.proximity.closest_point(mesh, samples)[1]
    assert np.mean(distance < 0.15) > 0.7

    strict = reconstruct_cfg(**{"proxy.min_registered_fraction": 1.01, "proxy.dense": {}})
    with pytest.raises(ReconstructionError, match="partial model") as info:
        build_proxy(box_flight, out_dir, recon_settings(strict), seed=0)
    assert info.value.record["status"] == "failed"
    assert info.value.record["registered_fraction"] == 1.0


def test_build_proxy_cuts_to_the_region_of_interest(box_flight, box_reconstruction):
    out_dir, _ = box_reconstruction
    roi = Box(BOXES[0][0], BOXES[0][1])  # the big box: the survey's site
    uncut = reconstruct_cfg(**{"proxy.dense": {}, "proxy.roi_margin_m": None})
    whole, _ = build_proxy(box_flight, out_dir, recon_settings(uncut), seed=0, roi=roi)
    cfg = reconstruct_cfg(**{"proxy.dense": {}, "proxy.roi_margin_m": 0.5})
    cut, record = build_proxy(box_flight, out_dir, recon_settings(cfg), seed=0, roi=roi)
    assert record["proxy_cached"] is False
    lo, hi = np.array(roi.lo[:2]) - 0.5, np.array(roi.hi[:2]) + 0.5
    tol = cfg.proxy.voxel_size_m + 1e-6  # the Poisson mesh is cut to the cropped cloud's box + 1 voxel
    assert np.all(cut.vertices[:, :2] >= lo - tol) and np.all(cut.vertices[:, :2] <= hi + tol)
    # without a margin nothing is cut: the ground around the site stays
    assert np.any(whole.vertices[:, :2] < lo - 1.0) or np.any(whole.vertices[:, :2] > hi + 1.0)


def test_proxy_dense_settings_override_only_the_exploratory_flight():
    cfg = reconstruct_cfg(**{"proxy.dense": {"max_image_size": 640, "num_partners": 2}})
    flight_cfg = exploration_values(cfg)
    assert flight_cfg["dense"]["max_image_size"] == 640 and flight_cfg["dense"]["num_partners"] == 2
    assert flight_cfg["dense"]["sgbm"] == OmegaConf.to_container(cfg.dense.sgbm)
    assert cfg.dense.max_image_size == 1024  # the scored flights' settings are untouched
    with pytest.raises(ValueError, match="unknown dense settings"):
        exploration_values(reconstruct_cfg(**{"proxy.dense": {"max_image_sise": 640}}))
    # A nested section is overridden key by key: the other fusion settings stay the scored flights'.
    cfg = reconstruct_cfg(**{"proxy.dense": {"fusion": {"method": "colmap"}}, "dense.fusion.method": "rays"})
    fusion = exploration_values(cfg)["dense"]["fusion"]
    assert fusion == {**OmegaConf.to_container(cfg.dense.fusion), "method": "colmap"}
    with pytest.raises(ValueError, match=r"proxy\.dense\.fusion: unknown dense settings \['methd'\]"):
        exploration_values(reconstruct_cfg(**{"proxy.dense": {"fusion": {"methd": "colmap"}}}))


def test_the_proxy_keeps_the_former_matcher_and_normal_tolerance_and_its_cache_key():
    from reconstruct.cache_keys import proxy_settings

    cfg = reconstruct_cfg()
    assert cfg.dense.fusion.max_normal_error == 30.0  # the scored flights (SGBM's depth-derived normals)
    assert cfg.dense.sgbm.p1_per_block_pixel == 0.8 and cfg.dense.sgbm.crop_to_overlap
    proxy_dense = exploration_values(cfg)["dense"]
    assert proxy_dense["fusion"]["max_normal_error"] == 10.0
    assert proxy_dense["sgbm"]["p1_per_block_pixel"] == 8.0 and not proxy_dense["sgbm"]["crop_to_overlap"]
    # Spelled out at their former values, the proxy's settings key its proxies as before they were
    # spelled out, when the scored flights had those values too.
    former = reconstruct_cfg()
    del former.proxy.dense.fusion["max_normal_error"]
    for key in ("p1_per_block_pixel", "crop_to_overlap"):
        del former.proxy.dense.sgbm[key]
    former.dense.fusion.max_normal_error = 10.0
    former.dense.sgbm.p1_per_block_pixel = 8.0
    del former.dense.sgbm["crop_to_overlap"]
    assert proxy_settings(exploration_values(cfg)) == proxy_settings(exploration_values(former))
    for changed in ("proxy.dense.fusion.max_normal_error", "proxy.dense.sgbm.p1_per_block_pixel"):
        other = reconstruct_cfg(**{changed: 20.0})
        assert proxy_settings(exploration_values(other)) != proxy_settings(exploration_values(cfg))


def _flight_of_images(image_dir: Path, images, intr: Intrinsics) -> Path:
    image_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, image in enumerate(images):
        name = f"{i:06d}.png"
        cv2.imwrite(str(image_dir / name), image)
        rot, t = cam_from_world(np.array([2.0 * i, 0.0, 10.0, 90.0, -90.0]))
        entries.append(
            {
                "name": name,
                "viewpoint": [2.0 * i, 0.0, 10.0, 90.0, -90.0],
                "kind": "test",
                "cam_from_world": {"rotation": rot.tolist(), "translation": t.tolist()},
            }
        )
    (image_dir / "cameras.json").write_text(json.dumps({"intrinsics": intr.as_dict(), "images": entries}))
    return image_dir


def test_failures_carry_a_record(tmp_path):
    intr = Intrinsics(128, 96, 60.0)
    cfg = reconstruct_cfg()
    flat = [np.full((96, 128), 128, np.uint8) for _ in range(2)]
    with pytest.raises(ReconstructionError, match="at least 3") as info:
        reconstruct_flight(
            _flight_of_images(tmp_path / "two", flat, intr), tmp_path / "out_two", recon_settings(cfg), 0
        )
    assert info.value.record["status"] == "failed" and info.value.record["stage"] == "input"
    assert info.value.record["n_images"] == 2

    flat = [np.full((96, 128), 128, np.uint8) for _ in range(4)]
    with pytest.raises(ReconstructionError, match="SIFT features") as info:
        reconstruct_flight(
            _flight_of_images(tmp_path / "flat", flat, intr), tmp_path / "out_flat", recon_settings(cfg), 0
        )
    assert info.value.record["stage"] == "extraction"
    assert info.value.record["registered_fraction"] == 0.0
    stored = json.loads((tmp_path / "out_flat" / "recon.json").read_text())
    assert stored["status"] == "failed"

    # Unrelated noise images: features, but nothing that registers.
    rng = np.random.default_rng(0)
    noise = [cv2.GaussianBlur(rng.integers(0, 255, (96, 128), dtype=np.uint8), (3, 3), 0) for _ in range(4)]
    with pytest.raises(ReconstructionError) as info:
        reconstruct_flight(
            _flight_of_images(tmp_path / "noise", noise, intr), tmp_path / "out_noise", recon_settings(cfg), 0
        )
    assert info.value.record["stage"] == "mapping"
    assert info.value.record["registered_fraction"] < cfg.min_registered_fraction


def test_poisson_proxy_of_a_sampled_box(tmp_path):
    """A clean oriented sample of a box on the ground meshes back within a few centimetres."""
    import open3d as o3d

    box = trimesh.creation.box(bounds=np.array([[-2.0, -1.5, 0.0], [2.0, 1.5, 2.0]]))
    ground = trimesh.creation.box(bounds=np.array([[-5.0, -5.0, -0.5], [5.0, 5.0, 0.0]]))
    world = trimesh.util.concatenate([box, ground])
    points, faces = trimesh.sample.sample_surface_even(world, 30000, seed=0)
    # Only what a flight sees: the ground's top outside the box's footprint, the box's walls and roof.
    under_box = (np.abs(points[:, 0]) < 2.0) & (np.abs(points[:, 1]) < 1.5) & (points[:, 2] < 1e-6)
    keep = (points[:, 2] >= -1e-6) & ~under_box
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
    cloud.normals = o3d.utility.Vector3dVector(world.face_normals[faces[keep]])
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), cloud)
    cfg = reconstruct_cfg(**{"proxy.face_budget": 5000, "proxy.voxel_size_m": 0.03, "proxy.poisson_depth": 8})
    mesh = poisson_proxy(
        tmp_path / "cloud.ply", Box((-4.5, -4.5, -1.0), (4.5, 4.5, 5.0)), recon_settings(cfg).proxy
    )
    assert len(mesh.faces) <= 5000
    on_box = trimesh.sample.sample_surface_even(box, 3000, seed=1)[0]
    on_box = on_box[on_box[:, 2] > 0.05]
    assert np.percentile(trimesh.proximity.closest_point(mesh, on_box)[1], 95) < 0.06
    assert np.percentile(trimesh.proximity.closest_point(world, mesh.vertices)[1], 95) < 0.06


def test_oriented_cloud_is_cropped_downsampled_and_unit_length(tmp_path):
    import open3d as o3d

    # A 4 x 4 m plane sampled every 2 cm with normals of length 3, plus points outside the box.
    ticks = np.arange(0.0, 4.0, 0.02)
    x, y = np.meshgrid(ticks, ticks)
    plane = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    outside = plane[:100] + [0.0, 0.0, 10.0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack([plane, outside])))
    cloud.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 3.0], (len(plane) + 100, 1)))
    path = tmp_path / "dense.ply"
    o3d.io.write_point_cloud(str(path), cloud)
    box = Box((-1.0, -1.0, -1.0), (5.0, 5.0, 1.0))
    out = oriented_cloud(path, box, voxel_m=0.1)
    assert 40 * 40 <= len(out["points"]) <= 41 * 41  # one point per 10 cm voxel of the 4 m square
    assert np.all(out["points"][:, 2] == 0.0)
    np.testing.assert_allclose(out["normals"], np.tile([0.0, 0.0, 1.0], (len(out["normals"]), 1)))
    bare = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(plane))
    o3d.io.write_point_cloud(str(tmp_path / "bare.ply"), bare)
    assert (
        len(oriented_cloud(tmp_path / "bare.ply", Box((-1.0, -1.0, -1.0), (5.0, 5.0, 1.0)), 0.1)["points"])
        == 0
    )


def test_degraded_ground_truth_is_cropped_decimated_and_noised():
    box = trimesh.creation.box(bounds=np.array([[-2.0, -3.0, 0.0], [2.0, 3.0, 3.0]]))
    ground = np.array([[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [50.0, 50.0, 0.0], [-50.0, 50.0, 0.0]])
    scene = Scene(
        "boxes",
        [
            MeshPart("ground", ground, np.array([[0, 1, 2], [0, 2, 3]])),
            MeshPart("box", box.vertices, box.faces),
        ],
        {},
        structure_bounds=Box((-2.0, -3.0, 0.0), (2.0, 3.0, 3.0)),
        evaluation_region=Box((-7.0, -8.0, -0.5), (7.0, 8.0, 4.0)),
    )
    cfg = reconstruct_cfg(**{"proxy.face_budget": 2000, "proxy.degraded.noise_sigma_m": 0.05})
    mesh = degraded_ground_truth(scene, recon_settings(cfg).proxy, seed=0)
    assert 1000 < len(mesh.faces) <= 2000
    assert np.all(mesh.bounds[0] > [-7.5, -8.5, -0.5]) and np.all(mesh.bounds[1] < [7.5, 8.5, 3.5])
    distance = trimesh.proximity.closest_point(scene.ground_truth_mesh, mesh.vertices)[1]
    # |N(0, 0.05)| has median 0.0337 m.
    assert np.median(distance) == pytest.approx(0.0337, rel=0.2)
    again = degraded_ground_truth(scene, recon_settings(cfg).proxy, seed=0)
    assert np.array_equal(again.vertices, mesh.vertices)
    exact = degraded_ground_truth(
        scene, recon_settings(reconstruct_cfg(**{"proxy.degraded.noise_sigma_m": 0.0})).proxy, seed=0
    )
    assert trimesh.proximity.closest_point(scene.ground_truth_mesh, exact.vertices)[1].max() < 1e-6


def test_written_normal_map_is_planar_like_colmap(tmp_path):
    """COLMAP's .bin maps are stored channel by channel (header ``W&H&C&``)."""
    normals = np.zeros((2, 3, 3), np.float32)
    normals[..., 0], normals[..., 2] = 0.6, -0.8
    write_maps(tmp_path, "a.png", np.full((2, 3), 5.0, np.float32), normals)
    raw = (tmp_path / "stereo" / "normal_maps" / "a.png.geometric.bin").read_bytes()
    header = b"3&2&3&"
    assert raw.startswith(header)
    data = np.frombuffer(raw[len(header) :], np.float32)
    assert np.allclose(data, np.repeat([0.6, 0.0, -0.8], 6))


def test_dense_backend_auto_is_the_cpu_back_end_measured_best():
    from reconstruct.dense import select_backend

    assert select_backend("auto") == "cpu"  # even where pycolmap has CUDA (archive/pre_p1/limitations.md)
    assert select_backend("oracle") == "oracle"
    assert select_backend("cpu") == "cpu"
    if not pycolmap.has_cuda:
        with pytest.raises(ValueError, match="no CUDA"):
            select_backend("cuda")
    with pytest.raises(ValueError, match="backend"):
        select_backend("opencl")


def test_flight_key_ignores_render_timings_but_not_poses_or_pixels(box_flight, tmp_path):
    import json
    import shutil

    copy = Path(shutil.copytree(box_flight, tmp_path / "flight"))
    key = flight_content_key(copy, read_flight(copy), reconstruct_cfg(), 0)
    cameras_path = copy / "cameras.json"
    cameras = json.loads(cameras_path.read_text())
    # A re-render of the same flight writes other timings: the reconstruction must be reused.
    cameras.update(render_time_s=123.0, build_time_s=4.5, images_per_s=0.1)
    cameras_path.write_text(json.dumps(cameras))
    assert flight_content_key(copy, read_flight(copy), reconstruct_cfg(), 0) == key
    cameras["images"][0]["cam_from_world"]["translation"][0] += 0.01
    cameras_path.write_text(json.dumps(cameras))
    moved = flight_content_key(copy, read_flight(copy), reconstruct_cfg(), 0)
    assert moved != key
    first = copy / cameras["images"][0]["name"]
    image = cv2.imread(str(first))
    image[0, 0] = 255 - image[0, 0]
    cv2.imwrite(str(first), image)
    assert flight_content_key(copy, read_flight(copy), reconstruct_cfg(), 0) not in (key, moved)


def test_dense_workspace_can_be_dropped_without_changing_the_key(box_flight, box_reconstruction, tmp_path):
    _, kept = box_reconstruction
    cfg = reconstruct_cfg(keep_dense_workspace=False)
    record = reconstruct_flight(box_flight, tmp_path, recon_settings(cfg), seed=0)
    assert not (tmp_path / "dense").exists() and (tmp_path / "dense.ply").is_file()
    assert record["dense_workspace_freed_mb"] > 1.0  # 33 views of depth + normal maps
    assert record["content_key"] == kept["content_key"]
    assert record["n_registered"] == kept["n_registered"] == 33
    assert reconstruct_flight(box_flight, tmp_path, recon_settings(cfg), seed=0)["cached"] is True


def _model_state(sparse_dir: Path) -> tuple:
    """Registered names, point count, camera centres and point positions of a written model."""
    rec = pycolmap.Reconstruction(sparse_dir)
    ids = sorted(rec.reg_image_ids())
    names = [rec.image(i).name for i in ids]
    centres = np.array([rec.image(i).projection_center() for i in ids])
    points = np.array([rec.point3D(i).xyz for i in sorted(rec.points3D)])
    return names, rec.num_points3D(), centres, points


def test_deterministic_mode_reconstructs_a_flight_twice_to_the_bit(box_flight, tmp_path):
    cfg = reconstruct_cfg(**{"deterministic": True, "proxy.dense": {}})
    states, clouds, proxies = [], [], []
    for attempt in range(2):
        out_dir = tmp_path / f"attempt{attempt}"
        mesh, record = build_proxy(box_flight, out_dir, recon_settings(cfg), seed=0)
        assert record["deterministic"] is True and record["cached"] is False
        states.append(_model_state(out_dir / "sparse"))
        clouds.append((out_dir / "dense.ply").read_bytes())
        proxies.append((out_dir / "proxy.ply").read_bytes())
    (names_a, n_a, centres_a, points_a), (names_b, n_b, centres_b, points_b) = states
    assert names_a == names_b and len(names_a) == 33
    assert n_a == n_b > 500  # 951 points from 33 views of 320 x 240
    np.testing.assert_array_equal(centres_a, centres_b)  # to the bit, not within a tolerance
    np.testing.assert_array_equal(points_a, points_b)
    assert clouds[0] == clouds[1] and len(clouds[0]) > 100_000
    assert proxies[0] == proxies[1]


def test_deterministic_mode_is_part_of_the_flight_key(box_flight):
    flight = read_flight(box_flight)
    cfgs = [reconstruct_cfg(**{"deterministic": on}) for on in (False, True)]
    keys = {flight_content_key(box_flight, flight, cfg, 0) for cfg in cfgs}
    assert len(keys) == 2


def test_image_ids_follow_the_flight_order(box_flight, box_reconstruction):
    """The extractor's threads finish in any order; the database's ids must not follow them."""
    out_dir, _ = box_reconstruction
    flight = read_flight(box_flight)
    with pycolmap.Database.open(out_dir / "database.db") as db:
        by_id = sorted((image.image_id, image.name) for image in db.read_all_images())
    assert [name for _, name in by_id] == list(flight.names)


def test_true_pose_model_puts_every_camera_at_its_true_pose(box_flight, box_reconstruction, tmp_path):
    """benchmarks.dense --true-poses: the copy's cameras are the simulation's (1e-9 m, 1e-4 deg)."""
    from benchmarks.dense import true_pose_model

    out_dir, record = box_reconstruction
    assert record["position_error_median_m"] > 1e-4  # SfM's cameras are off by millimetres at least
    copy = pycolmap.Reconstruction(true_pose_model(out_dir / "sparse", box_flight, tmp_path / "true"))
    errors = pose_errors(copy, read_flight(box_flight))
    assert errors["n_registered"] == 33
    assert errors["position_error_max_m"] < 1e-9 and errors["rotation_error_max_deg"] < 1e-4  # arccos near 1
    assert copy.num_points3D() == pycolmap.Reconstruction(out_dir / "sparse").num_points3D()


def test_reference_views_cover_each_sparse_point_k_times():
    """Views 0-4 see points 0-29, view 5 alone sees points 30-39. Two views per point: the cover
    takes views 0 and 1 for the shared points, then view 5 for its ten, unless a view must add more
    than ten under-covered points."""
    incidence = np.zeros((6, 40), dtype=np.int8)
    incidence[:5, :30] = 1
    incidence[5, 30:] = 1
    assert reference_views(incidence, 2, 5).tolist() == [True, True, False, False, False, True]
    assert reference_views(incidence, 2, 11).tolist() == [True, True, False, False, False, False]
    assert reference_views(incidence, 5, 1).tolist() == [True] * 6
    with pytest.raises(ValueError, match="must be >= 1"):
        reference_views(incidence, 0, 1)


def test_bench_dense_knows_the_settings_whose_default_is_null(tmp_path):
    """A variant may set fusion.max_memory_gb or reference_views_per_point (null by default); a
    misspelt setting is refused by name before any work."""
    from benchmarks.dense import run_variant

    overrides = ["fusion.max_memory_gb=2", "reference_views_per_point=8", "num_partner=3"]
    with pytest.raises(ValueError, match=r"unknown dense settings \['num_partner'\]"):
        run_variant(tmp_path, tmp_path / "out", overrides, scene=None, eval_settings=None)
    assert not (tmp_path / "out").exists()


def test_bench_dense_cover_counts_the_views_of_a_sparse_model(tmp_path):
    """pycolmap's synthetic model (30 views, 300 points each seen by every view): its tracks are
    30 long, so K = 30 keeps every view and K = 1 keeps one view (it sees all 300 points)."""
    from benchmarks.dense import cover_sizes

    _, truth = synthetic_dataset(tmp_path)
    (tmp_path / "run" / "recon" / "sparse").mkdir(parents=True)
    truth.write(tmp_path / "run" / "recon" / "sparse")
    tracks = [truth.point3D(p).track.length() for p in truth.point3D_ids()]
    cover = cover_sizes(tmp_path / "run", [1, 30], min_new_points=1)
    assert cover["n_views"] == truth.num_reg_images() == 30
    assert cover["n_points"] == len(tracks)
    assert cover["mean_track"] == pytest.approx(np.mean(tracks))
    assert cover["kept"] == {1: 1, 30: 30}
