"""Depth-map filtering before fusion: what a depth must show to be kept (CPU back-end).

Two tests, each a setting of ``reconstruct.dense`` (off: the maps as SGBM left them):

- **Occlusion edges** (``edge_margin_px``): block matching fattens the foreground at a depth
  discontinuity: a window straddling the edge matches on the near surface's texture, so the far
  surface's pixels next to the edge take the near depth (points floating in front of the far
  surface). Pixels within the margin of a depth jump larger than ``EDGE_REL_JUMP`` are dropped.
- **Multi-view geometric consistency** (``geometric_consistency``): a depth is kept when at least
  ``min_views`` of the view's ``num_views`` most overlapping views have, where its point projects,
  a depth of their own within ``rel_tol`` of the point's depth in that view (COLMAP's and OpenMVS's
  filter). A wrong match is rarely repeated by the matching of another view, so the depths that
  survive are the ones several views measured; occluded points find no support and are dropped
  only when no view confirms them.

Vectorised over whole maps: one projection of every pixel of the reference into each neighbour.
"""

from __future__ import annotations

import cv2
import numpy as np

# A depth jump larger than this (relative to the nearer depth) inside the edge window is an
# occlusion edge (the same threshold as the normal estimation's, reconstruct.dense).
EDGE_REL_JUMP = 0.05


def edge_pixels(depth: np.ndarray, margin_px: int, rel_jump: float = EDGE_REL_JUMP) -> np.ndarray:
    """(H, W) bool: pixels with a depth within ``margin_px`` of a depth jump over ``rel_jump``.

    The jump is measured across every (2 margin + 1) square window: the window's largest depth
    over its smallest, NaN (no depth) ignored.
    """
    if margin_px <= 0:
        return np.zeros(depth.shape, bool)
    valid = np.isfinite(depth)
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8)
    hi = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel)
    lo = cv2.erode(np.where(valid, depth, np.inf).astype(np.float32), kernel)
    with np.errstate(invalid="ignore", over="ignore"):  # windows without a depth: lo is inf
        return valid & (hi > (1.0 + rel_jump) * lo)


def project(points: np.ndarray, K: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """World points (..., 3) in a view: (columns, rows) in OpenCV pixels and depths (m)."""
    cam = points @ rotation.T + translation
    z = cam[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = K[0, 0] * cam[..., 0] / z + K[0, 2]
        v = K[1, 1] * cam[..., 1] / z + K[1, 2]
    return u, v, z


def back_project(depth: np.ndarray, K: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """World points (H, W, 3) of a depth map (depth along the optical axis; NaN stays NaN)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    cam = rays * depth[..., None]
    return (cam - translation) @ rotation


def geometric_support(ref, depth: np.ndarray, neighbours, rel_tol: float) -> np.ndarray:
    """(H, W) int: how many neighbours confirm each depth of the reference.

    Args:
        ref: the reference view (``reconstruct.dense.View``: OpenCV ``K``, cam_from_world).
        depth: its depth map (H, W), NaN where none.
        neighbours: (view, depth map) pairs of the views to check against.
        rel_tol: a neighbour confirms when its own depth at the projection lies within this
            (relative) of the point's depth in the neighbour.
    """
    points = back_project(depth.astype(np.float64), ref.K, ref.rotation, ref.translation)
    support = np.zeros(depth.shape, np.int32)
    for view, other in neighbours:
        u, v, z = project(points, view.K, view.rotation, view.translation)
        col, row = np.rint(u), np.rint(v)
        inside = (z > 0) & (col >= 0) & (col < view.width) & (row >= 0) & (row < view.height)
        measured = np.full(depth.shape, np.nan)
        measured[inside] = other[row[inside].astype(int), col[inside].astype(int)]
        with np.errstate(invalid="ignore"):
            support += np.abs(measured - z) <= rel_tol * z
    return support
