"""Proxy meshes for the planners: Poisson mesh of the exploratory flight's dense cloud, or (not the
paper's setting, for fast planner work and tests) a decimated and noised ground-truth mesh.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from reconstruct.errors import ReconstructionError
from reconstruct.settings import ProxySettings
from scene.base import Box, Scene

log = logging.getLogger(__name__)


def crop_mesh_to_box(mesh: trimesh.Trimesh, box: Box, max_edge_m: float) -> trimesh.Trimesh:
    """The part of ``mesh`` inside ``box``, subdivided so that no edge is longer than ``max_edge_m``.

    Faces are split (midpoint subdivision) only while they touch the box, so a huge ground plane
    costs no more than the box's share of it; the kept faces are those whose centroid lies inside
    the box, which makes the crop boundary jagged at the scale of ``max_edge_m``.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    lo, hi = box.lo_array, box.hi_array
    for _ in range(64):
        tri = vertices[faces]
        touches = np.all((tri.max(axis=1) >= lo) & (tri.min(axis=1) <= hi), axis=1)
        faces = faces[touches]
        if len(faces) == 0:
            break
        tri = vertices[faces]
        edge_len = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        long_faces = np.flatnonzero(edge_len > max_edge_m)
        if len(long_faces) == 0:
            break
        vertices, faces = trimesh.remesh.subdivide(vertices, faces, face_index=long_faces)
    centroids = vertices[faces].mean(axis=1) if len(faces) else np.zeros((0, 3))
    faces = faces[box.contains(centroids)]
    out = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    out.remove_unreferenced_vertices()
    return out


def decimate(mesh: trimesh.Trimesh, face_budget: int) -> trimesh.Trimesh:
    """Quadric-error decimation (Open3D) down to at most ``face_budget`` faces; smaller meshes pass."""
    face_budget = int(face_budget)
    if face_budget < 4:
        raise ValueError(f"proxy.face_budget must be at least 4, got {face_budget}")
    if len(mesh.faces) <= face_budget:
        return mesh
    # heavy (open3d): imported on use
    import open3d as o3d

    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    simplified = o3d_mesh.simplify_quadric_decimation(target_number_of_triangles=face_budget)
    simplified.remove_degenerate_triangles()
    simplified.remove_unreferenced_vertices()
    return trimesh.Trimesh(
        vertices=np.asarray(simplified.vertices), faces=np.asarray(simplified.triangles), process=True
    )


def degraded_ground_truth(scene: Scene, proxy: ProxySettings, seed: int) -> trimesh.Trimesh:
    """A stand-in proxy: the ground truth cropped, decimated and noised. NOT the paper's setting.

    The ground-truth mesh is cropped to the scene's evaluation region (structure plus ground apron,
    about what an exploratory flight reconstructs), subdivided to ``proxy.degraded.max_edge_m``
    metres so large flat faces can carry noise, decimated to ``proxy.face_budget`` faces, and every
    vertex is moved along its normal by Gaussian noise of ``proxy.degraded.noise_sigma_m`` metres.

    Args:
        scene: the ground-truth scene.
        proxy: ``reconstruct.proxy``, typed (``ReconstructSettings.proxy``).
        seed: seed of the noise.

    Returns:
        The degraded mesh in world metres.
    """
    max_edge, sigma = proxy.degraded.max_edge_m, proxy.degraded.noise_sigma_m
    mesh = crop_mesh_to_box(scene.ground_truth_mesh, scene.evaluation_region, max_edge)
    if len(mesh.faces) == 0:
        raise ValueError(f"scene {scene.name!r}: no ground-truth surface inside the evaluation region")
    mesh = decimate(mesh, proxy.face_budget)
    rng = np.random.default_rng(seed)
    offsets = rng.normal(0.0, sigma, size=len(mesh.vertices))
    noisy = mesh.vertices + offsets[:, None] * mesh.vertex_normals
    out = trimesh.Trimesh(vertices=noisy, faces=mesh.faces, process=False)
    log.info(
        "degraded ground-truth proxy of %s: %d faces, noise sigma %.3f m", scene.name, len(out.faces), sigma
    )
    return out


def oriented_cloud(dense_ply, bounds: Box, voxel_m: float) -> dict[str, np.ndarray]:
    """The fused cloud's points and unit normals inside ``bounds``, voxel-downsampled (m).

    Returns:
        {"points": (N, 3), "normals": (N, 3)} in world metres; empty arrays when the file has no
        normals (the fusion writes them) or no point inside ``bounds``.
    """
    # heavy (open3d): imported on use
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(dense_ply))
    points = np.asarray(cloud.points)
    empty = {"points": np.zeros((0, 3)), "normals": np.zeros((0, 3))}
    if len(points) == 0 or not cloud.has_normals():
        return empty
    cloud = cloud.select_by_index(np.flatnonzero(bounds.contains(points)))
    if voxel_m > 0:
        cloud = cloud.voxel_down_sample(float(voxel_m))
    normals = np.asarray(cloud.normals)
    length = np.linalg.norm(normals, axis=1)
    keep = length > 1e-9
    return {"points": np.asarray(cloud.points)[keep], "normals": normals[keep] / length[keep, None]}


def poisson_proxy(
    dense_ply, bounds: Box, proxy: ProxySettings, deterministic: bool = False
) -> trimesh.Trimesh:
    """Proxy mesh from a fused dense cloud: crop, voxel-downsample, screened Poisson, density trim,
    crop again, decimate.

    Args:
        dense_ply: fused cloud (positions, ideally with normals) in world metres.
        bounds: region of interest in world metres (e.g. the flight's camera hull plus a margin);
            points outside it are dropped and the mesh is cut back to it.
        proxy: ``reconstruct.proxy``, typed (``ReconstructSettings.proxy``).
        deterministic: solve the Poisson system on one thread (the threaded solver's sums, and so
            the mesh's last bits, change from run to run).

    Returns:
        The proxy mesh in world metres with at most ``proxy.face_budget`` faces.

    Raises:
        ReconstructionError: the cloud is missing or has too few points inside ``bounds``.
    """
    # heavy (open3d): imported on use
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(dense_ply))
    points = np.asarray(cloud.points)
    inside = bounds.contains(points) if len(points) else np.zeros(0, bool)
    if inside.sum() < 100:
        raise ReconstructionError(
            f"{dense_ply}: {int(inside.sum())} dense points inside the proxy region; cannot mesh a proxy",
            {"stage": "proxy", "n_dense_points": len(points)},
        )
    cloud = cloud.select_by_index(np.flatnonzero(inside))
    voxel = proxy.voxel_size_m
    if voxel > 0:
        cloud = cloud.voxel_down_sample(voxel)
    if not cloud.has_normals():
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=proxy.normal_radius_m, max_nn=30))
        cloud.orient_normals_consistent_tangent_plane(15)
    log.info(
        "poisson proxy: %d points (voxel %.3f m), depth %d",
        len(cloud.points),
        voxel,
        proxy.poisson_depth,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=proxy.poisson_depth, linear_fit=False, n_threads=1 if deterministic else -1
        )
    densities = np.asarray(densities)
    mesh.remove_vertices_by_mask(densities < np.quantile(densities, proxy.density_quantile))
    # Poisson closes the surface far beyond the data; keep what lies within the cloud's own box.
    cloud_box = Box.from_points(np.asarray(cloud.points))
    vertices = np.asarray(mesh.vertices)
    mesh.remove_vertices_by_mask(~cloud_box.expanded(voxel, voxel, voxel).contains(vertices))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    out = trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.triangles), process=True)
    if len(out.faces) == 0:
        raise ReconstructionError(
            f"{dense_ply}: Poisson reconstruction produced no surface", {"stage": "proxy"}
        )
    return decimate(out, proxy.face_budget)
