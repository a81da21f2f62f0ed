"""Closed volumes of a mesh: where no camera may fly (and, for scoring, what no camera can see).

One ray-casting test, shared by the planners (candidate rejection), the plan check every cell runs
before rendering (``mission.validate``) and the scoring.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh

# Share of a position's rays that must leave an interior for it to count as enclosed (a camera in
# a doorway or under an eave still sees out along most rays).
ENCLOSED_BACK_FRACTION = 0.75
_GRID = np.array(
    [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)]
)
GRID_DIRECTIONS = (_GRID / np.linalg.norm(_GRID, axis=1, keepdims=True)).astype(np.float32)


def raycasting_scene(mesh: trimesh.Trimesh) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ray-casting scene of a triangle mesh (world metres)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
    )
    return scene


def enclosed_positions(
    scene: o3d.t.geometry.RaycastingScene,
    positions: np.ndarray,
    min_back_fraction: float = ENCLOSED_BACK_FRACTION,
) -> np.ndarray:
    """(N,) bool: positions (N, 3) inside a closed part of the mesh.

    From each position rays leave along the 26 directions of a 3 x 3 x 3 grid; a position is
    enclosed when at least ``min_back_fraction`` of them first hit the mesh from behind (the ray
    runs along the hit face's outward normal: it left an interior). A camera under an eave or in a
    courtyard sees open sky or outer faces along most rays; one inside a hall does not.
    """
    q = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    if len(q) == 0:
        return np.zeros(0, bool)
    dirs = GRID_DIRECTIONS
    rays = np.concatenate([np.repeat(q, len(dirs), axis=0), np.tile(dirs, (len(q), 1))], axis=1)
    hits = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    hit = np.isfinite(hits["t_hit"].numpy())
    normals = hits["primitive_normals"].numpy()
    back = hit & (np.einsum("ij,ij->i", normals, rays[:, 3:]) > 0)
    return back.reshape(len(q), len(dirs)).mean(axis=1) >= float(min_back_fraction)
