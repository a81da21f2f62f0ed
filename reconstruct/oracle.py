"""The matcher's ceiling: depth maps ray-cast from the ground truth at the registered SfM cameras.

``reconstruct.dense.backend=oracle`` replaces SGBM by what a perfect matcher would measure: for
every view the dense stage would give a depth map (one with a stereo partner), the ground truth is
ray-cast through each pixel from the view's *registered* pose (so registration and pose errors
still count), and the depth gets stereo noise of the pair the view would use:

    sigma_z = z^2 / (f * B) * disparity_sigma_px

(z the depth along the optical axis, f the focal length in pixels, B the baseline of the view's
combined depth map, ``reconstruct.workspace.stereo_baselines``: its partners' as the real back-end
combines them, metres). Normals are the ground truth's, turned to face the camera. The maps
are fused by the same fusion as the real back-end, so the fused cloud scores what the plan allows
once matching is perfect; its weights are the stereo model's alone, since no matching window spans
a slanted surface here (``reconstruct.dense.fusion_config``). A ray-cast per view costs a
fraction of one SGBM pair.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from reconstruct.dense_settings import DenseSettings
from reconstruct.stereo_noise import stereo_depth_sigma
from reconstruct.workspace import read_views, select_partners, stereo_baselines, write_maps
from scene.enclosure import raycasting_scene


def view_rays(K: np.ndarray, rotation: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) world directions through every pixel centre (OpenCV ``K``), scaled to unit depth
    along the optical axis: a hit at ray parameter t lies at depth t."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    return rays_cam @ rotation


def oracle_view(
    scene: o3d.t.geometry.RaycastingScene,
    center: np.ndarray,
    K: np.ndarray,
    rotation: np.ndarray,
    size: tuple[int, int],
    baseline_m: float,
    disparity_sigma_px: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """One view's noisy depth (H, W) float32 (NaN: the ray misses) and camera-frame normals (H, W, 3)
    facing the camera, from the ground truth ray-cast at pose (``rotation``, ``center``)."""
    width, height = size
    rays = view_rays(K, rotation, width, height)
    origins = np.broadcast_to(np.asarray(center, dtype=np.float64), rays.shape)
    query = np.concatenate([origins, rays], axis=-1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(query))
    depth = hit["t_hit"].numpy().reshape(height, width).astype(np.float64)
    normals_world = hit["primitive_normals"].numpy().reshape(height, width, 3).astype(np.float64)
    missed = ~np.isfinite(depth)
    depth[missed] = np.nan
    sigma = stereo_depth_sigma(np.nan_to_num(depth), K[0, 0], baseline_m, disparity_sigma_px)
    depth = depth + rng.standard_normal(depth.shape) * sigma
    depth[~(depth > 0)] = np.nan
    normals = normals_world @ rotation.T
    facing_away = np.einsum("hwc,hwc->hw", normals_world, rays) > 0
    normals[facing_away] *= -1.0
    normals[~np.isfinite(depth)] = 0.0
    return depth.astype(np.float32), normals.astype(np.float32)


def compute_depth_maps_oracle(
    workspace: Path, settings: DenseSettings, ground_truth: trimesh.Trimesh, seed: int
) -> dict[str, int]:
    """Oracle back-end: a depth and normal map for every view of the workspace that has a stereo
    partner (``select_partners``, as the CPU back-end chooses them); returns valid-pixel counts.

    Args:
        workspace: the dense workspace (undistorted images and the registered model).
        settings: the ``reconstruct.dense`` settings (``oracle.disparity_sigma_px``, px, and the
            partner rules).
        ground_truth: the ground-truth mesh in the model's frame (world metres).
        seed: seeds each view's noise (with the view's name).
    """
    workspace = Path(workspace)
    views = read_views(workspace)
    partners = select_partners(workspace, views, settings)
    sigma_px = settings.oracle.disparity_sigma_px
    baselines = stereo_baselines(views, partners, settings.partner_weights)
    scene = raycasting_scene(ground_truth)
    valid = {}
    for name in sorted(views):
        ref = views[name]
        if not partners.get(name):
            valid[name] = 0
            continue
        baseline = baselines[name]
        rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
        depth, normals = oracle_view(
            scene, ref.center, ref.K, ref.rotation, (ref.width, ref.height), baseline, sigma_px, rng
        )
        write_maps(workspace, name, depth, normals)
        valid[name] = int(np.count_nonzero(np.isfinite(depth)))
    return valid
