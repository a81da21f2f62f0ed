"""After fusion: keep, where a surface is seen many times over, the points that many views support.

COLMAP's fusion turns every depth pixel that at least ``min_num_pixels`` others confirm into a point;
nothing is left unfused. Where a surface is seen by a dozen views, the pixels that agree best form
the first, well-supported points (a median over many views), and the remainder, the pixels that
did not agree with those (noise, block matching's fattening at occlusion edges, grazing views),
still form points of their own from the few views that happen to agree with each other. The more
views a flight has, the more such leftovers it fuses: the cloud's error tail grows with redundancy
(``tests/test_dense_quality.py`` shows it on a box edge).

The support filter keeps a fused point when the number of views that support it is at least
``share`` of the best-supported point within ``radius_m`` (a 3 x 3 x 3 block of voxels of that
size). A sparse flight's points (2-3 views each) keep theirs; a redundant flight's leftovers, beside
points a dozen views agree on, are dropped.
"""

from __future__ import annotations

import numpy as np

_OFFSETS = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)])


def local_max_support(points: np.ndarray, support: np.ndarray, radius_m: float) -> np.ndarray:
    """(N,) the largest support of any point in each point's voxel or the 26 around it."""
    cells = np.floor(np.asarray(points, float) / float(radius_m)).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 3
    # One integer per voxel (offset by one so that the neighbours of the lowest cells stay >= 0).
    keys = ((cells[:, 0] + 1) * span[1] + (cells[:, 1] + 1)) * span[2] + (cells[:, 2] + 1)
    unique, inverse = np.unique(keys, return_inverse=True)
    cell_max = np.zeros(len(unique), dtype=np.asarray(support).dtype)
    np.maximum.at(cell_max, inverse, support)
    best = np.zeros(len(points), dtype=cell_max.dtype)
    for dx, dy, dz in _OFFSETS:
        neighbour = keys + (dx * span[1] + dy) * span[2] + dz
        at = np.searchsorted(unique, neighbour)
        found = unique[np.minimum(at, len(unique) - 1)] == neighbour
        best[found] = np.maximum(best[found], cell_max[at[found]])
    return best


def supported_points(points: np.ndarray, support: np.ndarray, radius_m: float, share: float) -> np.ndarray:
    """(N,) bool: the points whose support (views) is at least ``share`` of their local best.

    Args:
        points: (N, 3) fused points (m).
        support: (N,) views that fused each point (COLMAP's visibility).
        radius_m: the neighbourhood's voxel size (m).
        share: 0 keeps every point; 0.5 drops a point a neighbour has twice the views of.
    """
    if share <= 0 or len(points) == 0:
        return np.ones(len(points), bool)
    return support >= share * local_max_support(points, support, radius_m)
