"""The COLMAP dense workspace every dense back-end shares: the undistorted views and their
cameras, each view's stereo partners and most overlapping views, and the depth and normal maps on
disk (``stereo/depth_maps``, ``stereo/normal_maps``, COLMAP's format). Positions in metres, in the
model frame.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap

from reconstruct.rectify import rectify_pair
from scene.io import write_atomic, write_text_atomic

if TYPE_CHECKING:
    from reconstruct.dense_settings import DenseSettings

log = logging.getLogger(__name__)

DEPTH_SUFFIX = ".geometric.bin"


@dataclass(frozen=True)
class View:
    """One undistorted workspace image: OpenCV intrinsics, cam_from_world, centre (metres)."""

    name: str
    K: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return -self.rotation.T @ self.translation

    @property
    def forward(self) -> np.ndarray:
        """Optical axis (3,) in the world frame."""
        return self.rotation[2]


def prepare_workspace(
    sparse_dir: Path,
    image_dir: Path,
    workspace: Path,
    settings: DenseSettings,
    *,
    downscale_first: bool = False,
) -> Path:
    """Undistort the images of the sparse model into a fresh COLMAP dense workspace; return it.

    Images are rescaled so their longest side is at most ``settings.max_image_size`` pixels. A model
    whose cameras are all PINHOLE and no larger than that needs neither: its images are linked
    into the workspace as they are (COLMAP's undistorter would decode and re-encode every one).
    Otherwise COLMAP's undistorter resamples each image at its full size and then downsizes it;
    ``downscale_first`` (``reconstruct.dense.downscale_before_undistorting``) downsizes first and
    undistorts at the workspace's size (``_downscaled_workspace``).
    """
    workspace = Path(workspace)
    shutil.rmtree(workspace, ignore_errors=True)
    workspace.parent.mkdir(parents=True, exist_ok=True)
    max_size = settings.max_image_size
    rec = pycolmap.Reconstruction(sparse_dir)
    if all(
        cam.model == pycolmap.CameraModelId.PINHOLE and max(cam.width, cam.height) <= max_size
        for cam in rec.cameras.values()
    ):
        _link_workspace(rec, Path(image_dir), workspace)
        return workspace
    if downscale_first:
        _downscaled_workspace(rec, Path(image_dir), workspace, max_size)
        return workspace
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = max_size
    pycolmap.undistort_images(
        workspace, sparse_dir, image_dir, output_type="COLMAP", undistort_options=options
    )
    _match_cameras_to_images(workspace)
    return workspace


def _link_workspace(rec: pycolmap.Reconstruction, image_dir: Path, workspace: Path) -> None:
    """The workspace ``undistort_images`` would write for an undistorted model at full size: images
    hard-linked (copied across file systems), the model, and ``stereo/patch-match.cfg`` with
    COLMAP's automatic choice of 20 source images per view."""
    (workspace / "images").mkdir(parents=True)
    names = sorted(rec.image(i).name for i in rec.reg_image_ids())
    for name in names:
        source, target = image_dir / name, workspace / "images" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(source, target)
        except OSError:
            shutil.copyfile(source, target)
    _write_model_and_stereo_config(rec, workspace, names)


def _downscaled_workspace(
    rec: pycolmap.Reconstruction, image_dir: Path, workspace: Path, max_size: int
) -> None:
    """The workspace ``undistort_images`` writes, with each image downsized to ``max_size`` (px,
    longest side) before it is undistorted rather than after.

    COLMAP's order resamples every pixel of the full-size photo through the lens model (62 s CPU
    for 100 photos of 1280 px); downsizing first (area averaging) and undistorting the small image
    costs a few seconds and keeps what a ``max_size`` depth map can see. The cameras are COLMAP's
    (``undistort_camera`` of the downsized camera, same options), the keypoints move with them.
    """
    options = pycolmap.UndistortCameraOptions()
    options.max_image_size = max_size
    downsized, undistorted = {}, {}
    for camera_id, camera in rec.cameras.items():
        small = pycolmap.Camera(
            model=camera.model,
            width=camera.width,
            height=camera.height,
            params=camera.params,
            camera_id=camera_id,
        )
        scale = min(1.0, max_size / max(camera.width, camera.height))
        small.rescale(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
        downsized[camera_id] = small
        undistorted[camera_id] = pycolmap.undistort_camera(options, small)
    (workspace / "images").mkdir(parents=True)
    names = []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        small = downsized[image.camera_id]
        bgr = cv2.imread(str(image_dir / image.name), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{image_dir / image.name}: unreadable image")
        bgr = cv2.resize(bgr, (small.width, small.height), interpolation=cv2.INTER_AREA)
        bitmap, _ = pycolmap.undistort_image(
            options, pycolmap.Bitmap.from_array(np.ascontiguousarray(bgr[:, :, ::-1])), small
        )
        target = workspace / "images" / image.name
        target.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(target), np.ascontiguousarray(bitmap.to_array()[:, :, ::-1])):
            raise ValueError(f"{target}: could not write the undistorted image")
        if image.points2D:
            original = rec.camera(image.camera_id)
            xy = np.array([p.xy for p in image.points2D])
            rays = original.cam_from_img(xy)
            moved = undistorted[image.camera_id].img_from_cam(np.column_stack([rays, np.ones(len(rays))]))
            for point, new_xy in zip(image.points2D, moved, strict=True):
                point.xy = new_xy
        names.append(image.name)
    for camera_id, camera in undistorted.items():
        camera.camera_id = camera_id
        rec.cameras[camera_id] = camera
    _write_model_and_stereo_config(rec, workspace, sorted(names))


def _write_model_and_stereo_config(rec: pycolmap.Reconstruction, workspace: Path, names: list[str]) -> None:
    """The workspace's ``sparse/`` model, its empty map folders and ``stereo/patch-match.cfg`` with
    COLMAP's automatic choice of 20 source images per view."""
    (workspace / "sparse").mkdir()
    rec.write(workspace / "sparse")
    stereo = workspace / "stereo"
    for folder in ("depth_maps", "normal_maps", "consistency_graphs"):
        (stereo / folder).mkdir(parents=True)
    write_text_atomic(stereo / "patch-match.cfg", "".join(f"{n}\n__auto__, 20\n" for n in names))


def _match_cameras_to_images(workspace: Path) -> None:
    """Rescale the workspace's cameras to the size of their undistorted images.

    COLMAP 3.13 / pycolmap 4.0.4's undistorter downsizes every image to ``max_image_size`` but
    leaves cameras that need no undistortion (PINHOLE, like the simulated survey camera) at their
    old size in ``sparse/``: depth maps computed from that model would be scaled wrongly.
    """
    rec = pycolmap.Reconstruction(workspace / "sparse")
    sizes = {}
    for image in rec.images.values():
        if image.camera_id not in sizes:
            bitmap = cv2.imread(str(workspace / "images" / image.name), cv2.IMREAD_UNCHANGED)
            if bitmap is None:
                raise ValueError(f"{workspace / 'images' / image.name}: unreadable undistorted image")
            sizes[image.camera_id] = (bitmap.shape[1], bitmap.shape[0])
    stale = {
        cid: size for cid, size in sizes.items() if size != (rec.camera(cid).width, rec.camera(cid).height)
    }
    for camera_id, (width, height) in stale.items():
        rec.camera(camera_id).rescale(width, height)
    if stale:
        rec.write(workspace / "sparse")


def read_views(workspace: Path) -> dict[str, View]:
    """The undistorted views of a workspace by image name."""
    rec = pycolmap.Reconstruction(Path(workspace) / "sparse")
    views = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        cam = image.camera
        if cam.model != pycolmap.CameraModelId.PINHOLE:
            raise ValueError(
                f"{workspace}: undistorted camera of {image.name} is {cam.model}, expected PINHOLE"
            )
        fx, fy, cx, cy = cam.params
        K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        pose = image.cam_from_world()
        views[image.name] = View(
            image.name,
            K,
            pose.rotation.matrix(),
            np.asarray(pose.translation),
            int(cam.width),
            int(cam.height),
        )
    return views


def select_partners(
    workspace: Path, views: Mapping[str, View], settings: DenseSettings
) -> dict[str, list[str]]:
    """Stereo partners of every view, best first (the rules are ``settings``' fields, angles in
    degrees).

    A partner shares at least ``min_shared_points`` sparse points with the reference, its median
    triangulation angle at those points lies in [``min_triangulation_angle_deg``,
    ``max_triangulation_angle_deg``] (too small: poor depth resolution; too large: poor matching),
    and the baseline makes at least ``min_baseline_axis_angle_deg`` with both optical axes (the
    epipoles stay far outside the images, so rectification does not blow up). With
    ``partners_must_rectify`` the pair must also rectify onto a canvas of at most
    ``max_rectified_area_ratio`` times the image (``reconstruct.rectify``), the test the matcher
    applies: a pair it would drop gets no partner slot. Among those, the
    ``num_partners`` with the highest score are kept: shared points, scaled down linearly for
    angles below ``partner_ideal_angle_deg`` (a wider angle gives a finer depth resolution).
    """
    model = pycolmap.MVSModel()
    model.read(str(workspace), "COLMAP")
    shared = model.compute_shared_points()
    angles = model.compute_triangulation_angles(50.0)
    lo = math.radians(settings.min_triangulation_angle_deg)
    hi = math.radians(settings.max_triangulation_angle_deg)
    min_axis = math.radians(settings.min_baseline_axis_angle_deg)
    min_shared = settings.min_shared_points
    num_partners = settings.num_partners
    ideal = max(math.radians(settings.partner_ideal_angle_deg), 1e-6)
    must_rectify = settings.partners_must_rectify
    max_area = settings.max_rectified_area_ratio
    partners: dict[str, list[str]] = {}
    for ref_idx in range(len(shared)):
        ref_name = model.get_image_name(ref_idx)
        ref = views[ref_name]
        candidates = []
        for src_idx, n_shared in shared[ref_idx].items():
            angle = angles[ref_idx].get(src_idx, 0.0)
            if n_shared < min_shared or not (lo <= angle <= hi):
                continue
            src = views[model.get_image_name(src_idx)]
            baseline = src.center - ref.center
            norm = np.linalg.norm(baseline)
            if norm == 0:
                continue
            cos_axes = np.abs(np.array([ref.forward @ baseline, src.forward @ baseline])) / norm
            if np.any(np.arccos(np.clip(cos_axes, 0.0, 1.0)) < min_axis):
                continue
            if must_rectify and rectify_pair(ref, src, max_area_ratio=max_area) is None:
                continue
            candidates.append((n_shared * min(1.0, angle / ideal), src.name))
        candidates.sort(reverse=True)
        partners[ref_name] = [name for _, name in candidates[:num_partners]]
    return partners


def stereo_baselines(
    views: Mapping[str, View], partners: Mapping[str, list[str]], partner_weights: str
) -> dict[str, float]:
    """Every view's stereo baseline (m): the ``B`` of its depth map's noise ``z^2 / (f B) s``.

    ``partner_weights: precision`` (``reconstruct.dense``) combines the partners' depths weighted by
    their precision (``B_k^2``), so the combined map's noise is that of one pair with baseline
    ``sqrt(sum B_k^2)`` (every partner measuring the pixel; fewer is coarser). ``equal``: the former
    rule, the first (best-scored) partner's baseline.
    """
    out = {}
    for name, chosen in partners.items():
        if not chosen:
            continue
        lengths = [float(np.linalg.norm(views[p].center - views[name].center)) for p in chosen]
        precision = partner_weights == "precision"
        out[name] = float(np.sqrt(np.sum(np.square(lengths)))) if precision else lengths[0]
    return out


def overlapping_views(workspace: Path) -> dict[str, list[str]]:
    """Every view's other views by the sparse points they share with it, most first."""
    model = pycolmap.MVSModel()
    model.read(str(workspace), "COLMAP")
    shared = model.compute_shared_points()
    return {
        model.get_image_name(ref): [
            model.get_image_name(src) for src, _ in sorted(shared[ref].items(), key=lambda kv: -kv[1])
        ]
        for ref in range(len(shared))
    }


def write_maps(workspace: Path, name: str, depth: np.ndarray, normals: np.ndarray) -> None:
    """Write a geometric depth map (0 = none) and normal map in COLMAP's format, atomically."""
    stereo = Path(workspace) / "stereo"
    depth = np.where(np.isfinite(depth) & np.any(normals != 0, axis=-1), depth, 0.0).astype(np.float32)
    positive = depth[depth > 0]
    lo, hi = (float(positive.min()), float(positive.max())) if len(positive) else (0.0, 1.0)
    depth_map = pycolmap.DepthMap.from_array(depth, lo, hi)
    normals = np.where((depth > 0)[..., None], normals, 0.0).astype(np.float32)
    # pycolmap 4.0.4's NormalMap.from_array copies the (H, W, 3) buffer verbatim, but COLMAP stores
    # maps channel by channel: hand it the planar buffer (tests/test_reconstruct.py checks the file).
    planar = np.ascontiguousarray(normals.transpose(2, 0, 1)).reshape(normals.shape)
    normal_map = pycolmap.NormalMap.from_array(planar)
    write_atomic(stereo / "depth_maps" / f"{name}{DEPTH_SUFFIX}", lambda p: depth_map.write(p))
    write_atomic(stereo / "normal_maps" / f"{name}{DEPTH_SUFFIX}", lambda p: normal_map.write(p))


def sparse_points_by_image(workspace: Path) -> dict[str, np.ndarray]:
    """The sparse world points (P, 3) each registered view of the workspace sees, by image name."""
    rec = pycolmap.Reconstruction(Path(workspace) / "sparse")
    points_by_name = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
        points_by_name[image.name] = np.array([rec.point3D(i).xyz for i in ids]) if ids else np.zeros((0, 3))
    return points_by_name


def read_maps(workspace: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """A view's geometric depth (H, W) (NaN where none) and camera-frame normals (H, W, 3)."""
    stereo = Path(workspace) / "stereo"
    depth_map = pycolmap.DepthMap()
    depth_map.read(str(stereo / "depth_maps" / f"{name}{DEPTH_SUFFIX}"))
    depth = depth_map.to_array().astype(np.float32)
    depth[~(depth > 0)] = np.nan
    normal_map = pycolmap.NormalMap()
    normal_map.read(str(stereo / "normal_maps" / f"{name}{DEPTH_SUFFIX}"))
    h, w = depth.shape
    # COLMAP stores maps channel by channel (reconstruct.dense.write_maps).
    normals = normal_map.to_array().reshape(3, h, w).transpose(1, 2, 0).astype(np.float32)
    return depth, normals
