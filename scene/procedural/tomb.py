"""``tomb``: a walled courtyard modelled on Tu Duc's tomb (Hue, Vietnam).

Layout (metres, origin at the courtyard centre, +y north, ground z = 0):

- courtyard wall 40 x 30 m (2.6 m high, 0.6 m thick, coping with a small overhang, blind panels
  recessed in its outer face), a three-bay gate in the south wall with its own tiled roof;
- the main pavilion on a 1 m stone platform with steps: a walled hall with recessed doors and
  windows, a colonnade of red lacquered columns, a two-tier hipped tile roof with deep eaves
  (1.5 m and 1.2 m overhangs), a ridge beam and finials;
- a stele pavilion (open on four columns, the stele inside under the roof), two free-standing steles,
  two rows of mandarin statues and a paved path from the gate.

Hard parts for nadir flights: the eaves' undersides, the colonnade behind them, the recessed doors,
the stele inside its pavilion, the inner faces of the courtyard wall.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from scene.base import Scene
from scene.procedural.common import box_walls, finish_scene, materials_for
from scene.procedural.geometry import (
    Builder,
    arched_wall,
    box,
    cylinder,
    dome_profile,
    hip_roof,
    place,
    revolve,
)

# (key, texture preset, texel size m, large map?)
MATERIALS = [
    ("stone", "stone_grey", 0.015, True),
    ("roof", "roof_tiles", 0.015, True),
    ("ground", "ground_grass", 0.025, True),
    ("plaster", "plaster_ochre", 0.015, False),
    ("wood", "wood_red", 0.01, False),
    ("paving", "paving", 0.02, False),
]


def build_tomb(cfg: Mapping, cache_dir=None) -> Scene:
    """Build the tomb scene from its config (``seed``, texture sizes, ``max_edge_m``, ...)."""
    started = time.perf_counter()
    seed = int(cfg.get("seed", 0))
    rng = np.random.default_rng([seed, 1])
    half_x, half_y = 0.5 * float(cfg.get("courtyard_x_m", 40.0)), 0.5 * float(cfg.get("courtyard_y_m", 30.0))
    b = Builder(materials_for(MATERIALS, cfg), seed, float(cfg.get("max_edge_m", 1.0)))

    _courtyard_wall(b, half_x, half_y, rng)
    _gate(b, -half_y)
    _pavilion(b, center=(0.0, 0.45 * half_y))
    _stele_pavilion(b, center=(-0.6 * half_x, -0.25 * half_y))
    for sx in (-1, 1):
        _stele(b, (sx * 0.78 * half_x, -0.72 * half_y), height=2.5)
        for k in range(4):
            _statue(b, (sx * 4.5, -0.72 * half_y + 2.2 * k + 1.0), rng)
    # Paved path from the gate to the steps, and a paved apron in front of the pavilion.
    b.add(box((-2.0, -half_y + 0.6, 0.0), (2.0, 0.45 * half_y - 6.5, 0.06), "paving"))
    b.add(box((-8.5, 0.45 * half_y - 6.5, 0.0), (8.5, 0.45 * half_y - 4.6, 0.06), "paving"))
    info = {
        "model": "Tu Duc's tomb (Hue), simplified",
        "courtyard_m": [2 * half_x, 2 * half_y],
    }
    return finish_scene("tomb", cfg, b, "ground", cache_dir, info, started)


def _courtyard_wall(b: Builder, hx: float, hy: float, rng: np.random.Generator) -> None:
    height, thick, gate_half = 2.6, 0.6, 3.0

    def panels(length: float) -> list[dict]:
        # Blind panels recessed 12 cm in the outer face every ~4 m.
        n = int(length // 4.0)
        pitch = length / max(n, 1)
        return [
            dict(x=k * pitch + 0.8, width=pitch - 1.6, sill=0.5, spring=2.0, depth=0.12, arch=False)
            for k in range(n)
            if pitch - 1.6 > 0.5
        ]

    runs = [  # (length, angle, origin): outer face of each straight run
        (2 * hx, np.pi, (hx, hy, 0.0)),  # north
        (2 * hy, np.pi / 2, (hx, -hy, 0.0)),  # east
        (2 * hy, -np.pi / 2, (-hx, hy, 0.0)),  # west
        (hx - gate_half, 0.0, (-hx, -hy, 0.0)),  # south-west of the gate
        (hx - gate_half, 0.0, (gate_half, -hy, 0.0)),  # south-east of the gate
    ]
    for length, angle, origin in runs:
        b.add(place(arched_wall(length, height, thick, panels(length), "stone"), angle, origin))
        # Coping: a cap 8 cm wider than the wall on both sides (a small overhang).
        cap = box((-0.08, -0.08, height), (length + 0.08, thick + 0.08, height + 0.18), "stone")
        b.add(cap.placed(angle, origin))


def _gate(b: Builder, y_wall: float) -> None:
    """Three-bay gate (tam quan) spanning x in [-3, 3] in the south wall, with a tiled hip roof."""
    for x_lo, width, height in ((-3.0, 0.8, 4.6), (2.2, 0.8, 4.6), (-1.2, 0.5, 4.0), (0.7, 0.5, 4.0)):
        b.add(box((x_lo, y_wall - 0.1, 0.0), (x_lo + width, y_wall + 0.7, height), "stone"))
        b.add(
            box((x_lo - 0.1, y_wall - 0.2, height), (x_lo + width + 0.1, y_wall + 0.8, height + 0.2), "stone")
        )
    b.add(box((-3.0, y_wall - 0.05, 3.4), (3.0, y_wall + 0.65, 4.0), "wood"))
    b.add(hip_roof(-3.9, y_wall - 0.9, 3.9, y_wall + 1.5, 4.0, 1.3, "roof", fascia=0.2, ridge_fraction=0.5))
    b.add(box((-1.6, y_wall + 0.15, 5.45), (1.6, y_wall + 0.45, 5.75), "roof"))


def _pavilion(b: Builder, center) -> None:
    cx, cy = center
    plat_x, plat_y, plat_h = 8.0, 5.0, 1.0
    b.add(box((cx - plat_x, cy - plat_y, 0.0), (cx + plat_x, cy + plat_y, plat_h), "stone"))
    # Steps on the south side: five 0.2 m risers, 0.35 m treads, with cheek walls.
    n_steps = 5
    for k in range(n_steps):
        depth = 0.35 * (n_steps - k)
        b.add(box((cx - 3.0, cy - plat_y - depth, 0.0), (cx + 3.0, cy - plat_y, 0.2 * (k + 1)), "stone"))
    for sx in (-1, 1):
        x0 = cx + sx * 3.0 if sx > 0 else cx - 3.45
        b.add(box((x0, cy - plat_y - 0.35 * n_steps, 0.0), (x0 + 0.45, cy - plat_y, plat_h + 0.2), "stone"))

    # Hall: walls with three recessed doors in front, windows elsewhere.
    hx, hy, z0, wall_h = 5.5, 2.5, plat_h, 4.2
    door = dict(width=1.6, sill=0.0, spring=2.8, depth=0.35, arch=False)
    window = dict(width=1.2, sill=1.0, spring=2.4, depth=0.3, arch=True)
    openings = {
        "south": [dict(door, x=x) for x in (1.2, 4.7, 8.2)],
        "north": [dict(window, x=x) for x in (2.0, 4.9, 7.8)],
        "east": [dict(window, x=1.9)],
        "west": [dict(window, x=1.9)],
    }
    b.add(
        box_walls(
            cx - hx, cy - hy, cx + hx, cy + hy, z0, wall_h, 0.6, "plaster", openings, back_material="wood"
        )
    )

    # Colonnade 1.4 m outside the hall, carrying a beam under the lower eave.
    col_x, col_y, col_top = hx + 1.4, hy + 1.4, z0 + 4.0
    xs = np.linspace(-col_x, col_x, 7)
    ys = np.linspace(-col_y, col_y, 4)
    positions = [(x, y) for x in xs for y in (-col_y, col_y)] + [
        (x, y) for x in (-col_x, col_x) for y in ys[1:-1]
    ]
    for x, y in positions:
        b.add(box((cx + x - 0.3, cy + y - 0.3, z0), (cx + x + 0.3, cy + y + 0.3, z0 + 0.25), "stone"))
        b.add(cylinder(0.2, z0 + 0.25, col_top, "wood", n=16).placed(0.0, (cx + x, cy + y, 0.0)))
    for y in (-col_y, col_y):
        b.add(
            box(
                (cx - col_x - 0.15, cy + y - 0.15, col_top - 0.35),
                (cx + col_x + 0.15, cy + y + 0.15, col_top),
                "wood",
            )
        )
    for x in (-col_x, col_x):
        b.add(
            box(
                (cx + x - 0.15, cy - col_y - 0.15, col_top - 0.35),
                (cx + x + 0.15, cy + col_y + 0.15, col_top),
                "wood",
            )
        )
    # Tie beams from the colonnade to the hall (visible only from below the eaves).
    for x in xs[1:-1]:
        for sy in (-1, 1):
            y_in, y_out = sorted((cy + sy * hy, cy + sy * col_y))
            b.add(box((cx + x - 0.12, y_in, col_top - 0.3), (cx + x + 0.12, y_out, col_top - 0.05), "wood"))

    # Lower roof: deep eaves (1.5 m beyond the columns), slopes up to the upper storey.
    eave_x, eave_y, z_eave = col_x + 1.5, col_y + 1.5, col_top
    up_x, up_y = hx - 1.0, hy - 0.5
    top = np.array(
        [[cx - up_x, cy - up_y], [cx + up_x, cy - up_y], [cx + up_x, cy + up_y], [cx - up_x, cy + up_y]]
    )
    b.add(hip_roof(cx - eave_x, cy - eave_y, cx + eave_x, cy + eave_y, z_eave, 1.6, "roof", top_rect=top))
    # Upper storey (clerestory) with small recessed windows, then the upper roof.
    z_up, up_h = z_eave, 3.3
    clerestory = {
        side: [dict(width=0.8, sill=2.2, spring=2.8, depth=0.15, arch=False, x=x) for x in xs_]
        for side, xs_ in (
            ("south", (1.5, 3.6, 5.7)),
            ("north", (1.5, 3.6, 5.7)),
            ("east", (1.6,)),
            ("west", (1.6,)),
        )
    }
    b.add(
        box_walls(cx - up_x, cy - up_y, cx + up_x, cy + up_y, z_up, up_h, 0.4, "plaster", clerestory, "wood")
    )
    z_eave2 = z_up + up_h
    b.add(
        hip_roof(
            cx - up_x - 1.2,
            cy - up_y - 1.2,
            cx + up_x + 1.2,
            cy + up_y + 1.2,
            z_eave2,
            2.3,
            "roof",
            ridge_fraction=0.45,
        )
    )
    ridge_z = z_eave2 + 0.25 + 2.3
    ridge_half = 0.45 * (up_x + 1.2)
    b.add(
        box(
            (cx - ridge_half - 0.3, cy - 0.18, ridge_z - 0.15),
            (cx + ridge_half + 0.3, cy + 0.18, ridge_z + 0.35),
            "roof",
        )
    )
    for sx in (-1, 1):  # upturned ridge-end ornaments
        b.add(
            cylinder(0.22, ridge_z + 0.35, ridge_z + 1.1, "roof", n=12, radius_top=0.05).placed(
                0.0, (cx + sx * (ridge_half + 0.1), cy, 0.0)
            )
        )
    gourd = [(0.35, 0.0), (0.45, 0.25), (0.3, 0.5), (0.18, 0.62), (0.3, 0.8), (0.25, 1.0), (0.0, 1.3)]
    b.add(
        revolve([(r, ridge_z + 0.35 + z) for r, z in gourd], "stone", n=16, convex=False).placed(
            0.0, (cx, cy, 0.0)
        )
    )


def _stele_pavilion(b: Builder, center) -> None:
    """Open pavilion on four square pillars sheltering a stele (seen only obliquely, under the roof)."""
    cx, cy = center
    b.add(box((cx - 3.2, cy - 3.2, 0.0), (cx + 3.2, cy + 3.2, 0.6), "stone"))
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = cx + sx * 2.5, cy + sy * 2.5
            b.add(box((x - 0.3, y - 0.3, 0.6), (x + 0.3, y + 0.3, 4.0), "stone"))
    for sy in (-1, 1):
        b.add(box((cx - 2.8, cy + sy * 2.5 - 0.2, 3.6), (cx + 2.8, cy + sy * 2.5 + 0.2, 4.0), "wood"))
    for sx in (-1, 1):
        b.add(box((cx + sx * 2.5 - 0.2, cy - 2.8, 3.6), (cx + sx * 2.5 + 0.2, cy + 2.8, 4.0), "wood"))
    b.add(hip_roof(cx - 3.9, cy - 3.9, cx + 3.9, cy + 3.9, 4.0, 2.2, "roof", ridge_fraction=0.0))
    b.add(
        revolve(dome_profile(0.3, 4.0 + 0.25 + 2.2 - 0.1, 0.5, steps=4), "stone", n=12).placed(
            0.0, (cx, cy, 0.0)
        )
    )
    _stele(b, (cx, cy), height=3.0, base_z=0.6)


def _stele(b: Builder, xy, height: float, base_z: float = 0.0) -> None:
    x, y = xy
    b.add(box((x - 1.1, y - 0.6, base_z), (x + 1.1, y + 0.6, base_z + 0.6), "stone"))
    b.add(box((x - 0.8, y - 0.18, base_z + 0.6), (x + 0.8, y + 0.18, base_z + 0.6 + height), "stone"))
    cap_z = base_z + 0.6 + height
    b.add(box((x - 0.95, y - 0.28, cap_z), (x + 0.95, y + 0.28, cap_z + 0.3), "stone"))


def _statue(b: Builder, xy, rng: np.random.Generator) -> None:
    """Stone mandarin: plinth, robed body, head (sizes jittered per statue)."""
    x, y = xy
    s = rng.uniform(0.92, 1.08)
    b.add(box((x - 0.35, y - 0.35, 0.0), (x + 0.35, y + 0.35, 0.4), "stone"))
    b.add(cylinder(0.28 * s, 0.4, 0.4 + 1.2 * s, "stone", n=12, radius_top=0.2 * s).placed(0.0, (x, y, 0.0)))
    head_z = 0.4 + 1.2 * s
    b.add(revolve(dome_profile(0.15 * s, head_z, 0.3 * s, steps=4), "stone", n=10).placed(0.0, (x, y, 0.0)))
