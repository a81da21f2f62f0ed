"""Visibility against an independent brute-force check (camera projection + trimesh ray casting)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from planner.sampling import sample_surface
from planner.visibility import VisibilityCache, VisibilityLimits, VisibilityModel
from scene.camera import Intrinsics, project_points
from scene.plan import PlanningError
from tests.planner_scenes import box_building

INTRINSICS = Intrinsics(320, 240, 60.0)
LIMITS = VisibilityLimits(min_distance_m=2.0, max_distance_m=40.0, max_incidence_deg=80.0)


def _scene_with_occluder() -> trimesh.Trimesh:
    building = box_building(size=(10.0, 8.0, 6.0), ground_half=25.0)
    wall = trimesh.creation.box(extents=(1.0, 4.0, 4.0))
    wall.apply_translation((9.0, 0.0, 2.0))  # stands in front of the +x face
    return trimesh.util.concatenate([building, wall])


def _viewpoints() -> np.ndarray:
    return np.array(
        [
            [20.0, 0.0, 3.0, 180.0, 0.0],  # looks at the +x face through the wall
            [0.0, 0.0, 25.0, 0.0, -90.0],  # nadir above the roof
            [15.0, 15.0, 10.0, -135.0, -20.0],
            [-18.0, 5.0, 4.0, -10.0, -5.0],
            [3.0, -22.0, 8.0, 95.0, -15.0],
        ]
    )


def _brute_force(mesh, points, normals, vps) -> np.ndarray:
    pixels, depth = project_points(points, vps, INTRINSICS)
    expected = np.zeros((len(vps), len(points)), bool)
    origins_all = points + 0.02 * normals
    for v, vp in enumerate(vps):
        for p in range(len(points)):
            to_cam = vp[:3] - points[p]
            dist = float(np.linalg.norm(to_cam))
            u, w = pixels[v, p]
            if depth[v, p] <= 0 or not (0 <= u <= INTRINSICS.width and 0 <= w <= INTRINSICS.height):
                continue
            if not (LIMITS.min_distance_m <= dist <= LIMITS.max_distance_m):
                continue
            if float(normals[p] @ to_cam) / dist < math.cos(math.radians(LIMITS.max_incidence_deg)):
                continue
            expected[v, p] = True
    # Occlusion: any triangle hit strictly between the lifted point and the camera centre.
    vi, pi = np.nonzero(expected)
    seg = vps[vi, :3] - origins_all[pi]
    length = np.linalg.norm(seg, axis=1)
    locations, ray_idx, _ = mesh.ray.intersects_location(origins_all[pi], seg / length[:, None])
    hit_dist = np.linalg.norm(locations - origins_all[pi][ray_idx], axis=1)
    blocked = np.zeros(len(vi), bool)
    blocked[ray_idx[hit_dist < length[ray_idx] - 1e-3]] = True
    expected[vi[blocked], pi[blocked]] = False
    return expected, int(blocked.sum())


def test_visibility_matches_brute_force_with_occlusion():
    mesh = _scene_with_occluder()
    points, normals = sample_surface(mesh, 600, seed=3)
    vps = _viewpoints()
    model = VisibilityModel(mesh, points, normals, INTRINSICS, LIMITS, ray_offset_m=0.02)
    got = model.observe(vps)
    expected, n_blocked = _brute_force(mesh, points, normals, vps)
    assert n_blocked > 20  # the wall and the building really occlude something
    mismatches = int((got.visible != expected).sum())
    # float32 (Open3D) vs float64 (trimesh) may disagree on a pair grazing an edge; nothing more.
    assert mismatches <= 2, mismatches
    assert got.visible.sum() > 300
    # the geometry returned with the matrix
    d = np.linalg.norm(vps[:, None, :3] - points[None], axis=-1)
    np.testing.assert_allclose(got.distance, d, rtol=1e-5, atol=1e-4)
    unit = (vps[:, None, :3] - points[None]) / d[..., None]
    np.testing.assert_allclose(got.direction[got.visible], unit[got.visible], atol=1e-5)
    np.testing.assert_array_equal(got.direction[~got.visible], 0.0)
    np.testing.assert_allclose(got.cos_incidence, np.einsum("vpk,pk->vp", unit, normals), atol=1e-5)


def test_wall_hides_the_face_behind_it():
    mesh = _scene_with_occluder()
    points = np.array([[5.0, 0.0, 2.0], [5.0, 3.5, 5.5]])  # behind the wall; beside and above it
    normals = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    model = VisibilityModel(mesh, points, normals, INTRINSICS, LIMITS)
    vis = model.visibility(np.array([[20.0, 0.0, 2.0, 180.0, 0.0]]))
    assert vis.tolist() == [[False, True]]
    assert model.rays_cast == 2


def test_cache_updates_only_changed_rows():
    mesh = _scene_with_occluder()
    points, normals = sample_surface(mesh, 300, seed=1)
    model = VisibilityModel(mesh, points, normals, INTRINSICS, LIMITS)
    vps = _viewpoints()
    cache = VisibilityCache(model, vps)
    moved = vps.copy()
    moved[[1, 3], 2] += 3.0
    cache.update([1, 3], moved[[1, 3]])
    np.testing.assert_array_equal(cache.visibility, model.visibility(moved))
    cache.remove([0])
    cache.append(vps[:1])
    np.testing.assert_array_equal(cache.visibility, model.visibility(np.concatenate([moved[1:], vps[:1]])))


def test_clearance_is_distance_to_the_surface():
    mesh = box_building(size=(10.0, 8.0, 6.0), ground_half=None)
    model = VisibilityModel(mesh, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), INTRINSICS, LIMITS)
    queries = np.array([[8.0, 0, 3], [0, 0, 10], [8, 7, 9]])
    np.testing.assert_allclose(model.clearance(queries), [3.0, 4.0, math.sqrt(27.0)], atol=1e-4)


def test_bad_limits_and_empty_proxy_raise():
    with pytest.raises(PlanningError, match="min_distance_m < max_distance_m"):
        VisibilityLimits(10.0, 5.0, 80.0)
    with pytest.raises(PlanningError, match="max_incidence_deg"):
        VisibilityLimits(1.0, 5.0, 95.0)
    with pytest.raises(PlanningError, match="empty"):
        VisibilityModel(trimesh.Trimesh(), np.zeros((1, 3)), np.ones((1, 3)), INTRINSICS, LIMITS)


def test_positions_inside_a_closed_hall_are_enclosed_and_outside_ones_not():
    hall = box_building(size=(40.0, 24.0, 15.0), ground_half=60.0)
    eave = trimesh.creation.box(extents=(4.0, 24.0, 0.5))  # a roof overhang on the +x side
    eave.apply_translation((22.0, 0.0, 12.0))
    proxy = trimesh.util.concatenate([hall, eave])
    model = VisibilityModel(proxy, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), INTRINSICS, LIMITS)
    positions = np.array(
        [
            [0.0, 0.0, 7.0],  # the middle of the hall
            [15.0, 8.0, 3.0],  # a corner of the hall, near the floor
            [0.0, 0.0, 30.0],  # above the roof
            [25.0, 0.0, 6.0],  # under the eave, beside the wall
            [-30.0, 0.0, 2.0],  # in front of a wall
        ]
    )
    np.testing.assert_array_equal(model.enclosed(positions), [True, True, False, False, False])
