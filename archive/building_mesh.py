"""A building mesh that has what users' models have and the procedural scenes lack.

    python -m archive.building_mesh --out cache/meshes/hall.glb
    python run.py scene=mesh scene.path=cache/meshes/hall.glb planner=lawnmower

Flat-coloured parts with no texture at all; a hall with a hollow, sealed interior (inner faces
facing into the cavity); a buttress buried half in the hall's wall; a tower; a choir whose base is
1 m above the hall's (a model built on a slope: the ground meets the lowest part); small steps
(detail). Z up, metres, a GLB with one colour per part and no maps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import trimesh

from scene.io import write_atomic


def _box(lo, hi, colour) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mesh = trimesh.creation.box(
        extents=hi - lo, transform=trimesh.transformations.translation_matrix(0.5 * (lo + hi))
    )
    mesh.visual = trimesh.visual.ColorVisuals(
        mesh, vertex_colors=np.tile([*colour, 255], (len(mesh.vertices), 1))
    )
    return mesh


def _gable(lo, hi, colour) -> trimesh.Trimesh:
    """A gable roof over the x-y rectangle lo..hi, ridge along x at height hi[2]."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    ym = 0.5 * (y0 + y1)
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, ym, z1], [x1, ym, z1]], float)
    f = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5], [0, 3, 2], [0, 2, 1]])
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.fix_normals()
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile([*colour, 255], (len(v), 1)))
    return mesh


def building() -> trimesh.Scene:
    """The parts, named, in one scene (metres, Z up; the hall's floor at z = 0)."""
    grey, red, beige, white = (150, 150, 146), (150, 70, 50), (196, 180, 150), (230, 228, 220)
    hall = _box((0, 0, 0), (30, 15, 10), grey)
    cavity = _box((0.4, 0.4, 0.4), (29.6, 14.6, 9.6), white)
    cavity.invert()  # the interior's faces look into the sealed cavity
    parts = {
        "hall": hall,
        "hall_interior": cavity,
        "roof": _gable((-0.5, -0.5, 10), (30.5, 15.5, 16), red),
        "buttress": _box((10, -1.5, 0), (11.5, 0.8, 7), grey),  # half inside the wall: buried faces
        "tower": _box((-7, 4, 0), (0, 11, 24), beige),
        "tower_cap": _gable((-7.5, 3.5, 24), (0.5, 11.5, 28), red),
        "choir": _box((30, 3, 1.0), (40, 12, 9), beige),  # base 1 m above the hall's
        "choir_roof": _gable((30, 2.5, 9), (40.5, 12.5, 13), red),
    }
    for k in range(3):  # steps before the hall's door: small parts
        parts[f"step{k}"] = _box(
            (12 + 0.3 * k, -2.4 + 0.4 * k, 0), (18 - 0.3 * k, -1.2, 0.2 * (k + 1)), white
        )
    scene = trimesh.Scene()
    for name, mesh in parts.items():
        scene.add_geometry(mesh, geom_name=name, node_name=name)
    return scene


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the GLB to write")
    args = parser.parse_args(argv)
    data = building().export(file_type="glb")
    write_atomic(args.out, lambda p: p.write_bytes(data))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
