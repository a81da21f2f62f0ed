"""Inside or outside a building, whatever the mesh's face orientation: a hall whose interior walls
face inwards, a gallery, a courtyard and an eave (inside, inside, outside, outside)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from scene.enclosure import ENCLOSED_BACK_FRACTION, GRID_DIRECTIONS, enclosed_positions, raycasting_scene


def ground() -> trimesh.Trimesh:
    return trimesh.Trimesh(
        [[-100, -100, 0], [100, -100, 0], [100, 100, 0], [-100, 100, 0]], [[0, 1, 2], [0, 2, 3]]
    )


def slab(lo, hi) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=np.array([lo, hi], float))


def inward_box(lo, hi, open_ends: bool = False) -> trimesh.Trimesh:
    """A room's inner surface: a box whose faces point into it (as a scan of the interior gives);
    ``open_ends``: without its two faces across x (a corridor open at both ends)."""
    box = slab(lo, hi)
    box.invert()
    if open_ends:
        box.update_faces(np.abs(box.face_normals[:, 0]) < 0.5)
    return box


SCENES = {
    # A 20 x 12 x 8 m hall seen from its middle: its interior walls face inwards.
    "hall": (
        trimesh.util.concatenate([ground(), inward_box((-10, -6, 0), (10, 6, 8))]),
        (0.0, 0.0, 4.0),
        True,
    ),
    # A 40 m long, 4 x 4 m gallery open at both ends, from its middle.
    "gallery": (
        trimesh.util.concatenate([ground(), inward_box((-20, -2, 0), (20, 2, 4), open_ends=True)]),
        (0.0, 0.0, 2.0),
        True,
    ),
    # A 20 x 20 m courtyard walled 10 m high, from its middle at 5 m.
    "courtyard": (
        trimesh.util.concatenate(
            [
                ground(),
                slab((-11, -11, 0), (11, -10, 10)),
                slab((-11, 10, 0), (11, 11, 10)),
                slab((-11, -10, 0), (-10, 10, 10)),
                slab((10, -10, 0), (11, 10, 10)),
            ]
        ),
        (0.0, 0.0, 5.0),
        False,
    ),
    # Under a 3 m eave of a 10 x 10 x 6 m building, 1.5 m from its wall, 4 m up.
    "eave": (
        trimesh.util.concatenate([ground(), slab((-5, -5, 0), (5, 5, 6)), slab((-8, -8, 6), (8, 8, 6.5))]),
        (6.5, 0.0, 4.0),
        False,
    ),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_inside_or_outside_whatever_the_face_orientation(name):
    mesh, position, inside = SCENES[name]
    assert enclosed_positions(raycasting_scene(mesh), np.array([position])).tolist() == [inside]


def test_the_inward_facing_hall_passes_the_back_face_test_alone():
    """Why the second test: from inside the hall every ray hits a face from its front."""
    mesh, position, _ = SCENES["hall"]
    rays = np.concatenate([np.repeat([position], len(GRID_DIRECTIONS), 0), GRID_DIRECTIONS], 1)
    hits = raycasting_scene(mesh).cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    back = np.einsum("ij,ij->i", hits["primitive_normals"].numpy(), GRID_DIRECTIONS) > 0
    assert np.isfinite(hits["t_hit"].numpy()).all() and back.mean() < ENCLOSED_BACK_FRACTION


def test_a_camera_above_the_buildings_is_outside():
    for mesh, _, _ in SCENES.values():
        assert not enclosed_positions(raycasting_scene(mesh), np.array([[0.0, 0.0, 30.0]]))[0]
