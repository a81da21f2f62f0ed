"""Lawnmower flights: measured overlaps on flat ground, image count, aiming, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from planner.lawnmower.lawnmower import plan, plan_exploration, structure_bounds_from_proxy
from scene.base import Box
from scene.camera import Intrinsics, project_points, world_from_cam_rotation
from scene.plan import PlanningError

CAMERA = Intrinsics(1024, 768, 60.0)
TOMB_BOUNDS = Box((-20.0, -15.0, 0.0), (20.0, 15.0, 12.0))


def ground_footprint(viewpoint: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The image's four corners projected onto z = 0: a (4, 2) polygon, counter-clockwise."""
    corners = np.array(
        [[0, 0], [intrinsics.width, 0], [intrinsics.width, intrinsics.height], [0, intrinsics.height]]
    )
    rays_cam = np.column_stack([(corners - [intrinsics.cx, intrinsics.cy]) / intrinsics.focal_px, np.ones(4)])
    rays_world = rays_cam @ world_from_cam_rotation(viewpoint[3], viewpoint[4]).T
    t = -viewpoint[2] / rays_world[:, 2]
    poly = viewpoint[None, :2] + t[:, None] * rays_world[:, :2]
    return poly if polygon_area(poly) > 0 else poly[::-1]


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman intersection of two counter-clockwise convex polygons."""
    out = list(subject)
    for a, b in zip(clip, np.roll(clip, -1, axis=0), strict=True):
        inp, out = out, []
        if not inp:
            break

        def inside(p, a=a, b=b):
            return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= -1e-12

        def cross_point(p, q, a=a, b=b):
            d1, d2 = q - p, b - a
            t = ((a[0] - p[0]) * d2[1] - (a[1] - p[1]) * d2[0]) / (d1[0] * d2[1] - d1[1] * d2[0])
            return p + t * d1

        for i, q in enumerate(inp):
            p = inp[i - 1]
            if inside(q):
                if not inside(p):
                    out.append(cross_point(p, q))
                out.append(q)
            elif inside(p):
                out.append(cross_point(p, q))
    return np.array(out).reshape(-1, 2)


def overlap_fraction(vp_a, vp_b) -> float:
    fa, fb = ground_footprint(vp_a, CAMERA), ground_footprint(vp_b, CAMERA)
    inter = clip_convex(fa, fb)
    return (polygon_area(inter) if len(inter) >= 3 else 0.0) / polygon_area(fa)


@pytest.mark.parametrize("front,side", [(0.8, 0.8), (0.7, 0.6), (0.9, 0.5)])
def test_nadir_overlaps_on_flat_ground_match_config(front, side):
    params = {"mode": "nadir", "front_overlap": front, "side_overlap": side}
    flight = plan_exploration(TOMB_BOUNDS, CAMERA, params, seed=0)
    vps = flight.viewpoints
    per_line = len(vps) // flight.info["n_lines"]
    assert per_line * flight.info["n_lines"] == len(vps)
    fronts = [overlap_fraction(vps[i], vps[i + 1]) for i in range(per_line - 1)]
    # Side neighbours: image j of line 0 and the image above it on line 1 (flown backwards).
    sides = [overlap_fraction(vps[j], vps[2 * per_line - 1 - j]) for j in range(per_line)]
    assert np.allclose(fronts, front, atol=0.02)
    assert np.allclose(sides, side, atol=0.02)


def test_tomb_sized_exploration_has_about_200_images():
    flight = plan_exploration(TOMB_BOUNDS, CAMERA, {}, seed=0)
    assert 150 <= len(flight.viewpoints) <= 250
    assert flight.info["altitude_m"] == pytest.approx(27.0)


def test_centre_mode_aims_every_camera_at_the_structure_centre():
    flight = plan_exploration(TOMB_BOUNDS, CAMERA, {"mode": "centre"}, seed=0)
    target = np.array([0.0, 0.0, 6.0])
    pixels, depth = project_points(target[None], flight.viewpoints, CAMERA)
    assert np.all(depth[:, 0] > 0)
    np.testing.assert_allclose(pixels[:, 0] - [CAMERA.cx, CAMERA.cy], 0.0, atol=1e-6)


def test_boustrophedon_order_has_short_hops():
    flight = plan_exploration(TOMB_BOUNDS, CAMERA, {"mode": "nadir"}, seed=0)
    hops = np.linalg.norm(np.diff(flight.viewpoints[:, :3], axis=0), axis=1)
    # No hop is longer than the line spacing: the lines are flown back and forth.
    assert hops.max() <= flight.info["spacing_across_m"] + 1e-9


def test_plan_from_proxy_uses_structure_above_ground():
    ground = trimesh.creation.box(extents=(200.0, 200.0, 0.2))
    ground.apply_translation((0, 0, -0.1))
    building = trimesh.creation.box(extents=(40.0, 30.0, 12.0))
    building.apply_translation((0, 0, 6.0))
    proxy = trimesh.util.concatenate([ground, building])
    from_proxy = plan(proxy, CAMERA, {"mode": "nadir"}, seed=0)
    from_box = plan_exploration(TOMB_BOUNDS, CAMERA, {"mode": "nadir"}, seed=0)
    np.testing.assert_allclose(from_proxy.viewpoints, from_box.viewpoints, atol=1e-9)


def test_structure_bounds_ignore_apron_bumps_and_floaters_but_keep_split_off_parts():
    # A reconstructed proxy in miniature: an 80 m ground apron with two bumps far from the building,
    # the building, a roof tier that the surface reconstruction split off (0.2 m above the roof) and
    # a floater 6 m above the roof. The box must be the building and its tier, nothing else.
    ground = trimesh.creation.box(extents=(80.0, 80.0, 0.2)).subdivide_to_size(2.0)
    ground.apply_translation((0, 0, -0.1))
    bumps = [trimesh.creation.box(extents=(2.0, 2.0, 1.5)) for _ in range(2)]
    bumps[0].apply_translation((33.0, 30.0, 0.75))
    bumps[1].apply_translation((-30.0, 20.0, 0.75))
    building = trimesh.creation.box(extents=(10.0, 8.0, 6.0))
    building.apply_translation((2.0, -1.0, 3.0))
    tier = trimesh.creation.box(extents=(4.0, 4.0, 1.0))
    tier.apply_translation((2.0, -1.0, 6.7))
    floater = trimesh.creation.icosphere(radius=1.0)
    floater.apply_translation((0.0, 0.0, 13.0))
    proxy = trimesh.util.concatenate([ground, *bumps, building, tier, floater])

    box = structure_bounds_from_proxy(proxy, min_height_m=0.5)

    np.testing.assert_allclose(box.lo, (-3.0, -5.0, 0.0), atol=1e-6)
    np.testing.assert_allclose(box.hi, (7.0, 3.0, 7.2), atol=1e-6)
    everything = trimesh.util.concatenate([ground, *bumps, building, tier, floater]).bounds
    assert everything[1][2] == pytest.approx(14.0) and everything[1][0] == pytest.approx(40.0)


@pytest.mark.parametrize(
    "params,setting",
    [
        ({"front_overlap": 1.0}, "front_overlap"),
        ({"side_overlap": -0.1}, "side_overlap"),
        ({"altitude_m": 10.0}, "altitude_m"),
        ({"mode": "spiral"}, "mode"),
        ({"overlap": 0.5}, "overlap"),
    ],
)
def test_bad_settings_are_refused_by_name(params, setting):
    with pytest.raises(ValueError, match=setting):
        plan_exploration(TOMB_BOUNDS, CAMERA, params, seed=0)


def test_structure_inside_one_footprint_is_refused():
    tiny = Box((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))
    with pytest.raises(PlanningError, match="altitude"):
        plan_exploration(tiny, CAMERA, {}, seed=0)


def test_orbit_ring_keeps_its_distance_from_the_footprint_and_faces_it():
    from planner.lawnmower.lawnmower import orbit_ring

    lo, hi, d, spacing = np.array([-5.0, -2.0]), np.array([5.0, 2.0]), 3.0, 1.5
    xy, inward = orbit_ring(lo, hi, d, spacing)
    perimeter = 2 * (10.0 + 4.0) + 2 * np.pi * d
    assert len(xy) == int(np.ceil(perimeter / spacing))
    # Distance from each point to the rectangle: exactly d; the inward normal points at its nearest point.
    nearest = np.clip(xy, lo, hi)
    np.testing.assert_allclose(np.linalg.norm(xy - nearest, axis=1), d, atol=1e-9)
    np.testing.assert_allclose(nearest - xy, inward * d, atol=1e-9)
    # Evenly spaced along the ring (chords of at most the spacing), counter-clockwise.
    steps = np.linalg.norm(np.diff(np.vstack([xy, xy[:1]]), axis=0), axis=1)
    assert steps.max() <= perimeter / len(xy) + 1e-9 and steps.min() > 0.9 * perimeter / len(xy)
    area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    assert area > 0


def test_exploration_with_orbit_rings_adds_rings_facing_the_structure():
    plain = plan_exploration(TOMB_BOUNDS, CAMERA, {}, seed=0)
    flight = plan_exploration(TOMB_BOUNDS, CAMERA, {"orbit_rings": 2}, seed=0)
    orbit = flight.viewpoints[np.array(flight.kinds) == "orbit"]
    np.testing.assert_allclose(flight.viewpoints[: len(plain.viewpoints)], plain.viewpoints)
    assert len(orbit) == flight.info["n_orbit_views"] == len(flight.viewpoints) - len(plain.viewpoints)
    # Two rings at 1/4 and 3/4 of the 12 m structure, 15 m (altitude_above_top_m) from its footprint.
    assert sorted(set(np.round(orbit[:, 2], 6))) == [3.0, 9.0]
    lo, hi = TOMB_BOUNDS.lo_array[:2], TOMB_BOUNDS.hi_array[:2]
    gap = np.linalg.norm(orbit[:, :2] - np.clip(orbit[:, :2], lo, hi), axis=1)
    np.testing.assert_allclose(gap, 15.0, atol=1e-9)
    # Each view faces the footprint (its nearest point) at the ring pitch.
    towards = np.clip(orbit[:, :2], lo, hi) - orbit[:, :2]
    yaw = np.degrees(np.arctan2(towards[:, 1], towards[:, 0]))
    np.testing.assert_allclose(np.mod(orbit[:, 3] - yaw + 180.0, 360.0) - 180.0, 0.0, atol=1e-9)
    assert np.all(orbit[:, 4] == -15.0)
    with pytest.raises(ValueError, match="orbit_rings must be >= 0"):
        plan_exploration(TOMB_BOUNDS, CAMERA, {"orbit_rings": -1}, seed=0)
