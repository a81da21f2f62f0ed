"""Closed volumes of a mesh: where no camera may fly (and, for scoring, what no camera can see).

One ray-casting test, shared by the planners (candidate rejection), the plan check every cell runs
before rendering (``mission.validate``) and the scoring.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree

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
    """(N,) bool: positions (N, 3) inside a closed part of the mesh, whatever its faces' orientation.

    Two tests, either enough:

    - **Back faces**: rays along the 26 directions of a 3 x 3 x 3 grid; at least
      ``min_back_fraction`` of them first hit the mesh from behind (the ray runs along the hit
      face's outward normal: it left an interior).
    - **No way out**: of ``ENCLOSED_DIRECTIONS`` rays spread evenly over the sphere, at least
      ``ENCLOSED_HIT_FRACTION`` hit the mesh at all, front or back. A hall whose interior walls
      face inwards (a scan of a building with its rooms) passes the first test's sight lines as
      front faces; from its inside almost no ray escapes (a door or windows: a few per cent of the
      sphere), while a camera in a courtyard sees the sky above it and one under an eave the open
      side, a quarter or more of the sphere.
    """
    q = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    if len(q) == 0:
        return np.zeros(0, bool)
    hit, back = _first_hits(scene, q, GRID_DIRECTIONS)
    behind = back.mean(axis=1) >= float(min_back_fraction)
    hit_any, _ = _first_hits(scene, q, SPHERE_DIRECTIONS)
    return behind | (hit_any.mean(axis=1) >= ENCLOSED_HIT_FRACTION)


def _first_hits(scene, positions: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, D) bool each: whether the ray from each position along each direction hits the mesh,
    and whether it hits a face from behind."""
    rays = np.concatenate(
        [np.repeat(positions, len(dirs), axis=0), np.tile(dirs, (len(positions), 1))], axis=1
    )
    hits = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    hit = np.isfinite(hits["t_hit"].numpy())
    back = hit & (np.einsum("ij,ij->i", hits["primitive_normals"].numpy(), rays[:, 3:]) > 0)
    return hit.reshape(len(positions), len(dirs)), back.reshape(len(positions), len(dirs))


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere (Fibonacci lattice), a fixed order."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z]).astype(np.float32)


# The "no way out" test of enclosed_positions: 64 directions (each about 1/64 of the sphere, 0.2 sr)
# and the share that must hit: 61 of 64, so a door or a row of windows (up to 3 of them) still
# reads inside, and a courtyard's sky or an eave's open side (16 or more) reads outside.
ENCLOSED_DIRECTIONS = 64
ENCLOSED_HIT_FRACTION = 61 / 64
SPHERE_DIRECTIONS = sphere_directions(ENCLOSED_DIRECTIONS)


# exposed_samples(): first-hop rays per sample (over its half-space; a wall sample under an eave
# sees out along rays slightly below its tangent plane, hence the negative cosine), the start
# offset off the surface, and the free length a ray must run before its midpoint may serve as a
# camera position (a drone needs room).
EXPOSURE_DIRECTIONS = 48
EXPOSURE_MIN_COS = -0.1
EXPOSURE_OFFSET_M = 0.01
EXPOSURE_FREE_M = 2.0
# From a free midpoint the open is looked for along the grid directions that do not point down
# (the sky and the horizon; the ground is below).
OPEN_DIRECTIONS = GRID_DIRECTIONS[GRID_DIRECTIONS[:, 2] >= 0]


def exposed_samples(
    scene: o3d.t.geometry.RaycastingScene,
    points: np.ndarray,
    normals: np.ndarray,
    n_directions: int = EXPOSURE_DIRECTIONS,
) -> np.ndarray:
    """(N,) bool: surface samples that a camera in the open could see.

    A sample is exposed when a ray from it (started ``EXPOSURE_OFFSET_M`` off the surface along its
    normal; along the normal first, then ``n_directions`` fixed directions of its half-space) either
    leaves the scene level or upwards without hitting anything (below z = 0 is earth), or runs at
    least ``EXPOSURE_FREE_M`` and its midpoint sees the open along one of 17 level or upward
    directions (a camera in a walled courtyard or under deep eaves). Faces buried inside other
    parts, the inside of a sealed hall and a box sealed inside another reach the open along no
    such path: no exterior camera can see them. Vectorised: each round casts one direction for
    every sample still unresolved.
    """
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
    exposed = np.zeros(len(p), bool)
    if len(p) == 0:
        return exposed
    origins = p + EXPOSURE_OFFSET_M * n

    def cast(starts: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = np.concatenate([starts, dirs], axis=1).astype(np.float32)
        return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()

    def resolve(rows: np.ndarray, dirs: np.ndarray) -> None:
        t = cast(origins[rows], dirs)
        # Below z = 0 is earth: a ray that leaves the scene downwards went under the ground's edge.
        escaped = ~np.isfinite(t) & (dirs[:, 2] >= 0.0) & (origins[rows, 2] >= 0.0)
        exposed[rows[escaped]] = True
        room = np.flatnonzero(np.isfinite(t) & (t >= EXPOSURE_FREE_M))
        middles = origins[rows[room]] + dirs[room] * (0.5 * t[room])[:, None]
        room, middles = room[middles[:, 2] >= 0.0], middles[middles[:, 2] >= 0.0]
        if len(room) == 0:
            return
        k = len(OPEN_DIRECTIONS)
        t2 = cast(np.repeat(middles, k, axis=0), np.tile(OPEN_DIRECTIONS, (len(middles), 1)))
        sees_open = (~np.isfinite(t2)).reshape(len(middles), k).any(axis=1)
        exposed[rows[room[sees_open]]] = True

    resolve(np.arange(len(p)), n)
    for d in sphere_directions(n_directions):
        rows = np.flatnonzero(~exposed)
        if len(rows) == 0:
            break
        rows = rows[n[rows] @ d >= EXPOSURE_MIN_COS]
        if len(rows):
            resolve(rows, np.broadcast_to(d, (len(rows), 3)))
    return exposed


# exposure(): above this many samples, rays are cast from an even subsample of this size and every
# sample takes the answer of its nearest subsample facing the same way (exposure changes over
# decimetres, samples lie millimetres to centimetres apart); normals weigh this much per unit.
EXPOSURE_MAX_CAST = 400_000
EXPOSURE_NORMAL_WEIGHT_M = 0.5


def exposure(
    scene: o3d.t.geometry.RaycastingScene,
    points: np.ndarray,
    normals: np.ndarray,
    max_cast: int = EXPOSURE_MAX_CAST,
) -> np.ndarray:
    """``exposed_samples`` for millions of samples: cast for at most ``max_cast`` of them.

    ``points`` should be spatially ordered (as the evaluation's Z-ordered samples are), so that
    every k-th sample is an even subsample.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(p) <= max_cast:
        return exposed_samples(scene, p, n)
    step = int(np.ceil(len(p) / max_cast))
    sub = np.arange(0, len(p), step)
    answer = exposed_samples(scene, p[sub], n[sub])
    tree = cKDTree(np.hstack([p[sub], EXPOSURE_NORMAL_WEIGHT_M * n[sub]]))
    _, nearest = tree.query(np.hstack([p, EXPOSURE_NORMAL_WEIGHT_M * n]), k=1, workers=-1)
    return answer[nearest]
