"""Dense reconstruction: depth + normal maps in a standard COLMAP workspace, fused by pycolmap.

Two back-ends write the same workspace (``images/``, ``sparse/``, ``stereo/depth_maps``,
``stereo/normal_maps``), then ``pycolmap.stereo_fusion`` fuses the geometric maps into a point cloud
in the frame of the sparse model (the world frame once it is aligned):

- ``cpu``: OpenCV semi-global matching on rectified pairs of each reference view with its best
  partner views (shared sparse points, triangulation angle, sideways baseline), disparities turned
  into depth along the reference rays, a multi-partner consistency filter, normals from the depth
  gradients;
- ``cuda``: ``pycolmap.patch_match_stereo`` (needs a CUDA build of pycolmap).

Pixel coordinates here are OpenCV's (pixel centres at integers); COLMAP's pinhole parameters are
shifted by half a pixel when the intrinsic matrices are built.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from reconstruct.dense_settings import (
    BACKENDS,
    OPENCV_P1_PER_BLOCK_PIXEL,
    OPENCV_P2_PER_BLOCK_PIXEL,
    DenseSettings,
)
from reconstruct.depth_filter import edge_pixels, geometric_support
from reconstruct.rectify import DEFAULT_MAX_AREA_RATIO, RectifiedPair, rectify_pair
from reconstruct.workspace import (
    DEPTH_SUFFIX,
    View,
    overlapping_views,
    prepare_workspace,
    read_views,
    select_partners,
    sparse_points_by_image,
    stereo_baselines,
    write_maps,
)
from scene.io import write_atomic, write_text_atomic

if TYPE_CHECKING:
    import scipy.sparse

log = logging.getLogger(__name__)

# A normal window whose depths spread more than this (relative) straddles an occlusion edge.
_MAX_WINDOW_DEPTH_JUMP = 0.05


def select_backend(requested: str) -> str:
    """The depth back-end to run: ``auto`` is the CPU back-end (SGBM), measured the better one here.

    The one CUDA measurement (PatchMatch on a 40-view 640 px tomb workspace, archive/pre_p1/limitations.md)
    was both slower end to end and less accurate than SGBM on 2 CPU cores, so ``auto`` does not pick
    CUDA merely because pycolmap has it; ``cuda`` asks for it. ``oracle`` ray-casts the ground truth
    (``reconstruct.oracle``): the matcher's ceiling, for simulated runs only.
    """
    if requested not in BACKENDS:
        raise ValueError(f"reconstruct.dense.backend must be one of {BACKENDS}, got {requested!r}")
    if requested == "auto":
        return "cpu"
    if requested == "cuda" and not pycolmap.has_cuda:
        raise ValueError(
            "reconstruct.dense.backend=cuda but this pycolmap has no CUDA (install pycolmap-cuda12)"
        )
    return requested


def disparity_search_range(pair: RectifiedPair, depth: np.ndarray, max_num_disparities: int):
    """SGBM (min_disparity, num_disparities) covering sparse points at rectified depths ``depth`` (m).

    The 2nd-98th percentile of their disparities, widened by 25 %; None with fewer than 5 points.
    When that span exceeds ``max_num_disparities``, the window of that width holding the most sparse
    points (80 % of it, with a tenth on each side as margin): a low view across the ground towards
    a wall sees disparities from the near ground to the far background, and a window anchored at
    the far end would leave out the wall in between.
    """
    depth = depth[depth > 0]
    if len(depth) < 5:
        return None
    disparity = np.sort(pair.K_rect[0, 0] * pair.baseline / depth)
    d_lo, d_hi = np.percentile(disparity, [2.0, 98.0])
    d_lo, d_hi = d_lo / 1.25, d_hi * 1.25
    min_disp = int(math.floor(d_lo))
    num = int(math.ceil((d_hi - min_disp) / 16.0)) * 16
    cap = int(max_num_disparities)
    if num <= cap:
        return min_disp, max(num, 16)
    inner = 0.8 * cap
    held = np.searchsorted(disparity, disparity + inner, side="right") - np.arange(len(disparity))
    start = disparity[int(np.argmax(held))]
    return int(math.floor(start - 0.1 * cap)), cap


def textured_pixels(gray: np.ndarray, window_px: int, min_std: float) -> np.ndarray:
    """Pixels (H, W) bool whose ``window_px`` square neighbourhood has a grey-level standard deviation
    of at least ``min_std`` (0-255 scale).

    SGBM's path costs carry a disparity across a textureless region: the uniform sky beside a tower
    takes the tower's depth and fuses into a cloud of sky-coloured points around it (the cathedral's
    lawnmower flight: 98 % of its points off by more than 0.5 m above 30 m were sky blue). Rendered
    sky has a local deviation below 0.5 grey levels, textured surfaces above 4 (1st percentile).
    """
    if int(window_px) < 1:
        raise ValueError(f"reconstruct.dense.texture_window_px must be >= 1, got {window_px}")
    g = np.asarray(gray, dtype=np.float32)
    size = (int(window_px), int(window_px))
    mean = cv2.boxFilter(g, -1, size, borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.boxFilter(g * g, -1, size, borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(mean_sq - mean * mean, 0.0)) >= float(min_std)


def sgbm_matcher(scfg: Mapping, num_disparities: int):
    """OpenCV's 3-way SGBM with ``reconstruct.dense.sgbm``'s settings, searching ``num_disparities``
    px from 0 (a multiple of 16); P1 and P2 are the settings' per-pixel penalties times the block's
    area (OpenCV's suggested 8 and 32 for one channel)."""
    block = int(scfg["block_size"])
    return cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=int(num_disparities),
        blockSize=block,
        P1=round(float(scfg.get("p1_per_block_pixel", OPENCV_P1_PER_BLOCK_PIXEL)) * block * block),
        P2=round(float(scfg.get("p2_per_block_pixel", OPENCV_P2_PER_BLOCK_PIXEL)) * block * block),
        disp12MaxDiff=int(scfg["disp12_max_diff"]),
        uniquenessRatio=int(scfg["uniqueness_ratio"]),
        speckleWindowSize=int(scfg["speckle_window_size"]),
        speckleRange=int(scfg["speckle_range"]),
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def sgbm_disparity(sgbm, left: np.ndarray, right: np.ndarray, mirror_pass: bool) -> np.ndarray:
    """SGBM's disparity (px, float32; negative where it found no match) of rectified ``left``.

    The 3-way mode aggregates its costs along paths that come from above only, so on a surface
    whose disparity changes down the image it lags behind the change: a pair's depth comes out
    0.1-0.35 px of disparity off, one way when the partner lies to the reference's right and the
    other way when it lies to its left (rectification turns the images half round). With
    ``mirror_pass`` the pair is matched once more upside down (rows reversed: epipolar lines and
    disparities stay as they were, the paths now come from below) and the two maps are averaged
    where both matched; where one did, its value is kept. On the tomb / Smith pairs this took the
    median error on the ground from +-0.13-0.35 to 0.004-0.04 px for 1.7-1.9x the matching time.
    """
    disparity = sgbm.compute(left, right).astype(np.float32) / 16.0  # SGBM's fixed point: 1/16 px
    if mirror_pass:
        mirrored = sgbm.compute(np.ascontiguousarray(left[::-1]), np.ascontiguousarray(right[::-1]))
        upside_down = mirrored[::-1].astype(np.float32) / 16.0
        both = (disparity >= 0) & (upside_down >= 0)
        only_mirrored = (disparity < 0) & (upside_down >= 0)
        disparity = np.where(only_mirrored, upside_down, disparity)
        disparity = np.where(both, 0.5 * (disparity + upside_down), disparity)
    return disparity.astype(np.float32)


def matchable_window(
    left_valid: np.ndarray, right_valid: np.ndarray, num_disparities: int
) -> tuple[slice, slice] | None:
    """The rows and columns of a rectified canvas SGBM must match to reach every pixel it can match.

    A reference pixel at column x (``left_valid``, (H, W) bool) can match where the partner
    (``right_valid``) has a pixel in columns x - num_disparities + 1 .. x of its row. The window
    is the box of those pixels, widened on the left by ``num_disparities`` columns (SGBM leaves the
    first ``num_disparities`` columns of what it matches unmatched). None when no pixel can match.
    On the tomb's 100-image ours flight the rectified canvases (the reference turned into the pair's
    orientation, plus the search's left padding) were 2.4x the image at the median and 37 % of their
    pixels could match; the box holds 67 % of the canvas's SGBM work.
    """
    n = int(num_disparities)
    reach = np.cumsum(np.pad(right_valid.astype(np.int32), ((0, 0), (n, 0))), axis=1)
    matchable = left_valid & ((reach[:, n:] - reach[:, :-n]) > 0)
    rows = np.flatnonzero(matchable.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(matchable.any(axis=0))
    start = max(0, int(cols[0]) - n)
    stop = min(max(int(cols[-1]) + 1, start + n + 1), matchable.shape[1])  # SGBM needs more than n
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(start, stop)


def pair_depth(
    ref: View, src: View, ref_gray: np.ndarray, src_gray: np.ndarray, ref_points: np.ndarray, cfg: Mapping
) -> np.ndarray | None:
    """Depth (H, W) float32 in metres along the reference's optical axis from one stereo pair.

    NaN where SGBM found no consistent match. ``ref_points`` (P, 3) are sparse world points seen by
    the reference; they bound the disparity search. None if the pair cannot be rectified.
    """
    max_area = float(cfg.get("max_rectified_area_ratio", DEFAULT_MAX_AREA_RATIO))
    pair = rectify_pair(ref, src, max_area_ratio=max_area)
    if pair is None:
        return None
    depth_rect = (ref_points - ref.center) @ pair.rect_from_world[2]
    search = disparity_search_range(pair, depth_rect, int(cfg["max_num_disparities"]))
    if search is None:
        return None
    min_disp, num_disp = search
    pair = rectify_pair(ref, src, disparity_offset=min_disp, pad_left=num_disp, max_area_ratio=max_area)
    if pair is None:
        return None
    width, height = pair.size
    ones = np.full(src_gray.shape, 255, np.uint8)
    right_valid = cv2.warpPerspective(ones, pair.H_src, (width, height), flags=cv2.INTER_NEAREST)
    scfg = cfg["sgbm"]
    row_span, col_span = slice(0, height), slice(0, width)
    if scfg.get("crop_to_overlap", False):
        ref_ones = np.full(ref_gray.shape, 255, np.uint8)
        left_valid = cv2.warpPerspective(ref_ones, pair.H_ref, (width, height), flags=cv2.INTER_NEAREST)
        window = matchable_window(left_valid > 0, right_valid > 0, num_disp)
        if window is None:
            return None
        row_span, col_span = window
    # Each image is warped straight into the window: the canvas shifted by its top-left corner.
    corner = np.array([[1.0, 0.0, -col_span.start], [0.0, 1.0, -row_span.start], [0.0, 0.0, 1.0]])
    size = (col_span.stop - col_span.start, row_span.stop - row_span.start)
    left = cv2.warpPerspective(ref_gray, corner @ pair.H_ref, size, flags=cv2.INTER_LINEAR)
    right = cv2.warpPerspective(src_gray, corner @ pair.H_src, size, flags=cv2.INTER_LINEAR)

    mirror_pass = bool(scfg.get("mirror_pass", False))
    disparity = np.full((height, width), -1.0, np.float32)
    disparity[row_span, col_span] = sgbm_disparity(sgbm_matcher(scfg, num_disp), left, right, mirror_pass)
    valid = disparity >= 0.0
    valid &= disparity + min_disp > 0.5
    # The matched pixel must lie inside the partner's image (SGBM happily matches the black border).
    rows, cols = np.nonzero(valid)
    match_cols = np.round(cols - disparity[rows, cols]).astype(int)
    inside = (match_cols >= 0) & (match_cols < width)
    inside[inside] = right_valid[rows[inside], match_cols[inside]] > 0
    valid[rows[~inside], cols[~inside]] = False
    disparity[~valid] = 0.0

    # Sample the disparity at every reference pixel; keep only pixels whose 4 neighbours are valid.
    u, v = np.meshgrid(np.arange(ref.width, dtype=np.float64), np.arange(ref.height, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], -1) @ pair.H_ref.T
    map_x = (pix[..., 0] / pix[..., 2]).astype(np.float32)
    map_y = (pix[..., 1] / pix[..., 2]).astype(np.float32)
    d_ref = cv2.remap(disparity, map_x, map_y, cv2.INTER_LINEAR, borderValue=0.0)
    ok = cv2.remap(valid.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderValue=0.0) > 0.999
    z_rect = np.full(d_ref.shape, np.nan, np.float32)
    z_rect[ok] = pair.K_rect[0, 0] * pair.baseline / (d_ref[ok] + min_disp)
    # Depth along the reference axis of the point at rectified depth z_rect on each reference ray.
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(ref.K).T
    rays_world = rays_cam @ ref.rotation
    scale = rays_world @ pair.rect_from_world[2]
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = (z_rect / scale).astype(np.float32)
    depth[~(depth > 0)] = np.nan
    min_std = float(cfg["min_texture_std"])
    if not min_std >= 0.0:
        raise ValueError(f"reconstruct.dense.min_texture_std must be >= 0 (0 disables it), got {min_std}")
    if min_std > 0.0:
        depth[~textured_pixels(ref_gray, int(cfg["texture_window_px"]), min_std)] = np.nan
    return depth


def consistent_depth(
    depths: np.ndarray, min_consistent: int, rel_tol: float, weights: np.ndarray | None = None
) -> np.ndarray:
    """Combine per-partner depth maps (K, H, W) (NaN = none) into one (H, W) (NaN = rejected).

    A pixel is kept when at least ``min(min_consistent, K)`` partners lie within ``rel_tol``
    (relative) of the partners' median; its depth is the mean of those agreeing partners, weighted
    by ``weights`` (K,) (each partner's precision; None: equal weights).
    """
    depths = np.asarray(depths, dtype=np.float32)
    needed = max(1, min(int(min_consistent), depths.shape[0]))
    # NaN-aware median without np.nanmedian's all-NaN warnings (warning filters are not thread-safe).
    ordered = np.sort(depths, axis=0)
    n_valid = np.isfinite(depths).sum(axis=0)
    lo_idx = np.maximum(n_valid - 1, 0) // 2
    hi_idx = n_valid // 2
    hi_idx = np.minimum(hi_idx, depths.shape[0] - 1)
    median = 0.5 * (
        np.take_along_axis(ordered, lo_idx[None], 0)[0] + np.take_along_axis(ordered, hi_idx[None], 0)[0]
    )
    median[n_valid == 0] = np.nan
    with np.errstate(invalid="ignore"):
        agree = np.abs(depths - median) <= rel_tol * median
    count = agree.sum(axis=0)
    w = np.ones(depths.shape[0], np.float64) if weights is None else np.asarray(weights, np.float64)
    w = np.where(agree, w[:, None, None], 0.0)
    total = (w * np.where(agree, depths, 0.0)).sum(axis=0)
    out = np.full(median.shape, np.nan, np.float32)
    keep = count >= needed
    out[keep] = total[keep] / w.sum(axis=0)[keep]
    return out


def partner_weights(ref: View, partners: Sequence[View], cfg: Mapping) -> np.ndarray | None:
    """The weights of ``partners``' depth maps in ``ref``'s combined map (``consistent_depth``):
    with ``partner_weights: precision`` each pair's precision, ``B^2`` (at one reference pixel every
    partner's depth noise is ``z^2 / (f B) s``); None (equal weights) otherwise."""
    if cfg.get("partner_weights", "equal") != "precision":
        return None
    return np.array([float(np.sum((p.center - ref.center) ** 2)) for p in partners])


def normals_from_depth(depth: np.ndarray, K: np.ndarray, window: int) -> np.ndarray:
    """Unit normals (H, W, 3) in the camera frame from a depth map (NaN = none), facing the camera.

    The back-projected points are box-filtered over ``window`` pixels before central differences
    over ``window // 2`` pixels, so SGBM's sub-pixel noise does not dominate. Windows that are not
    full or straddle a depth jump (> ``_MAX_WINDOW_DEPTH_JUMP`` relative) give no normal; such
    pixels near a surface's edge then take the mean normal of their neighbours, so the edges of
    surfaces are not eroded by the window. Zero where undefined.
    """
    h, w = depth.shape
    valid = np.isfinite(depth)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    points = np.where(valid[..., None], rays * np.nan_to_num(depth)[..., None], 0.0).astype(np.float32)
    k = max(1, int(window))
    kernel = np.ones((k, k), np.uint8)
    weight = cv2.boxFilter(valid.astype(np.float32), -1, (k, k), normalize=False)
    summed = cv2.boxFilter(points, -1, (k, k), normalize=False)
    depth_hi = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel)
    depth_lo = cv2.erode(np.where(valid, depth, np.inf).astype(np.float32), kernel)
    with np.errstate(invalid="ignore"):
        smooth_window = (depth_hi - depth_lo) <= _MAX_WINDOW_DEPTH_JUMP * depth_lo
    full = (weight >= 0.999 * k * k) & smooth_window
    smooth = summed / np.maximum(weight, 1.0)[..., None]
    s = max(1, k // 2)
    du = np.zeros_like(smooth)
    dv = np.zeros_like(smooth)
    du[:, s:-s] = smooth[:, 2 * s :] - smooth[:, : -2 * s]
    dv[s:-s, :] = smooth[2 * s :, :] - smooth[: -2 * s, :]
    ok = np.zeros_like(full)
    ok[s:-s, s:-s] = full[s:-s, 2 * s :] & full[s:-s, : -2 * s] & full[2 * s :, s:-s] & full[: -2 * s, s:-s]
    ok &= valid
    normals = np.cross(dv, du)
    norm = np.linalg.norm(normals, axis=-1)
    ok &= norm > 0
    normals[ok] /= norm[ok][:, None]
    normals[~ok] = 0.0
    # Grow the normals into the valid pixels they do not reach (edges of surfaces), 1 px a step.
    for _ in range(2 * s + 1):
        missing = valid & ~ok
        if not missing.any():
            break
        count = cv2.boxFilter(ok.astype(np.float32), -1, (3, 3), normalize=False)
        mean = cv2.boxFilter(normals, -1, (3, 3), normalize=False)
        grow = missing & (count > 0)
        length = np.linalg.norm(mean[grow], axis=-1)
        keep = length > 1e-6
        rows, cols = np.nonzero(grow)
        normals[rows[keep], cols[keep]] = mean[grow][keep] / length[keep][:, None]
        ok[rows[keep], cols[keep]] = True
    facing_away = np.einsum("hwc,hwc->hw", normals, rays) > 0
    normals[facing_away] *= -1.0
    normals[~ok] = 0.0
    return normals.astype(np.float32)


def reference_views(incidence, per_point: int, min_new_points: int) -> np.ndarray:
    """Which views get a depth map when each sparse point needs only ``per_point`` of them.

    Greedy cover: repeatedly take the view that sees the most points still seen by fewer than
    ``per_point`` chosen views, until no view adds ``min_new_points`` of them. A point seen by
    fewer views keeps all of them that add enough. Views left out still serve as stereo partners.

    Args:
        incidence: (V, P) sparse 0/1 matrix, view v sees sparse point p.
        per_point: chosen views wanted per point (>= 1).
        min_new_points: a view adding fewer under-covered points than this is not chosen (>= 1).

    Returns:
        (V,) bool, True for a view that gets a depth map.
    """
    import scipy.sparse  # here: the CUDA back-end's machine needs only numpy, OpenCV and pycolmap

    if int(per_point) < 1 or int(min_new_points) < 1:
        raise ValueError(
            f"reference views: per_point and min_new_points must be >= 1, got {per_point}, {min_new_points}"
        )
    A = scipy.sparse.csr_matrix(incidence, dtype=np.int32)
    chosen = np.zeros(A.shape[0], dtype=bool)
    covered = np.zeros(A.shape[1], dtype=np.int32)
    while True:
        gains = A @ (covered < per_point).astype(np.int32)
        gains[chosen] = -1
        best = int(np.argmax(gains))
        if gains[best] < min_new_points:
            return chosen
        chosen[best] = True
        covered[A.indices[A.indptr[best] : A.indptr[best + 1]]] += 1


def sparse_incidence(rec: pycolmap.Reconstruction, names) -> scipy.sparse.csr_matrix:
    """(len(names), P) 0/1 matrix: which sparse points of the model ``rec`` each view sees."""
    import scipy.sparse

    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    column = {pid: k for k, pid in enumerate(sorted(rec.point3D_ids()))}
    rows, cols = [], []
    for r, name in enumerate(names):
        image = by_name.get(name)
        ids = {p.point3D_id for p in image.points2D if p.has_point3D()} if image is not None else set()
        rows.extend([r] * len(ids))
        cols.extend(column[i] for i in ids)
    data = np.ones(len(rows), dtype=np.int8)
    return scipy.sparse.csr_matrix((data, (rows, cols)), shape=(len(names), len(column)))


def compute_depth_maps_cpu(workspace: Path, cfg: Mapping) -> dict[str, int]:
    """CPU back-end: SGBM depth + normal maps for every view that has partners (or, with
    ``reference_views_per_point`` set, for the views ``reference_views`` keeps); return valid-pixel
    counts (0 for a view without a map)."""
    workspace = Path(workspace)
    views = read_views(workspace)
    partners = select_partners(workspace, views, cfg)
    per_point = cfg.get("reference_views_per_point")
    if per_point is not None:
        order = sorted(views)
        keep = reference_views(
            sparse_incidence(pycolmap.Reconstruction(workspace / "sparse"), order),
            int(per_point),
            int(cfg.get("reference_min_new_points", 1)),
        )
        log.info(
            "dense: %d of %d views get a depth map (%d per sparse point), the rest serve as partners",
            int(keep.sum()),
            len(order),
            int(per_point),
        )
        references = {name for name, k in zip(order, keep, strict=True) if k}
    else:
        references = set(views)
    points_by_name = sparse_points_by_image(workspace)
    min_consistent = int(cfg["min_consistent_partners"])
    rel_tol = float(cfg["consistency_rel_tol"])
    window = int(cfg["normal_window_px"])
    edge_margin = int(cfg.get("edge_margin_px", 0))
    geometric = cfg.get("geometric_consistency") or {"min_views": 0}
    checked = int(geometric["min_views"]) > 0  # a second pass checks every map against others
    raw_dir = workspace / "stereo" / "raw_depth"
    if checked:
        raw_dir.mkdir(parents=True, exist_ok=True)

    def finish(name: str, depth: np.ndarray) -> int:
        normals = normals_from_depth(depth, views[name].K, window)
        write_maps(workspace, name, depth, normals)
        return int(np.count_nonzero(np.any(normals != 0, axis=-1)))

    def gray(name: str) -> np.ndarray:
        image = cv2.imread(str(workspace / "images" / name), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{workspace / 'images' / name}: unreadable image")
        return image

    def one_view(name: str) -> tuple[str, int]:
        ref = views[name]
        if name not in references or not partners.get(name):
            return name, 0
        ref_gray = gray(name)
        depths, measured = [], []
        for src_name in partners[name]:
            depth = pair_depth(ref, views[src_name], ref_gray, gray(src_name), points_by_name[name], cfg)
            if depth is not None:
                depths.append(depth)
                measured.append(views[src_name])
        if not depths:
            return name, 0
        weights = partner_weights(ref, measured, cfg)
        depth = consistent_depth(np.stack(depths), min_consistent, rel_tol, weights)
        depth[edge_pixels(depth, edge_margin)] = np.nan
        if checked:
            np.save(raw_dir / f"{name.replace('/', '__')}.npy", depth)
            return name, int(np.count_nonzero(np.isfinite(depth)))
        return name, finish(name, depth)

    def raw(name: str) -> np.ndarray:
        return np.load(raw_dir / f"{name.replace('/', '__')}.npy")

    def checked_view(name: str) -> tuple[str, int]:
        depth = raw(name)
        others = [n for n in neighbours[name] if valid_pixels.get(n, 0) > 0][: int(geometric["num_views"])]
        support = geometric_support(
            views[name], depth, [(views[n], raw(n)) for n in others], float(geometric["rel_tol"])
        )
        depth[support < int(geometric["min_views"])] = np.nan
        return name, finish(name, depth)

    threads = int(cfg.get("num_threads", -1))
    threads = os.cpu_count() or 1 if threads <= 0 else threads
    names = sorted(views)
    n_without = sum(1 for n in names if not partners.get(n))
    if n_without:
        log.info("%d of %d views have no stereo partner", n_without, len(names))
    valid_pixels = {}
    # One view per core, each SGBM on one thread: OpenCV's own pool inside every worker would put
    # threads x cores threads on the cores.
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if threads > 1 else opencv_threads)
    try:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for name, count in tqdm(
                pool.map(one_view, names), total=len(names), desc="stereo (SGBM)", unit="view"
            ):
                valid_pixels[name] = count
            if checked:
                neighbours = overlapping_views(workspace)
                mapped = [n for n in names if valid_pixels[n] > 0]
                for name, count in tqdm(
                    pool.map(checked_view, mapped), total=len(mapped), desc="geometric check", unit="view"
                ):
                    valid_pixels[name] = count
    finally:
        cv2.setNumThreads(opencv_threads)
        shutil.rmtree(raw_dir, ignore_errors=True)
    return valid_pixels


def compute_depth_maps_cuda(workspace: Path, cfg: Mapping) -> dict[str, int]:
    """CUDA back-end: ``pycolmap.patch_match_stereo`` with geometric consistency.

    Source views come from the workspace's ``stereo/patch-match.cfg`` (the undistorter writes
    ``__auto__, 20``). Returns 1 for every view that got a geometric depth map.
    """
    stereo = Path(workspace) / "stereo"
    # COLMAP only logs (does not raise) when it cannot write a map into a missing folder.
    for folder in ("depth_maps", "normal_maps", "consistency_graphs"):
        (stereo / folder).mkdir(parents=True, exist_ok=True)
    pcfg = cfg["patch_match"]
    options = pycolmap.PatchMatchOptions()
    options.max_image_size = int(cfg["max_image_size"])
    options.window_radius = int(pcfg["window_radius"])
    options.num_iterations = int(pcfg["num_iterations"])
    options.geom_consistency = True
    options.min_triangulation_angle = float(cfg["min_triangulation_angle_deg"])
    pycolmap.patch_match_stereo(workspace, workspace_format="COLMAP", options=options)
    return {p.name[: -len(DEPTH_SUFFIX)]: 1 for p in (stereo / "depth_maps").glob(f"*{DEPTH_SUFFIX}")}


def fusion_options(cfg: Mapping, deterministic: bool = False) -> pycolmap.StereoFusionOptions:
    """COLMAP's fusion options from the ``reconstruct.dense`` config."""
    fcfg = cfg["fusion"]
    options = pycolmap.StereoFusionOptions()
    options.min_num_pixels = int(fcfg["min_num_pixels"])
    options.max_reproj_error = float(fcfg["max_reproj_error"])
    options.max_depth_error = float(fcfg["max_depth_error"])
    options.max_normal_error = float(fcfg["max_normal_error"])
    options.max_image_size = int(cfg["max_image_size"])
    if fcfg.get("check_num_images") is not None:  # COLMAP's default (50) unless set
        options.check_num_images = int(fcfg["check_num_images"])
    if deterministic:
        options.num_threads = 1
    return options


# What COLMAP's fusion holds per view, in bytes per pixel: the RGB image (3), the depth (4), the
# normal (12) and the "already fused" mask (1).
FUSION_BYTES_PER_PX = 20


# ``fusion.max_memory_gb: auto``: fusion's views may hold this share of the memory the machine has
# free when fusion starts. Chunked fusion peaks at about 1.6x its budget (archive/pre_p1/throughput.md),
# so 0.5 keeps the peak near 0.8 of what is free.
AUTO_MEMORY_SHARE = 0.5


def fusion_budget_gb(setting) -> float | None:
    """The fusion memory budget (GB) of ``fusion.max_memory_gb``: a number as given, ``auto`` a share
    of the memory free now (``AUTO_MEMORY_SHARE``), None no budget."""
    if setting is None:
        return None
    if setting == "auto":
        import psutil

        return AUTO_MEMORY_SHARE * psutil.virtual_memory().available / 1e9
    return float(setting)


def fusion_chunk_size(workspace: Path, names, max_memory_gb: float | None) -> int | None:
    """How many views a fusion chunk may hold within ``max_memory_gb`` (GB); None when every view
    of ``names`` fits at once (or there is no budget)."""
    if max_memory_gb is None:
        return None
    views = read_views(workspace)
    view_bytes = [FUSION_BYTES_PER_PX * views[n].width * views[n].height for n in names]
    budget = float(max_memory_gb) * 1e9
    if sum(view_bytes) <= budget:
        return None
    max_views = int(budget // max(view_bytes))
    if max_views < 2:
        raise ValueError(
            f"reconstruct.dense.fusion.max_memory_gb={max_memory_gb:.3g} holds fewer than two views "
            f"({max(view_bytes) / 1e9:.3f} GB each)"
        )
    return max_views


@dataclass(frozen=True)
class FusionReport:
    """How a fusion ran: fused points, chunks (1: every view at once) and the budget (GB, or None)."""

    n_points: int
    n_chunks: int
    max_memory_gb: float | None


def fuse(workspace: Path, output_ply: Path, cfg: Mapping, names, deterministic: bool = False) -> int:
    """Fuse the workspace's geometric depth/normal maps of ``names`` into ``output_ply``; return the
    number of fused points (``fuse_report`` says how it ran)."""
    return fuse_report(workspace, output_ply, cfg, names, deterministic).n_points


def fuse_report(
    workspace: Path, output_ply: Path, cfg: Mapping, names, deterministic: bool = False
) -> FusionReport:
    """Fuse the workspace's geometric depth/normal maps of ``names`` into ``output_ply``. The PLY
    carries positions, normals and colours (model frame, metres).

    Above the ``fusion.max_memory_gb`` budget (``fusion_budget_gb``) the views are fused in chunks
    (``reconstruct.fusion_chunks``). ``deterministic`` fuses on one thread: COLMAP's fusion threads
    share the "pixel already fused" masks, so which thread claims a pixel first (and so the cloud)
    changed from run to run.
    """
    workspace = Path(workspace)
    names = sorted(names)
    if cfg["fusion"].get("method", "colmap") == "rays":
        return FusionReport(_fuse_rays(workspace, output_ply, cfg, names), 1, None)
    budget = fusion_budget_gb(cfg["fusion"].get("max_memory_gb"))
    max_views = fusion_chunk_size(workspace, names, budget)
    if max_views is None:
        n_points = _fuse_views(workspace, output_ply, cfg, names, deterministic)
        return FusionReport(_support_filtered(output_ply, cfg, n_points), 1, budget)
    n_points, n_chunks = _fuse_in_chunks(workspace, output_ply, cfg, names, max_views, deterministic)
    return FusionReport(n_points, n_chunks, budget)


def _fuse_views(workspace: Path, output_ply: Path, cfg: Mapping, names, deterministic: bool) -> int:
    """One COLMAP fusion of ``names`` (all held in memory at once) into ``output_ply``."""
    write_text_atomic(workspace / "stereo" / "fusion.cfg", "".join(f"{n}\n" for n in sorted(names)))
    fused = pycolmap.stereo_fusion(
        output_ply,
        workspace,
        workspace_format="COLMAP",
        input_type="geometric",
        options=fusion_options(cfg, deterministic),
        output_type="PLY",
    )
    return int(fused.num_points3D()) if hasattr(fused, "num_points3D") else -1


def _fuse_in_chunks(
    workspace: Path, output_ply: Path, cfg: Mapping, names: list[str], max_views: int, deterministic: bool
) -> tuple[int, int]:
    import open3d as o3d

    from reconstruct import fusion_chunks as fc

    sparse_dir = workspace / "sparse"
    # COLMAP's fusion walks from a view to its check_num_images most overlapping ones: a chunk
    # holds them for each of its own views.
    per_view = fusion_options(cfg, deterministic).check_num_images
    neighbours = fc.top_neighbours(fc.shared_points(sparse_dir, names), per_view)
    chunks = fc.plan_chunks(neighbours, max_views)
    log.info(
        "fusion: %d views in %d chunks of at most %d (own + neighbour views: %s)",
        len(names),
        len(chunks),
        max_views,
        ", ".join(f"{len(c.own)}+{len(c.neighbours)}" for c in chunks),
    )
    workspace_index = {name: i for i, name in enumerate(fc.model_image_names(sparse_dir))}
    chunk_of = np.full(len(workspace_index), -1)
    for c, chunk in enumerate(chunks):
        chunk_of[[workspace_index[names[v]] for v in chunk.own]] = c
    parts: dict[str, list[np.ndarray]] = {"points": [], "normals": [], "colors": [], "support": []}
    chunk_ply = Path(output_ply).with_name(Path(output_ply).name + ".chunk.ply")
    chunk_vis = chunk_ply.with_name(chunk_ply.name + ".vis")
    try:
        for c, chunk in enumerate(tqdm(chunks, desc="fusion", unit="chunk")):
            _fuse_views(workspace, chunk_ply, cfg, [names[v] for v in chunk.views], deterministic)
            counts, indices = fc.read_visibility(chunk_vis)
            cloud = o3d.io.read_point_cloud(str(chunk_ply))
            if len(cloud.points) != len(counts) or (chunk_of[indices] < 0).any():
                raise RuntimeError(f"{chunk_vis}: does not match {chunk_ply} and the chunk's views")
            keep = fc.owning_chunk(counts, indices, chunk_of, len(chunks)) == c
            parts["points"].append(np.asarray(cloud.points)[keep])
            parts["normals"].append(np.asarray(cloud.normals)[keep])
            parts["colors"].append(np.asarray(cloud.colors)[keep])
            parts["support"].append(counts[keep])
    finally:
        chunk_ply.unlink(missing_ok=True)
        chunk_vis.unlink(missing_ok=True)
    arrays = {key: np.concatenate(value) for key, value in parts.items()}
    n_points = _write_cloud(output_ply, arrays, _support_kept(arrays, cfg))
    return n_points, len(chunks)


def _fuse_rays(workspace: Path, output_ply: Path, cfg: Mapping, names: list[str]) -> int:
    """``fusion.method: rays`` (``reconstruct.fusion_rays``): points on the depth maps' rays."""
    from reconstruct.fusion_rays import best_conditioned_per_voxel, fuse_along_rays, well_conditioned

    views = read_views(workspace)
    partners = select_partners(workspace, views, cfg)
    baselines = stereo_baselines(views, partners, cfg.get("partner_weights", "equal"))
    cloud = fuse_along_rays(workspace, names, views, overlapping_views(workspace), baselines, cfg["fusion"])
    n_fused = len(cloud["points"])
    fusion = cfg["fusion"]
    cloud = well_conditioned(
        cloud, float(fusion.get("conditioning_cell_m", 0.05)), float(fusion.get("conditioning_ratio", 0.0))
    )
    n_conditioned = len(cloud["points"])
    cloud = best_conditioned_per_voxel(cloud, float(fusion.get("ray_voxel_m", 0.0)))
    log.info(
        "fusion along rays: %d points from %d views (%d after the conditioning filter, %d one per voxel)",
        n_fused,
        len(names),
        n_conditioned,
        len(cloud["points"]),
    )
    return _write_cloud(output_ply, cloud, _support_kept(cloud, cfg))


def _support_kept(cloud: Mapping, cfg: Mapping) -> np.ndarray | None:
    """The fused points the support filter keeps (``reconstruct.fusion_support``); None when it is off."""
    share = float(cfg["fusion"].get("support_share", 0.0))
    if share <= 0:
        return None
    from reconstruct.fusion_support import supported_points

    keep = supported_points(
        cloud["points"], cloud["support"], float(cfg["fusion"]["support_radius_m"]), share
    )
    log.info("fusion: the support filter keeps %d of %d points", int(keep.sum()), len(keep))
    return keep


# Open3D's binary PLY row of a fused point: position and normal as doubles, colour as bytes.
PLY_ROW_BYTES = 3 * 8 + 3 * 8 + 3
PLY_HEADER_MAX_BYTES = 4096


def _write_cloud(path: Path, cloud: Mapping, keep: np.ndarray | None) -> int:
    """Write points, normals and colours (``keep`` of them, or all) as a PLY; return the count.

    Raises OSError, leaving no file, when the disk has not the room or the file came out short:
    Open3D reports success on a PLY the full disk cut off, and evaluation then fails on it later.
    """
    import open3d as o3d

    keep = slice(None) if keep is None else keep
    out = o3d.geometry.PointCloud()
    out.points = o3d.utility.Vector3dVector(cloud["points"][keep])
    out.normals = o3d.utility.Vector3dVector(cloud["normals"][keep])
    out.colors = o3d.utility.Vector3dVector(cloud["colors"][keep])
    need = len(out.points) * PLY_ROW_BYTES
    free = shutil.disk_usage(Path(path).parent).free
    if free < need + PLY_HEADER_MAX_BYTES:
        raise OSError(f"{path}: the fused cloud needs {need / 1e9:.2f} GB, the disk has {free / 1e9:.2f} GB")
    written = o3d.io.write_point_cloud(str(path), out)
    size = Path(path).stat().st_size if Path(path).exists() else 0
    if not written or not need <= size <= need + PLY_HEADER_MAX_BYTES:
        Path(path).unlink(missing_ok=True)
        raise OSError(f"{path}: wrote {size} bytes of the fused cloud's {need} and a header (disk full?)")
    return len(out.points)


def _support_filtered(output_ply: Path, cfg: Mapping, n_points: int) -> int:
    """Apply the support filter to a one-pass fusion's PLY (and its ``.vis``) in place."""
    if float(cfg["fusion"].get("support_share", 0.0)) <= 0 or n_points <= 0:
        return n_points
    # Imported here: the CUDA back-end's machine needs only numpy, OpenCV and pycolmap.
    import open3d as o3d

    from reconstruct.fusion_chunks import read_visibility

    counts, _ = read_visibility(Path(str(output_ply) + ".vis"))
    cloud = o3d.io.read_point_cloud(str(output_ply))
    arrays = {
        "points": np.asarray(cloud.points),
        "normals": np.asarray(cloud.normals),
        "colors": np.asarray(cloud.colors),
        "support": counts,
    }
    return _write_cloud(output_ply, arrays, _support_kept(arrays, cfg))


def dense_reconstruct(
    sparse_dir: Path,
    image_dir: Path,
    out_dir: Path,
    cfg: Mapping,
    deterministic: bool = False,
    ground_truth=None,
    seed: int = 0,
) -> dict:
    """Workspace, depth maps (CPU, CUDA or oracle back-end) and fusion into ``out_dir/dense.ply``.

    Args:
        sparse_dir: the (aligned) sparse model.
        image_dir: the flight's images.
        out_dir: where ``dense/`` (the workspace) and ``dense.ply`` go.
        cfg: the ``reconstruct.dense`` config.
        deterministic: the same cloud, bit for bit, from the same model and images (see ``fuse``).
        ground_truth: the ground-truth mesh (world metres), for the ``oracle`` back-end only.
        seed: seeds the oracle's noise.

    Returns:
        ``backend``, ``dense_time_s`` (s), ``n_depth_maps``, ``n_dense_points``, ``dense_path``,
        ``fusion_n_chunks``, ``fusion_max_memory_gb`` (the budget fusion ran under, or None).

    Raises:
        ValueError: a bad setting, or the oracle asked for without a ground truth.
    """
    DenseSettings.from_config(cfg)  # a bad setting is refused before the workspace is touched
    backend = select_backend(str(cfg["backend"]))
    if backend == "oracle" and ground_truth is None:
        raise ValueError(
            "reconstruct.dense.backend=oracle needs the ground truth: only a simulated run has one"
        )
    start = time.perf_counter()
    workspace = prepare_workspace(Path(sparse_dir), Path(image_dir), Path(out_dir) / "dense", cfg)
    log.info("dense: %s back-end", backend)
    if backend == "cuda":
        valid = compute_depth_maps_cuda(workspace, cfg)
    elif backend == "oracle":
        from reconstruct.oracle import compute_depth_maps_oracle

        valid = compute_depth_maps_oracle(workspace, cfg, ground_truth, seed)
    else:
        valid = compute_depth_maps_cpu(workspace, cfg)
    names = [n for n, count in valid.items() if count > 0]
    output_ply = Path(out_dir) / "dense.ply"
    report = FusionReport(0, 0, None)
    if names:
        report = _fuse_atomic(workspace, output_ply, fusion_config(backend, cfg), names, deterministic)
    return {
        "backend": backend,
        "dense_time_s": time.perf_counter() - start,
        "n_depth_maps": len(names),
        "n_dense_points": report.n_points,
        "dense_path": str(output_ply) if names else None,
        "fusion_n_chunks": report.n_chunks,
        "fusion_max_memory_gb": report.max_memory_gb,
    }


def fusion_config(backend: str, cfg: Mapping) -> Mapping:
    """The dense settings ``backend``'s maps are fused with. The oracle's depth comes from no
    matching window, and its noise is the stereo model's alone (``reconstruct.oracle``), so fusion
    weighs it by that model: ``fusion.slant_window_px`` 0."""
    fusion = cfg["fusion"]
    if backend != "oracle" or not float(fusion.get("slant_window_px", 0.0)):
        return cfg
    return {**cfg, "fusion": {**fusion, "slant_window_px": 0.0}}


def _fuse_atomic(workspace: Path, output_ply: Path, cfg: Mapping, names, deterministic: bool) -> FusionReport:
    holder = {}

    def writer(tmp: Path) -> None:
        holder["report"] = fuse_report(workspace, tmp, cfg, names, deterministic)
        # pycolmap also writes which images saw each point (<ply>.vis, ~70 MB a cell); nothing
        # here reads it, and under the temporary name it would be left behind.
        tmp.with_name(tmp.name + ".vis").unlink(missing_ok=True)

    write_atomic(output_ply, writer)
    return holder["report"]
