"""Photo-consistency of the proxy in the exploratory flight's own images (``ours_plus`` evidence).

The cloud signals of ``planner.ours.evidence`` read the exploration's fused cloud, so a surface that the
cloud itself places a few centimetres off looks sure to them. The images see it: a small patch of
the proxy's tangent plane around a sample, projected into the views that see it, shows the same
texture in every view only where the proxy lies on the true surface; off it, each view looks at a
slightly different piece of wall, and the patches decorrelate. This is the normalised cross-
correlation (NCC) score of plane-sweep and PatchMatch stereo, evaluated at the proxy instead of
searched for.

Per sample: the views of the exploration's aligned sparse model (its poses, not the true ones) that
see it unoccluded by the proxy, within ``max_incidence_deg`` of its normal, with the whole patch in
the image; the ``n_views`` most frontal of them; a ``patch_size`` x ``patch_size`` grid on the
tangent plane, one reference-view pixel apart; NCC of each other view's patch against the most
frontal one's; the sample's score is their mean. A patch too plain to correlate (grey-level
standard deviation below ``min_std`` in the reference view) or seen by fewer than two views gets
no score (NaN).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.ndimage import map_coordinates

from reconstruct.workspace import read_views
from scene.enclosure import raycasting_scene
from scene.plan import PlanningError


@dataclass(frozen=True)
class PhotoSettings:
    """``conf/planner/ours_plus.yaml``: ``evidence.photo``. Angles in degrees, grey levels 0-255."""

    n_views: int
    patch_size: int
    max_incidence_deg: float
    min_std: float
    ncc_lo: float  # mean NCC at or below which the photo signal is 1 (unsure) ...
    ncc_hi: float  # ... and at or above which it is 0

    @classmethod
    def from_config(cls, node: Mapping) -> PhotoSettings:
        s = cls(
            n_views=int(node["n_views"]),
            patch_size=int(node["patch_size"]),
            max_incidence_deg=float(node["max_incidence_deg"]),
            min_std=float(node["min_std"]),
            ncc_lo=float(node["ncc_lo"]),
            ncc_hi=float(node["ncc_hi"]),
        )
        if s.n_views < 2:
            raise PlanningError(f"planner ours_plus: evidence.photo.n_views must be >= 2, got {s.n_views}")
        if s.patch_size < 3 or s.patch_size % 2 == 0:
            raise PlanningError(
                f"planner ours_plus: evidence.photo.patch_size must be odd and >= 3, got {s.patch_size}"
            )
        if not 0.0 < s.max_incidence_deg < 90.0:
            raise PlanningError(
                "planner ours_plus: evidence.photo.max_incidence_deg must be in (0, 90), "
                f"got {s.max_incidence_deg}"
            )
        if not -1.0 <= s.ncc_lo < s.ncc_hi <= 1.0:
            raise PlanningError(
                "planner ours_plus: evidence.photo needs -1 <= ncc_lo < ncc_hi <= 1, "
                f"got {s.ncc_lo} and {s.ncc_hi}"
            )
        return s


@dataclass(frozen=True)
class PhotoViews:
    """Registered views of a flight: intrinsics (V, 3, 3) in OpenCV pixels (centre of the top-left
    pixel at 0), cam_from_world rotations (V, 3, 3) and translations (V, 3), grey images (V, H, W)."""

    K: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    images: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        return -np.einsum("vji,vj->vi", self.rotation, self.translation)

    @classmethod
    def from_reconstruction(cls, recon_dir: Path, image_dir: Path) -> PhotoViews:
        """The registered views of ``recon_dir/sparse`` (COLMAP, world frame) and their images."""
        views = sorted(read_views(Path(recon_dir)).values(), key=lambda v: v.name)
        if not views:
            raise PlanningError(f"{recon_dir}/sparse: no registered view for photo-consistency")
        images = []
        for view in views:
            gray = cv2.imread(str(Path(image_dir) / view.name), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise PlanningError(f"{image_dir / view.name}: missing or unreadable exploration image")
            images.append(gray)
        return cls(
            np.stack([v.K for v in views]),
            np.stack([v.rotation for v in views]),
            np.stack([v.translation for v in views]),
            np.stack(images),
        )


def _project(views: PhotoViews, points: np.ndarray, view_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (..., 2) and depths (...) of ``points`` (..., 3) in views ``view_ids`` (...)."""
    cam = np.einsum("...ij,...j->...i", views.rotation[view_ids], points) + views.translation[view_ids]
    depth = cam[..., 2]
    pix = np.einsum("...ij,...j->...i", views.K[view_ids], cam)
    return pix[..., :2] / np.where(np.abs(pix[..., 2:]) > 1e-12, pix[..., 2:], 1e-12), depth


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(normals, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(normals, u)


def photo_consistency(
    points: np.ndarray,
    normals: np.ndarray,
    proxy: trimesh.Trimesh,
    views: PhotoViews,
    s: PhotoSettings,
) -> dict[str, np.ndarray]:
    """Mean NCC (P,) of each sample's patch across its views (NaN: no score), and the views used.

    Args:
        points, normals: (P, 3) proxy samples and unit normals (world metres).
        proxy: the proxy mesh (occlusion).
        views: the exploration's registered views.
        s: the settings.

    Returns:
        ``ncc`` (P,) mean NCC against the most frontal view, ``n_views`` (P,) views that see the
        sample (before the ``s.n_views`` cut), ``signal`` (P,) in [0, 1] (0 where ``ncc`` is NaN).
    """
    # heavy (open3d): imported on use
    import open3d as o3d

    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    n_points, n_views = len(points), len(views.K)
    height, width = views.images.shape[1:]
    half = s.patch_size // 2

    # Which views see which samples: in front, within the incidence cone, the patch in the image.
    to_cam = views.centers[None] - points[:, None]  # (P, V, 3)
    dist = np.linalg.norm(to_cam, axis=2)
    cos = np.einsum("pvi,pi->pv", to_cam, normals) / np.maximum(dist, 1e-12)
    view_ids = np.broadcast_to(np.arange(n_views), (n_points, n_views))
    pix, depth = _project(views, np.broadcast_to(points[:, None], (n_points, n_views, 3)), view_ids)
    margin = half + 2
    seen = (
        (depth > 0)
        & (cos >= np.cos(np.radians(s.max_incidence_deg)))
        & (pix[..., 0] >= margin)
        & (pix[..., 0] <= width - 1 - margin)
        & (pix[..., 1] >= margin)
        & (pix[..., 1] <= height - 1 - margin)
    )
    # Occlusion by the proxy: a ray from just off the surface towards the camera must reach it.
    p_idx, v_idx = np.nonzero(seen)
    if len(p_idx):
        origins = points[p_idx] + normals[p_idx] * 0.05
        directions = to_cam[p_idx, v_idx] / dist[p_idx, v_idx, None]
        rays = np.hstack([origins, directions]).astype(np.float32)
        hit = raycasting_scene(proxy).cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        blocked = hit < dist[p_idx, v_idx] - 0.1
        seen[p_idx[blocked], v_idx[blocked]] = False
    n_seen = seen.sum(axis=1)

    # The most frontal views of each sample, the first being the reference.
    k = min(s.n_views, n_views)
    order = np.argsort(np.where(seen, -cos, np.inf), axis=1)[:, :k]  # (P, k)
    chosen_seen = np.take_along_axis(seen, order, axis=1)
    ref = order[:, 0]
    # Patch grid on the tangent plane, one reference pixel apart.
    u, v = _tangent_basis(normals)
    ref_depth = np.take_along_axis(depth, ref[:, None], axis=1)[:, 0]
    step = np.abs(ref_depth) / views.K[ref, 0, 0]
    offsets = np.arange(-half, half + 1, dtype=float)
    du, dv = np.meshgrid(offsets, offsets, indexing="ij")
    grid = (
        points[:, None]
        + (du.ravel()[None, :, None] * u[:, None] + dv.ravel()[None, :, None] * v[:, None])
        * step[:, None, None]
    )  # (P, G, 3)
    patches = np.full((n_points, k, grid.shape[1]), np.nan)
    for j in range(k):
        ids = order[:, j]
        for view in np.unique(ids[chosen_seen[:, j]]):
            rows = np.nonzero((ids == view) & chosen_seen[:, j])[0]
            pix_v, _ = _project(views, grid[rows], np.full(grid[rows].shape[:2], view))
            patches[rows, j] = map_coordinates(
                views.images[view],
                [pix_v[..., 1].ravel(), pix_v[..., 0].ravel()],
                order=1,
                output=np.float64,
            ).reshape(len(rows), -1)
    centred = patches - patches.mean(axis=2, keepdims=True)
    norm = np.linalg.norm(centred, axis=2)
    unit = centred / np.where(norm > 1e-9, norm, np.nan)[..., None]
    ncc = np.einsum("pg,pjg->pj", unit[:, 0], unit[:, 1:])  # (P, k - 1), NaN where a view is missing
    ref_std = patches[:, 0].std(axis=1)  # NaN where no view sees the sample
    valid = chosen_seen[:, 1:] & np.isfinite(ncc)
    with np.errstate(invalid="ignore"):
        mean = np.where(valid.any(axis=1), np.nansum(np.where(valid, ncc, 0.0), 1) / valid.sum(1), np.nan)
    mean = np.where((ref_std >= s.min_std) & (n_seen >= 2), mean, np.nan)
    signal = np.clip((s.ncc_hi - mean) / (s.ncc_hi - s.ncc_lo), 0.0, 1.0)
    return {"ncc": mean, "n_views": n_seen, "signal": np.where(np.isfinite(mean), signal, 0.0)}
