"""Reading a reconstruction to score: any point cloud or mesh file -> world points (N, 3) in metres."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from evaluate.geometry import sample_surface

# Read with trimesh: meshes (faces) or vertex-only point clouds.
TRIMESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf")
# Read with Open3D's point-cloud reader.
OPEN3D_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
# A NumPy array (N, 3) (or (N, >3): the first three columns are x, y, z).
NUMPY_SUFFIXES = (".npy",)
SUPPORTED_SUFFIXES = TRIMESH_SUFFIXES + OPEN3D_SUFFIXES + NUMPY_SUFFIXES


class ReconstructionFileError(ValueError):
    """A file that cannot be read as a point cloud or mesh (the message names it)."""


def load_reconstruction(
    path: str | Path,
    mesh_input: str = "vertices",
    mesh_density_per_m2: float = 10000.0,
    seed: int = 0,
    max_samples: int | None = None,
) -> tuple[np.ndarray, str]:
    """The points to score from a point-cloud or mesh file, in the file's (world) metres.

    Meshes are scored by their vertices (``mesh_input="vertices"``: what a fused MVS mesh's
    accuracy is usually quoted on) or by samples of their surface (``"surface"``: uniform by area at
    ``mesh_density_per_m2``, deterministic by ``seed``; fairer for meshes with large triangles).

    Args:
        path: PLY/OBJ/OFF/STL/GLB/GLTF (trimesh), PCD/XYZ/XYZN/XYZRGB/PTS (Open3D) or NPY.
        mesh_input: ``vertices`` or ``surface``.
        mesh_density_per_m2: samples per square metre for ``surface``.
        seed: seed of the surface samples.
        max_samples: refuse a ``surface`` sampling that would draw more points than this (memory:
            a 15,000 m^2 proxy at 10,000 samples/m^2 is 150 M points, 20 GB while scoring).

    Returns:
        points (N, 3) float64 (N may be 0), and the kind: ``point_cloud``, ``mesh_vertices`` or
        ``mesh_surface_samples``.

    Raises:
        FileNotFoundError: no such file.
        ReconstructionFileError: unsupported suffix, or the content is not a point cloud or mesh.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"reconstruction file not found: {path}")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ReconstructionFileError(
            f"{path}: unsupported file type {suffix or '(no suffix)'!r}; "
            f"expected one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    if path.stat().st_size == 0:
        raise ReconstructionFileError(f"{path}: empty file, not a point cloud or mesh")
    if suffix in NUMPY_SUFFIXES:
        return _load_numpy(path), "point_cloud"
    if suffix in OPEN3D_SUFFIXES:
        return _load_open3d(path), "point_cloud"
    return _load_trimesh(path, mesh_input, mesh_density_per_m2, seed, max_samples)


def _load_numpy(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise ReconstructionFileError(f"{path}: not a NumPy array file ({exc})") from exc
    if array.ndim != 2 or array.shape[1] < 3 or not np.issubdtype(array.dtype, np.number):
        raise ReconstructionFileError(
            f"{path}: expected a numeric (N, 3) array, got {array.dtype} {array.shape}"
        )
    return np.asarray(array[:, :3], dtype=np.float64)


def _load_open3d(path: Path) -> np.ndarray:
    # heavy (open3d): imported on use
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format="auto")
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0 and not _has_only_blank_lines(path):
        raise ReconstructionFileError(f"{path}: Open3D read no points; not a point cloud")
    return points


def _has_only_blank_lines(path: Path) -> bool:
    try:
        return path.read_text().strip() == ""
    except UnicodeDecodeError:
        return False


def _load_trimesh(
    path: Path, mesh_input: str, density: float, seed: int, max_samples: int | None = None
) -> tuple[np.ndarray, str]:
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ReconstructionFileError(
            f"{path}: not a point cloud or mesh ({type(exc).__name__}: {exc})"
        ) from exc
    geometries = list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene) else [loaded]
    if isinstance(loaded, trimesh.Scene):
        if not geometries and _ply_vertex_count(path) == 0:
            return np.zeros((0, 3)), "point_cloud"
        if not geometries:
            raise ReconstructionFileError(f"{path}: holds no geometry; not a point cloud or mesh")
        geometries = [g.copy().apply_transform(t) for g, t in _scene_instances(loaded)]
    meshes = [g for g in geometries if isinstance(g, trimesh.Trimesh)]
    clouds = [g for g in geometries if isinstance(g, trimesh.PointCloud)]
    other = [type(g).__name__ for g in geometries if not isinstance(g, trimesh.Trimesh | trimesh.PointCloud)]
    if other:
        raise ReconstructionFileError(f"{path}: holds {', '.join(other)}, not a point cloud or mesh")
    parts = [np.asarray(c.vertices, dtype=np.float64).reshape(-1, 3) for c in clouds]
    with_faces = [m for m in meshes if len(m.faces)]
    kind = "point_cloud"
    if with_faces and mesh_input == "surface":
        mesh = trimesh.util.concatenate(with_faces) if len(with_faces) > 1 else with_faces[0]
        parts.append(sample_surface(mesh, density, seed, max_samples)[0])
        kind = "mesh_surface_samples"
    else:
        parts.extend(np.asarray(m.vertices, dtype=np.float64).reshape(-1, 3) for m in meshes)
        kind = "mesh_vertices" if with_faces else kind
    return (np.concatenate(parts) if parts else np.zeros((0, 3))), kind


def _ply_vertex_count(path: Path) -> int | None:
    """The vertex count a PLY header declares, or None when ``path`` has no valid PLY header."""
    with path.open("rb") as f:
        if f.readline().strip() != b"ply":
            return None
        count = None
        for _ in range(200):
            words = f.readline().split()
            if words[:2] == [b"element", b"vertex"] and len(words) == 3 and words[2].isdigit():
                count = int(words[2])
            if words == [b"end_header"]:
                return count
    return None


def _scene_instances(scene: trimesh.Scene):
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        yield scene.geometry[name], transform
