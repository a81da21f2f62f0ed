"""Fusion along the reference rays: one point per depth pixel that other views confirm, placed on
that pixel's ray at the precision-weighted depth of every view that measured it.

COLMAP's fusion (``fusion.method: colmap``) gathers, from a reference pixel, the pixels of other
views within ``max_reproj_error`` pixels and ``max_depth_error`` of it and outputs the coordinate-wise
median of their back-projected points. Those points lie on the surface but up to two pixels apart
across it, and the median of each coordinate of points spread over a slanted or curved surface
lies off it: the more views join a cluster, the wider it spreads and the farther its median leaves
the surface, so a flight's fused cloud gets less accurate as views are added (``tests/
test_dense_quality.py``, archive/pre_p1/dense_stage.md).

Here (``fusion.method: rays``) views are taken in turn. Every unused depth pixel of the reference
is projected into its ``ray_neighbours`` most overlapping views; a neighbour confirms it when its
own depth at the projected pixel (nearest) lies within ``max_depth_error`` (relative) of the
point's depth in that view and its normal within ``max_normal_error``. A pixel confirmed by at least
``min_num_pixels - 1`` neighbours becomes one point on the reference's ray, at the mean of the
measured depths along that ray (each neighbour's: where the ray meets the tangent plane of its
measured point and normal) weighted by each measurement's precision: the stereo model's
``1 / sigma_z^2`` with ``sigma_z ~ z^2 / B`` (z the depth in the measuring view, B its stereo
baseline), so a far or narrow-baseline view counts less than a close, wide one; with
``slant_window_px`` above 0 a measurement's variance also holds the window's depth spread on a
surface slanted to its ray (``reconstruct.stereo_noise.slant_depth_sigma``), so a grazing view counts
less than a frontal one at the same depth and baseline. With ``gate_disparity_px`` above 0, a
measurement farther from that mean than so many pixels of its own disparity noise is dropped and the
rest fused again (``_gate_claims``). The confirming
pixels are marked used and seed no point of their own. Points are whole rays of the depth maps,
never averaged across the surface, and every view is handled with its neighbours only, so memory
stays at a few views whatever the flight's size, and the result is the same on any thread count.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from reconstruct.dense_settings import FusionSettings
from reconstruct.depth_filter import project
from reconstruct.stereo_noise import slant_depth_sigma, stereo_depth_sigma
from reconstruct.workspace import read_maps

# What ``fuse_along_rays`` returns for every fused point.
CLOUD_FIELDS = ("points", "normals", "colors", "support", "depth_sigma")


class _MapCache:
    """The depth and normal maps of the views fusion holds, the least recently used dropped first."""

    def __init__(self, workspace: Path, capacity: int) -> None:
        self.workspace, self.capacity = workspace, max(2, capacity)
        self.maps: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __getitem__(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        if name in self.maps:
            self.maps[name] = self.maps.pop(name)  # most recent last
        else:
            if len(self.maps) >= self.capacity:
                self.maps.pop(next(iter(self.maps)))
            self.maps[name] = read_maps(self.workspace, name)
        return self.maps[name]


# A tangent plane within acos(0.1) = 84 deg of the ray's normal incidence is met by the ray; a more
# grazing one is not trusted (the neighbour's point's foot on the ray is used instead).
GRAZING_COS = 0.1


def fuse_along_rays(
    workspace: Path,
    names: Sequence[str],
    views: Mapping,
    neighbours: Mapping[str, list[str]],
    baselines: Mapping[str, float],
    fusion: FusionSettings,
) -> dict[str, np.ndarray]:
    """Fuse the geometric maps of ``names`` (see the module docstring).

    Args:
        workspace: the dense workspace (its ``images/`` give the colours).
        names: the views with depth maps, in the order they seed points.
        views: ``reconstruct.dense.View`` by name (OpenCV intrinsics, cam_from_world, metres).
        neighbours: every view's other views, most overlapping first.
        baselines: every view's stereo baseline (m), the precision weight's B.
        fusion: the ``reconstruct.dense.fusion`` settings.

    Returns:
        ``points`` (N, 3), ``normals`` (N, 3) world unit normals, ``colors`` (N, 3) in [0, 1],
        ``support`` (N,) how many views measured each point (the reference included),
        ``depth_sigma`` (N,) the fused depth's standard deviation (m) at one pixel of disparity noise
        under the stereo model (``1 / sqrt`` of the summed precisions): how well conditioned it is.
    """
    workspace = Path(workspace)
    names = list(names)
    mapped = set(names)
    n_neighbours = fusion.ray_neighbours
    min_pixels = fusion.min_num_pixels
    rel_tol = fusion.max_depth_error
    min_cos = math.cos(math.radians(fusion.max_normal_error))
    slant_px = fusion.slant_window_px
    gate_px = fusion.gate_disparity_px
    used = {name: np.zeros((views[name].height, views[name].width), bool) for name in names}
    cache = _MapCache(workspace, 2 * n_neighbours + 2)
    out: dict[str, list[np.ndarray]] = {key: [] for key in CLOUD_FIELDS}
    for name in names:
        ref = views[name]
        depth, normals = cache[name]
        seeds = np.isfinite(depth) & ~used[name]
        if not seeds.any():
            continue
        rows, cols = np.nonzero(seeds)
        z_ref = depth[rows, cols].astype(np.float64)
        rays = (np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float64)) @ np.linalg.inv(ref.K).T
        world_rays = rays @ ref.rotation  # world directions of unit camera depth
        points = ref.center + world_rays * z_ref[:, None]
        n_ref_world = normals[rows, cols].astype(np.float64) @ ref.rotation
        cos_ref = _cos_incidence(world_rays, n_ref_world) if slant_px > 0 else None
        weight_ref = _precision(z_ref, ref.K[0, 0], baselines.get(name, 1.0), cos_ref, slant_px)
        weighted = weight_ref * z_ref
        total = weight_ref.copy()
        support = np.ones(len(rows), np.int32)
        claims = []
        for other in [n for n in neighbours.get(name, []) if n in mapped][:n_neighbours]:
            view = views[other]
            u, v, z = project(points, view.K, view.rotation, view.translation)
            col, row = np.rint(u), np.rint(v)
            inside = (z > 0) & (col >= 0) & (col < view.width) & (row >= 0) & (row < view.height)
            idx = np.flatnonzero(inside)
            r, c = row[idx].astype(int), col[idx].astype(int)
            d_other, n_other = cache[other]
            measured = d_other[r, c]
            with np.errstate(invalid="ignore"):
                agree = np.abs(measured - z[idx]) <= rel_tol * z[idx]
            agree &= ~used[other][r, c]
            n_other_world = n_other[r, c].astype(np.float64) @ view.rotation
            agree &= np.einsum("ij,ij->i", n_other_world, n_ref_world[idx]) >= min_cos
            idx, r, c, n_other_world = idx[agree], r[agree], c[agree], n_other_world[agree]
            # The neighbour's measurement carried onto the reference's ray: where the ray meets the
            # neighbour's tangent plane (its point and normal). The nearest pixel's point lies up to
            # half a pixel across the surface from the ray; on a slanted surface its foot on the
            # ray would be off by that much times the slope (grazing planes fall back to the foot).
            other_points = back_project_pixels(view, c, r, measured[agree])
            offset = other_points - ref.center
            ray = world_rays[idx]
            facing = np.einsum("ij,ij->i", ray, n_other_world)
            foot = np.einsum("ij,ij->i", offset, ray) / np.einsum("ij,ij->i", ray, ray)
            grazing = np.abs(facing) < GRAZING_COS * np.linalg.norm(ray, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(grazing, foot, np.einsum("ij,ij->i", offset, n_other_world) / facing)
            cos_other = _cos_incidence(other_points - view.center, n_other_world) if slant_px > 0 else None
            w = _precision(
                measured[agree].astype(np.float64),
                view.K[0, 0],
                baselines.get(other, 1.0),
                cos_other,
                slant_px,
            )
            weighted[idx] += w * t
            total[idx] += w
            support[idx] += 1
            claims.append((other, idx, r, c, t, w))
        if gate_px > 0:
            claims = _gate_claims(claims, weighted, total, support, z_ref, weight_ref, gate_px)
        keep = support >= min_pixels
        fused_depth = weighted[keep] / total[keep]
        out["points"].append(ref.center + world_rays[keep] * fused_depth[:, None])
        out["normals"].append(n_ref_world[keep] / np.linalg.norm(n_ref_world[keep], axis=1, keepdims=True))
        out["colors"].append(_colours(workspace, name, rows[keep], cols[keep]))
        out["support"].append(support[keep])
        out["depth_sigma"].append(1.0 / np.sqrt(total[keep]))
        used[name][rows, cols] = True
        for other, idx, r, c, _, _ in claims:
            fused = keep[idx]
            used[other][r[fused], c[fused]] = True
    if not out["points"]:
        return {key: np.zeros((0, 3)) for key in ("points", "normals", "colors")} | {
            "support": np.zeros(0, int),
            "depth_sigma": np.zeros(0),
        }
    return {key: np.concatenate(value) for key, value in out.items()}


def _gate_claims(claims, weighted, total, support, z_ref, weight_ref, gate_px):
    """Drop, in place, every measurement farther from its point's fused depth than ``gate_px``
    pixels of its own disparity noise (``1 / sqrt(w)`` is its sigma at one pixel), the reference's
    own included, and re-sum the rest. The agreement band (``max_depth_error``, 1 % of the depth:
    25 cm at 25 m) is wide enough to let a measurement many sigmas off join the mean, and the more
    views a flight has, the more of those a point collects. Returns the claims that stay."""
    fused = weighted / total
    weighted[:] = 0.0
    total[:] = 0.0
    support[:] = 0
    ref_ok = np.abs(z_ref - fused) * np.sqrt(weight_ref) <= gate_px
    weighted[ref_ok] += weight_ref[ref_ok] * z_ref[ref_ok]
    total[ref_ok] += weight_ref[ref_ok]
    support[ref_ok] += 1
    kept = []
    for other, idx, r, c, t, w in claims:
        ok = np.abs(t - fused[idx]) * np.sqrt(w) <= gate_px
        idx, r, c, t, w = idx[ok], r[ok], c[ok], t[ok], w[ok]
        weighted[idx] += w * t
        total[idx] += w
        support[idx] += 1
        kept.append((other, idx, r, c, t, w))
    total[total == 0] = np.inf  # no measurement left: support 0, dropped; no division by zero
    return kept


def well_conditioned(cloud: Mapping[str, np.ndarray], cell_m: float, ratio: float) -> dict[str, np.ndarray]:
    """The points whose ``depth_sigma`` is at most ``ratio`` times the smallest within one
    ``cell_m`` cube of theirs (their cube of a grid and its 26 neighbours); ``ratio`` 0 keeps all.

    Where a flight's views overlap many times over, a patch of surface is measured by well
    conditioned views (close, wide baselines) and by poorly conditioned ones (far, oblique, narrow
    baselines) alike; fusion confirms both, and the poor ones, several times noisier, set the error
    percentiles: a denser flight of the same views got *less* accurate (archive/pre_p1/dense_stage.md).
    Dropping a point that a much better measured one stands beside keeps the patch (completeness)
    and its best measurements: a view added to a flight then adds a point only where it is among
    the best measured there. Where only poor views saw a patch, their points are its best and stay.
    The neighbouring cubes count too, so a poor point off the surface by up to a cube is compared
    with the good points on it.
    """
    if ratio <= 0 or len(cloud["points"]) == 0:
        return dict(cloud)
    cells = np.floor(cloud["points"] / cell_m).astype(np.int64)
    cells -= cells.min(axis=0) - 1  # >= 1, so every neighbour index is >= 0
    span = cells.max(axis=0) + 2
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    occupied, cell_of = np.unique(keys, return_inverse=True)
    cell_best = np.full(len(occupied), np.inf)
    np.minimum.at(cell_best, cell_of.ravel(), cloud["depth_sigma"])
    near_best = cell_best.copy()
    for dx, dy, dz in np.ndindex(3, 3, 3):
        shifted = occupied + ((dx - 1) * span[1] + (dy - 1)) * span[2] + (dz - 1)
        at = np.minimum(np.searchsorted(occupied, shifted), len(occupied) - 1)
        found = occupied[at] == shifted
        near_best[found] = np.minimum(near_best[found], cell_best[at[found]])
    keep = cloud["depth_sigma"] <= ratio * near_best[cell_of.ravel()]
    return {key: value[keep] for key, value in cloud.items()}


def best_conditioned_per_voxel(cloud: Mapping[str, np.ndarray], voxel_m: float) -> dict[str, np.ndarray]:
    """One point per ``voxel_m`` cube: the best conditioned (smallest ``depth_sigma``; of equals, the
    first); 0 keeps all.

    Every view that sees a surface seeds points of its own where no earlier seed claimed its pixels,
    so the more views a flight has, the more points each patch of surface gets, from far and narrow-
    baseline views too. Keeping the best conditioned point of each small cube keeps the cloud's
    density near the survey's GSD and lets a view added to a flight only replace a patch's point by
    a better measured one, never add a worse one beside it.
    """
    if voxel_m <= 0 or len(cloud["points"]) == 0:
        return dict(cloud)
    cells = np.floor(cloud["points"] / voxel_m).astype(np.int64)
    order = np.lexsort((cloud["depth_sigma"], cells[:, 2], cells[:, 1], cells[:, 0]))
    sorted_cells = cells[order]
    first = np.ones(len(order), bool)
    first[1:] = np.any(sorted_cells[1:] != sorted_cells[:-1], axis=1)
    keep = np.sort(order[first])
    return {key: value[keep] for key, value in cloud.items()}


def back_project_pixels(view, cols: np.ndarray, rows: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points (N, 3) of pixels (``cols``, ``rows``) at depths ``depth`` along the optical axis."""
    rays = np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float64) @ np.linalg.inv(view.K).T
    return view.center + (rays * np.asarray(depth, np.float64)[:, None]) @ view.rotation


def _precision(
    depth: np.ndarray, focal_px: float, baseline_m: float, cos_incidence: np.ndarray | None, slant_px: float
) -> np.ndarray:
    """1 / sigma^2 (1/m^2) of depth measurements (z, B in metres): the stereo model's sigma_z at one
    pixel of disparity noise and, for ``slant_px`` > 0, the window's spread on a slanted surface."""
    z = np.maximum(depth, 1e-6)
    variance = stereo_depth_sigma(z, focal_px, baseline_m, 1.0) ** 2
    if slant_px > 0:
        variance = variance + slant_depth_sigma(z, focal_px, cos_incidence, slant_px) ** 2
    return 1.0 / variance


def _cos_incidence(rays: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each ray (N, 3, any length) and its surface normal (N, 3)."""
    dot = np.abs(np.einsum("ij,ij->i", rays, normals))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.nan_to_num(dot / (np.linalg.norm(rays, axis=1) * np.linalg.norm(normals, axis=1)))


def _colours(workspace: Path, name: str, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    image = cv2.imread(str(Path(workspace) / "images" / name), cv2.IMREAD_COLOR)
    if image is None:
        return np.full((len(rows), 3), 0.5)
    return image[rows, cols, ::-1].astype(np.float64) / 255.0
