"""Uniform-by-area sampling of surface points and normals on a (proxy) triangle mesh."""

from __future__ import annotations

import numpy as np
import trimesh

from scene.plan import PlanningError


def validate_proxy(mesh: trimesh.Trimesh, name: str = "proxy") -> trimesh.Trimesh:
    """Return ``mesh`` if it has finite vertices and positive surface area; raise PlanningError.

    Args:
        mesh: triangle mesh in world metres.
        name: what the mesh is, for the message.
    """
    if mesh is None or not isinstance(mesh, trimesh.Trimesh):
        raise PlanningError(f"{name} must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise PlanningError(f"{name} mesh is empty (no faces): nothing to plan for")
    if not np.all(np.isfinite(mesh.vertices)):
        raise PlanningError(f"{name} mesh has NaN or infinite vertices")
    areas = mesh.area_faces
    if not np.isfinite(areas).all() or float(areas.sum()) <= 0.0:
        raise PlanningError(f"{name} mesh is degenerate: total surface area is {float(areas.sum())} m^2")
    return mesh


def sample_surface(mesh: trimesh.Trimesh, n_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points uniformly by area on a mesh, with the unit normals of their faces.

    Deterministic for a fixed ``seed`` (numpy ``default_rng``). Faces of zero area are never picked.

    Args:
        mesh: triangle mesh in world metres (normals follow the face winding).
        n_points: number of samples (>= 1).
        seed: random seed.

    Returns:
        points (P, 3) in metres and normals (P, 3) unit vectors, both float64.
    """
    validate_proxy(mesh)
    if int(n_points) < 1:
        raise PlanningError(f"n_points must be >= 1, got {n_points}")
    rng = np.random.default_rng(seed)
    areas = mesh.area_faces.astype(float)
    face_index = rng.choice(len(areas), size=int(n_points), p=areas / areas.sum())
    triangles = mesh.vertices[mesh.faces[face_index]]
    # Uniform barycentric sampling: fold the unit square onto the triangle.
    r = rng.random((int(n_points), 2))
    flip = r.sum(axis=1) > 1.0
    r[flip] = 1.0 - r[flip]
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    points = a + r[:, :1] * (b - a) + r[:, 1:] * (c - a)
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals
