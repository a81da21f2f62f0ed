"""Depth + normal maps of a dense workspace: the CPU back-end (SGBM on rectified pairs of each
reference view with its partners, ``reconstruct.stereo.matching``) and the CUDA back-end
(``pycolmap.patch_match_stereo``); which views get a map (``reference_views``).

Fusion of the maps into a cloud is ``reconstruct.dense``'s.
"""

from __future__ import annotations

import logging
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap
import scipy.sparse
from tqdm import tqdm

from reconstruct.dense_settings import DenseSettings
from reconstruct.depth_filter import edge_pixels, geometric_support
from reconstruct.stereo.matching import consistent_depth, normals_from_depth, pair_depth, partner_weights
from reconstruct.workspace import (
    DEPTH_SUFFIX,
    overlapping_views,
    read_views,
    select_partners,
    sparse_points_by_image,
    write_maps,
)

if TYPE_CHECKING:
    import scipy.sparse

log = logging.getLogger(__name__)


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


def compute_depth_maps_cpu(workspace: Path, settings: DenseSettings) -> dict[str, int]:
    """CPU back-end: SGBM depth + normal maps for every view that has partners (or, with
    ``reference_views_per_point`` set, for the views ``reference_views`` keeps); return valid-pixel
    counts (0 for a view without a map)."""
    workspace = Path(workspace)
    views = read_views(workspace)
    partners = select_partners(workspace, views, settings)
    per_point = settings.reference_views_per_point
    if per_point is not None:
        order = sorted(views)
        keep = reference_views(
            sparse_incidence(pycolmap.Reconstruction(workspace / "sparse"), order),
            per_point,
            settings.reference_min_new_points,
        )
        log.info(
            "dense: %d of %d views get a depth map (%d per sparse point), the rest serve as partners",
            int(keep.sum()),
            len(order),
            per_point,
        )
        references = {name for name, k in zip(order, keep, strict=True) if k}
    else:
        references = set(views)
    points_by_name = sparse_points_by_image(workspace)
    min_consistent = settings.min_consistent_partners
    rel_tol = settings.consistency_rel_tol
    window = settings.normal_window_px
    edge_margin = settings.edge_margin_px
    geometric = settings.geometric_consistency
    checked = geometric.min_views > 0  # a second pass checks every map against others
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
            depth = pair_depth(ref, views[src_name], ref_gray, gray(src_name), points_by_name[name], settings)
            if depth is not None:
                depths.append(depth)
                measured.append(views[src_name])
        if not depths:
            return name, 0
        weights = partner_weights(ref, measured, settings)
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
        others = [n for n in neighbours[name] if valid_pixels.get(n, 0) > 0][: geometric.num_views]
        measured = [(views[n], raw(n)) for n in others]
        support = geometric_support(views[name], depth, measured, geometric.rel_tol)
        depth[support < geometric.min_views] = np.nan
        return name, finish(name, depth)

    threads = settings.num_threads
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


def compute_depth_maps_cuda(workspace: Path, settings: DenseSettings) -> dict[str, int]:
    """CUDA back-end: ``pycolmap.patch_match_stereo`` with geometric consistency.

    Source views come from the workspace's ``stereo/patch-match.cfg`` (the undistorter writes
    ``__auto__, 20``). Returns 1 for every view that got a geometric depth map.
    """
    stereo = Path(workspace) / "stereo"
    # COLMAP only logs (does not raise) when it cannot write a map into a missing folder.
    for folder in ("depth_maps", "normal_maps", "consistency_graphs"):
        (stereo / folder).mkdir(parents=True, exist_ok=True)
    options = pycolmap.PatchMatchOptions()
    options.max_image_size = settings.max_image_size
    options.window_radius = settings.patch_match.window_radius
    options.num_iterations = settings.patch_match.num_iterations
    options.geom_consistency = True
    options.min_triangulation_angle = settings.min_triangulation_angle_deg
    pycolmap.patch_match_stereo(workspace, workspace_format="COLMAP", options=options)
    return {p.name[: -len(DEPTH_SUFFIX)]: 1 for p in (stereo / "depth_maps").glob(f"*{DEPTH_SUFFIX}")}
