"""``church``: a cross-plan Orthodox church modelled on St Sophia (five domes, three apses).

Layout (metres, origin at the crossing, +x east, ground z = 0): a 20 x 20 m core 16 m high with
four 10 m wide arms (west 6 m long with the portal, north and south 6 m, east 5 m) under gable
roofs; three apses on the east (a main one of 4.5 m radius and two of 2.5 m) with half-domes; a
central 12-sided drum (apothem 4.5 m) with arched windows and a gilded onion dome (cross at ~35 m);
four smaller 8-sided drums with green domes over the corners of the core.

Hard parts for nadir flights: the window recesses on every facade and drum, the eaves of the arm
roofs and of the domes, the re-entrant corners of the cross, the apses' curved walls.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from scene.base import Scene
from scene.procedural.common import box_walls, finish_scene, materials_for, polygon_drum, polygon_prism
from scene.procedural.geometry import (
    Builder,
    box,
    dome_profile,
    gable_roof,
    hip_roof,
    loft,
    onion_profile,
    revolve,
)

MATERIALS = [
    ("plaster", "plaster_white", 0.015, True),
    ("roof", "metal_green", 0.015, True),
    ("ground", "ground_grass", 0.025, True),
    ("gold", "metal_gold", 0.012, False),
    ("brick", "brick", 0.012, False),
    ("wood", "wood_dark", 0.01, False),
]

_WINDOW = dict(width=1.4, sill=5.5, spring=8.5, depth=0.5, arch=True)
_HIGH_WINDOW = dict(width=1.2, sill=10.5, spring=12.6, depth=0.45, arch=True)


def build_church(cfg: Mapping, cache_dir=None) -> Scene:
    """Build the church scene from its config (``seed``, texture sizes, ``max_edge_m``, ...)."""
    started = time.perf_counter()
    seed = int(cfg.get("seed", 0))
    b = Builder(materials_for(MATERIALS, cfg), seed, float(cfg.get("max_edge_m", 1.0)))
    core_h = float(cfg.get("core_height_m", 16.0))

    # Plinth (brick) under the whole cross, 0.6 m high, 0.3 m proud of the walls.
    for x0, y0, x1, y1 in ((-10, -10, 10, 10), (-16, -5, 16, 5), (-5, -16, 5, 16)):
        b.add(box((x0 - 0.3, y0 - 0.3, 0.0), (x1 + 0.3, y1 + 0.3, 0.6), "brick"))

    # Core: windows in the parts of its walls that the arms do not cover.
    core_windows = [dict(_WINDOW, x=1.8), dict(_WINDOW, x=16.8), dict(_HIGH_WINDOW, x=9.4)]
    b.add(
        box_walls(
            -10,
            -10,
            10,
            10,
            0.6,
            core_h - 0.6,
            1.0,
            "plaster",
            {s: core_windows for s in ("north", "south", "east", "west")},
            back_material="wood",
        )
    )
    b.add(hip_roof(-10.6, -10.6, 10.6, 10.6, core_h, 2.0, "roof", top_rect=_square(6.0)))

    # Arms: (x0, y0, x1, y1, roof axis angle, portal side).
    arm_h = core_h - 2.0
    arms = [
        (-16.0, -5.0, -10.0, 5.0, 0.0, "west"),
        (10.0, -5.0, 15.0, 5.0, 0.0, "east"),
        (-5.0, 10.0, 5.0, 16.0, np.pi / 2, "north"),
        (-5.0, -16.0, 5.0, -10.0, np.pi / 2, "south"),
    ]
    for x0, y0, x1, y1, angle, end in arms:
        portal = dict(width=3.0, sill=0.0, spring=4.5, depth=0.9, arch=True, x=3.5)
        flank = [dict(_HIGH_WINDOW, x=x, sill=7.0, spring=9.5) for x in (1.3, 7.5)]
        end_openings = [portal, *flank] if end != "east" else []
        side_window = [
            dict(_WINDOW, x=2.0, width=1.2) if (x1 - x0 if angle == 0 else y1 - y0) > 5.5 else None
        ]
        openings = {end: end_openings}
        for side in ("north", "south") if angle == 0 else ("east", "west"):
            openings[side] = [o for o in side_window if o is not None]
        b.add(box_walls(x0, y0, x1, y1, 0.6, arm_h - 0.6, 1.2, "plaster", openings, back_material="wood"))
        length, width = (x1 - x0, y1 - y0) if angle == 0 else (y1 - y0, x1 - x0)
        center = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0)
        # Arm roofs run into the core: extend them 2 m inwards; eaves overhang 0.5 m.
        inward = -np.sign(center[0] if angle == 0 else center[1])
        roof = gable_roof(length + 2.5, width + 1.0, arm_h, 3.6, "roof")
        shift = np.array([inward * 1.0, 0.0, 0.0]) if angle == 0 else np.array([0.0, inward * 1.0, 0.0])
        b.add(
            roof.placed(
                angle,
                np.asarray(center)
                + shift
                + (0.25 * -inward * (angle == 0), 0.25 * -inward * (angle != 0), 0),
            )
        )

    # Apses on the east: half-cylinders with half-domes, blind arcading as shallow pilasters.
    for cy, radius, height in ((0.0, 4.5, 11.0), (-7.5, 2.5, 9.0), (7.5, 2.5, 9.0)):
        x_base = 15.0 if cy == 0.0 else 10.0
        wall = _half_disc(radius, 16)
        b.add(loft([(wall, 0.6), (wall, height)], "plaster", mapping="cyl").placed(0.0, (x_base, cy, 0.0)))
        b.add(
            loft(
                [(_half_disc(radius + 0.3, 16), 0.0), (_half_disc(radius + 0.3, 16), 0.6)],
                "brick",
                mapping="cyl",
            ).placed(0.0, (x_base, cy, 0.0))
        )
        rings = [
            (_half_disc(radius * np.cos(a) + 0.25, 16), height + radius * np.sin(a))
            for a in np.linspace(0, np.pi / 2 * 0.98, 7)
        ]
        b.add(loft(rings, "roof", mapping="box").placed(0.0, (x_base, cy, 0.0)))
        for a in np.linspace(-np.pi / 2 * 0.75, np.pi / 2 * 0.75, 5):
            px, py = (radius + 0.1) * np.cos(a), (radius + 0.1) * np.sin(a)
            b.add(
                box((-0.15, -0.3, 0.6), (0.15, 0.3, height - 0.4), "plaster").placed(
                    a, (x_base + px, cy + py, 0.0)
                )
            )

    # Central drum, onion dome, cross.
    z_drum = core_h + 1.6
    drum_window = dict(width=1.1, sill=1.4, spring=4.0, depth=0.6, arch=True, x=-0.55)
    b.add(polygon_drum(4.5, 12, z_drum, 6.5, 1.0, "plaster", drum_window, "wood"))
    b.add(polygon_prism(4.9, 12, z_drum + 6.5, z_drum + 7.0, "brick"))  # cornice ring: a small overhang
    b.add(revolve(onion_profile(4.6, z_drum + 7.0, 8.5), "gold", n=32, convex=False))
    _cross(b, (0.0, 0.0), z_drum + 7.0 + 8.5 - 0.3, 3.2, "gold")

    # Corner drums and domes.
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = (sx * 6.5, sy * 6.5)
            small_window = dict(width=0.8, sill=1.0, spring=2.6, depth=0.4, arch=True, x=-0.4)
            b.add(polygon_drum(2.2, 8, core_h - 0.3, 4.6, 0.6, "plaster", small_window, "wood", center=c))
            top = core_h - 0.3 + 4.6
            b.add(polygon_prism(2.45, 8, top, top + 0.35, "brick", center=c))
            b.add(
                revolve(dome_profile(2.4, top + 0.35, 2.8, steps=8), "roof", n=24).placed(
                    0.0, (c[0], c[1], 0.0)
                )
            )
            _cross(b, c, top + 0.35 + 2.8 - 0.1, 1.6, "gold")

    info = {"model": "Cross-plan Orthodox church after St Sophia, simplified", "core_m": 20.0}
    return finish_scene("church", cfg, b, "ground", cache_dir, info, started)


def _square(half: float) -> np.ndarray:
    return np.array([[-half, -half], [half, -half], [half, half], [-half, half]], float)


def _half_disc(radius: float, n: int) -> np.ndarray:
    """Counter-clockwise half disc facing +x (the flat side on x = 0)."""
    a = np.linspace(-np.pi / 2, np.pi / 2, n + 1)
    return radius * np.column_stack([np.cos(a), np.sin(a)])


def _cross(b: Builder, xy, z0: float, height: float, material: str) -> None:
    """An Orthodox cross: a post, a long bar and a short bar (thin boxes, metres)."""
    x, y = xy
    t = 0.08 * height / 3.0 + 0.05
    b.add(box((x - t, y - t, z0), (x + t, y + t, z0 + height), material))
    b.add(
        box(
            (x - t, y - 0.3 * height, z0 + 0.62 * height),
            (x + t, y + 0.3 * height, z0 + 0.62 * height + 2 * t),
            material,
        )
    )
    b.add(
        box(
            (x - t, y - 0.18 * height, z0 + 0.82 * height),
            (x + t, y + 0.18 * height, z0 + 0.82 * height + 2 * t),
            material,
        )
    )
