"""Where a user's model meets the ground: the ground height, and pads under parts that would float.

A model whose nave reaches deeper than its choir, placed with its lowest point on the ground,
leaves the choir hovering above a slit that no real building has. ``floating_pads`` finds connected
pieces whose
base hangs between ``PAD_MIN_GAP_M`` and ``snap_m`` above the ground with nothing of the model under
it and fills the gap with a plinth of the part's footprint (on a ``cell_m`` raster), its top just
under the part. ``footprint_ground_height`` is the height under most of the model's footprint.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh
from scipy import ndimage

from scene.enclosure import raycasting_scene

PAD_MIN_GAP_M = 0.01  # a gap below this is no slit (the ground already meets the part)
PAD_TOP_BELOW_M = 0.005  # the pad's top sits this far under the part (no coplanar faces)
PAD_MIN_AREA_M2 = 2.0  # smaller floating bases (a sill, a bracket) are details, not slits
BASE_BAND_M = 0.05  # a face within this of a part's lowest point belongs to its base


def footprint_ground_height(mesh: trimesh.Trimesh, cell_m: float = 0.5) -> float:
    """The most common height (0.1 m bins) of the model's lowest surface over its footprint (m)."""
    lo, hi = mesh.bounds
    xs = np.arange(lo[0] + 0.5 * cell_m, hi[0], cell_m)
    ys = np.arange(lo[1] + 0.5 * cell_m, hi[1], cell_m)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    n = gx.size
    rays = np.column_stack([gx.ravel(), gy.ravel(), np.full(n, lo[2] - 1.0), np.zeros((n, 2)), np.ones(n)])
    t = raycasting_scene(mesh).cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    heights = lo[2] - 1.0 + t[np.isfinite(t)]
    if len(heights) == 0:
        return float(lo[2])
    bins = np.round(heights / 0.1).astype(np.int64)
    values, counts = np.unique(bins, return_counts=True)
    mode = values[np.argmax(counts)] * 0.1
    return float(heights[np.abs(heights - mode) <= 0.05].min())


def floating_pads(
    parts: list[tuple[np.ndarray, np.ndarray]],
    snap_m: float,
    cell_m: float = 0.25,
    support: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plinths (vertices, faces) under the pieces (world metres, ground z = 0) that float a little.

    Args:
        parts: (vertices, faces) of every part of the model.
        snap_m: largest gap (m) filled; 0 fills none (the model says its parts float).
        cell_m: raster of the pads' outlines (m).
        support: what may hold a piece up (default ``parts``): the whole model, with the faces
            dropped for lying on the ground (a hall's floor slab holds its interior up).
    """
    if snap_m <= 0 or not parts:
        return []
    support = parts if support is None else support
    offsets = np.cumsum([0] + [len(v) for v, _ in support[:-1]])
    whole = trimesh.Trimesh(
        np.concatenate([v for v, _ in support]),
        np.concatenate([f + o for (_, f), o in zip(support, offsets, strict=True)]),
        process=False,
    )
    scene = raycasting_scene(whole)
    pads = []
    for vertices, faces in _components(parts):
        used = vertices[np.unique(faces)]
        z0 = float(used[:, 2].min())
        if not PAD_MIN_GAP_M < z0 <= snap_m:
            continue
        base = faces[(vertices[faces][:, :, 2] < z0 + BASE_BAND_M).all(axis=1)]
        if len(base) == 0:
            continue
        points = _base_points(vertices, base, cell_m)
        # Unsupported: nothing of the model between the point and the ground.
        down = np.column_stack(
            [points[:, :2], points[:, 2] - 0.01, np.zeros((len(points), 2)), -np.ones(len(points))]
        )
        t = scene.cast_rays(o3d.core.Tensor(down.astype(np.float32)))["t_hit"].numpy()
        free = points[~np.isfinite(t)]  # the ground is not in ``support``: any hit holds it up
        if len(free) == 0:
            continue
        origin = free[:, :2].min(axis=0) - cell_m
        ij = np.floor((free[:, :2] - origin) / cell_m).astype(np.int64)
        grid = np.zeros(ij.max(axis=0) + 2, bool)
        grid[ij[:, 0], ij[:, 1]] = True
        grid = ndimage.binary_fill_holes(ndimage.binary_closing(grid))
        if grid.sum() * cell_m * cell_m < PAD_MIN_AREA_M2:
            continue
        pads.append(_columns_mesh(grid, origin, cell_m, z0 - PAD_TOP_BELOW_M))
    return pads


def _components(parts: list[tuple[np.ndarray, np.ndarray]]):
    """The connected pieces (vertices, faces) of every part: one file part may hold a whole building."""
    for vertices, faces in parts:
        mesh = trimesh.Trimesh(vertices, faces, process=True, validate=False)  # merges shared corners
        for piece in mesh.split(only_watertight=False):
            yield np.asarray(piece.vertices, float), np.asarray(piece.faces, np.int64)


def _base_points(vertices: np.ndarray, faces: np.ndarray, cell_m: float) -> np.ndarray:
    """Points on the base faces at least one per ``cell_m / 2`` square, plus their corners."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    count = int(np.ceil(mesh.area / (0.25 * cell_m * cell_m))) + 1
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    return np.concatenate([samples, vertices[np.unique(faces)]])


def _columns_mesh(grid: np.ndarray, origin: np.ndarray, cell_m: float, top: float):
    """Closed-top prism of the occupied raster cells from z = 0 to ``top``: top and outer sides."""
    i, j = np.nonzero(grid)
    x0, y0 = origin[0] + i * cell_m, origin[1] + j * cell_m
    x1, y1 = x0 + cell_m, y0 + cell_m
    zeros, tops = np.zeros_like(x0), np.full_like(x0, top)
    quads = [
        np.stack(
            [np.column_stack(c) for c in ((x0, y0, tops), (x1, y0, tops), (x1, y1, tops), (x0, y1, tops))], 1
        )
    ]
    padded = np.pad(grid, 1)
    sides = {  # neighbour offset -> the quad's corners (counter-clockwise seen from outside)
        (1, 0): ((x1, y0, zeros), (x1, y1, zeros), (x1, y1, tops), (x1, y0, tops)),
        (-1, 0): ((x0, y1, zeros), (x0, y0, zeros), (x0, y0, tops), (x0, y1, tops)),
        (0, 1): ((x1, y1, zeros), (x0, y1, zeros), (x0, y1, tops), (x1, y1, tops)),
        (0, -1): ((x0, y0, zeros), (x1, y0, zeros), (x1, y0, tops), (x0, y0, tops)),
    }
    for (di, dj), corners in sides.items():
        open_side = ~padded[i + 1 + di, j + 1 + dj]
        quads.append(np.stack([np.column_stack([a[open_side] for a in corner]) for corner in corners], 1))
    quads = np.concatenate(quads)  # (Q, 4, 3)
    vertices = quads.reshape(-1, 3)
    base = 4 * np.arange(len(quads))[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices, faces.astype(np.int64)
