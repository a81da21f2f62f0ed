"""Building blocks shared by the procedural scenes: walled boxes, polygonal drums, scene assembly."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from scene.base import Box, Scene
from scene.procedural.geometry import Builder, Material, Piece, arched_wall, box, ground_tiles, loft, place
from scene.textures import cached_texture, material_seed


def box_walls(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    z0: float,
    height: float,
    thickness: float,
    material: str,
    openings: Mapping[str, Sequence[dict]] | None = None,
    back_material: str | None = None,
    core: bool = True,
) -> list[Piece]:
    """Four walls around the rectangle [x0, x1] x [y0, y1] (metres), base z0, with recesses per side.

    ``openings`` maps a side (``south`` -y, ``north`` +y, ``east`` +x, ``west`` -x) to
    :func:`~scene.procedural.geometry.arched_wall` openings, x measured along the side from its
    left end seen from outside. ``core`` fills the inside with a solid so that the walls' inner faces
    are hidden (buildings have no modelled interior).
    """
    openings = openings or {}
    lx, ly = x1 - x0, y1 - y0
    sides = {
        "south": (lx, 0.0, (x0, y0, z0)),
        "north": (lx, np.pi, (x1, y1, z0)),
        "east": (ly, np.pi / 2, (x1, y0, z0)),
        "west": (ly, -np.pi / 2, (x0, y1, z0)),
    }
    pieces: list[Piece] = []
    for side, (length, angle, origin) in sides.items():
        wall = arched_wall(length, height, thickness, openings.get(side, ()), material, back_material)
        pieces += place(wall, angle, origin)
    if core and min(lx, ly) > 2 * thickness + 1e-6:
        pieces.append(
            box((x0 + thickness, y0 + thickness, z0), (x1 - thickness, y1 - thickness, z0 + height), material)
        )
    return pieces


def polygon_drum(
    radius: float,
    n_sides: int,
    z0: float,
    height: float,
    thickness: float,
    material: str,
    window: dict | None = None,
    back_material: str | None = None,
    center=(0.0, 0.0),
) -> list[Piece]:
    """A regular polygonal drum (``radius`` = apothem, metres) with one recess per side, plus a core.

    ``window`` is one :func:`arched_wall` opening with ``x`` measured from the side's centre
    (``x`` = -width/2 centres it); None gives plain sides.
    """
    side = 2.0 * radius * np.tan(np.pi / n_sides)
    pieces: list[Piece] = []
    for k in range(n_sides):
        outward = 2 * np.pi * k / n_sides
        # Local wall frame: x along the side, -y outward. Rotation maps local -y to the outward normal.
        angle = outward + np.pi / 2
        openings = []
        if window is not None:
            o = dict(window)
            o["x"] = 0.5 * side + float(window["x"])
            openings = [o]
        wall = arched_wall(side, height, thickness, openings, material, back_material)
        c, s = np.cos(angle), np.sin(angle)
        # Local origin is the left end of the outer face: centre - side/2 along the side direction.
        start = np.array([radius * np.cos(outward), radius * np.sin(outward)]) - 0.5 * side * np.array([c, s])
        pieces += place(wall, angle, (start[0] + center[0], start[1] + center[1], z0))
    inner = radius - thickness
    ring = _regular(inner / np.cos(np.pi / n_sides), n_sides)
    pieces.append(loft([(ring + center, z0), (ring + center, z0 + height)], material, mapping="cyl"))
    return pieces


def _regular(circumradius: float, n: int) -> np.ndarray:
    """Counter-clockwise polygon whose sides face the angles 2 pi k / n."""
    a = (2 * np.arange(n) + 1) * np.pi / n
    return circumradius * np.column_stack([np.cos(a), np.sin(a)])


def polygon_prism(
    radius: float, n_sides: int, z0: float, z1: float, material: str, center=(0.0, 0.0)
) -> Piece:
    """Solid regular prism with apothem ``radius`` whose sides face the angles 2 pi k / n (metres)."""
    ring = _regular(radius / np.cos(np.pi / n_sides), n_sides) + np.asarray(center, float)
    return loft([(ring, z0), (ring, z1)], material, mapping="cyl")


def materials_for(spec: Sequence[tuple[str, str, float, bool]], cfg: Mapping) -> list[Material]:
    """Materials from (key, preset, texel_m, large) rows: large maps get ``cfg.texture_size`` texels,
    the others ``cfg.small_texture_size``."""
    large, small = int(cfg.get("texture_size", 4096)), int(cfg.get("small_texture_size", 2048))
    for name, value in (("texture_size", large), ("small_texture_size", small)):
        if value < 256 or value > 8192 or value & (value - 1):
            raise ValueError(f"scene.{name} must be a power of two in [256, 8192], got {value}")
    return [Material(key, preset, float(texel), large if big else small) for key, preset, texel, big in spec]


def finish_scene(
    name: str,
    cfg: Mapping,
    builder: Builder,
    ground_material: str,
    cache_dir,
    info: dict,
    started: float,
) -> Scene:
    """Ground tiles around the structure, hidden-face culling, textures and bounds -> Scene.

    The ground extends ``cfg.ground_margin_m`` (default 30 m) beyond the structure's footprint on
    every side. ``evaluation_region`` = structure bounds grown ``cfg.eval_apron_m`` (default 3 m)
    sideways, from z = -0.5 m to the top + 1 m: the structure plus a strip of ground around it.
    """
    seed = int(cfg.get("seed", 0))
    margin = float(cfg.get("ground_margin_m", 30.0))
    apron = float(cfg.get("eval_apron_m", 3.0))
    if margin < apron or apron < 0:
        raise ValueError(f"scene.ground_margin_m ({margin}) must be >= scene.eval_apron_m ({apron}) >= 0")
    points = np.concatenate([p.world_vertices() for p in builder.pieces])
    structure = Box.from_points(points)
    ground_mat = builder.materials[ground_material]
    period = ground_mat.texel_m * ground_mat.size
    tiles = ground_tiles(
        structure.lo_array[:2] - margin,
        structure.hi_array[:2] + margin,
        ground_material,
        tile_m=period,
        cell_m=float(cfg.get("ground_cell_m", 1.0)),
    )
    for tile in tiles:  # one texture per tile (own seed), so no patch of ground repeats
        builder.materials.setdefault(tile.material, replace(ground_mat, key=tile.material))
    ground_keys = {tile.material for tile in tiles}
    parts = builder.build(ground=tiles)
    structure = Box.from_points(np.concatenate([p.vertices for p in parts if p.name not in ground_keys]))
    evaluation = Box(
        (structure.lo[0] - apron, structure.lo[1] - apron, -0.5),
        (structure.hi[0] + apron, structure.hi[1] + apron, structure.hi[2] + 1.0),
    )
    textures = {
        m.key: cached_texture(name, m.key, m.preset, m.size, material_seed(seed, m.key), cache_dir)
        for m in builder.materials.values()
        if any(p.texture == m.key for p in parts)
    }
    n_faces = sum(len(p.faces) for p in parts)
    info = dict(info)
    info.update(
        n_faces=n_faces,
        n_vertices=sum(len(p.vertices) for p in parts),
        texture_bytes=int(sum(t.nbytes for t in textures.values())),
        textures={
            m.key: {"preset": m.preset, "texel_m": m.texel_m, "size": m.size}
            for m in builder.materials.values()
        },
        footprint_m=[float(v) for v in structure.extent[:2]],
        ground_parts=sorted(ground_keys),
        height_m=float(structure.hi[2]),
        build_seconds=round(time.perf_counter() - started, 3),
    )
    return Scene(name, parts, textures, structure, evaluation, seed=seed, info=info)
