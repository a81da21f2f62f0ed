"""``cathedral``: modelled on the Metropolitan Cathedral of Mexico City.

Layout (metres, origin at the centre of the footprint, +y north, main facade to the south, ground
z = 0): a 110 x 55 m footprint. A nave 16 m wide and 28 m high under a shallow gable roof, aisles
(10 m, 21 m high) with a small cupola over every 8 m bay, side chapels (8 m, 14 m high) with
buttresses between the bays, a crossing dome on an octagonal drum (lantern top ~55 m), a lower
apse (Altar of the Kings) at the north end, and on the south a facade block with three recessed
portals, pilasters and cornices between two bell towers about 60 m high (square bodies to 34 m,
bell stages with deep arched openings, bell-shaped caps, lanterns, crosses).

Hard parts for nadir flights: the portals and bell openings (deep recesses), the cornices
(overhangs), the tall vertical facades, the narrow gaps between buttresses.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from scene.base import Scene
from scene.procedural.common import box_walls, finish_scene, materials_for, polygon_drum, polygon_prism
from scene.procedural.geometry import Builder, box, cylinder, dome_profile, gable_roof, loft, rect, revolve

MATERIALS = [
    ("stone", "stone_beige", 0.015, True),
    ("tezontle", "tezontle", 0.015, True),
    ("roof", "roof_concrete", 0.02, True),
    ("ground", "ground_dry", 0.03, True),
    ("tiles", "dome_tiles", 0.015, False),
    ("wood", "wood_dark", 0.01, False),
]

_Y_FRONT, _Y_BACK = -45.0, 50.0  # nave front (behind the facade block) and back wall


def build_cathedral(cfg: Mapping, cache_dir=None) -> Scene:
    """Build the cathedral scene from its config (``seed``, texture sizes, ``tower_height_m``, ...)."""
    started = time.perf_counter()
    seed = int(cfg.get("seed", 0))
    b = Builder(materials_for(MATERIALS, cfg), seed, float(cfg.get("max_edge_m", 1.0)))
    tower_top = float(cfg.get("tower_height_m", 60.0))
    if not 45.0 <= tower_top <= 90.0:
        raise ValueError(f"scene.tower_height_m must lie in [45, 90], got {tower_top}")

    _body(b)
    _dome(b, y=24.0)
    _facade(b)
    for sx in (-1, 1):
        _tower(b, sx, tower_top)
    info = {"model": "Metropolitan Cathedral of Mexico City, simplified", "tower_height_m": tower_top}
    return finish_scene("cathedral", cfg, b, "ground", cache_dir, info, started)


def _bay_windows(length: float, pitch: float, window: dict) -> list[dict]:
    n = int(length // pitch)
    start = 0.5 * (length - n * pitch)
    return [dict(window, x=start + k * pitch + 0.5 * (pitch - window["width"])) for k in range(n)]


def _body(b: Builder) -> None:
    length = _Y_BACK - _Y_FRONT
    # Nave.
    clerestory = dict(width=2.4, sill=22.5, spring=25.0, depth=0.7, arch=True)
    nave_open = {s: _bay_windows(length, 8.0, clerestory) for s in ("east", "west")}
    b.add(box_walls(-8.0, _Y_FRONT, 8.0, _Y_BACK, 0.0, 28.0, 1.5, "tezontle", nave_open, "wood"))
    roof = gable_roof(length + 1.0, 17.0, 28.0, 3.0, "roof", fascia=0.4)
    b.add(roof.placed(np.pi / 2, (0.0, 0.5 * (_Y_FRONT + _Y_BACK), 0.0)))
    for sx in (-1, 1):
        # Aisles: 10 m wide, 21 m high, windows above the chapel roofs, a cupola on every bay.
        x0, x1 = (8.0, 18.0) if sx > 0 else (-18.0, -8.0)
        aisle_window = dict(width=2.0, sill=15.5, spring=18.2, depth=0.6, arch=True)
        side = "east" if sx > 0 else "west"
        b.add(
            box_walls(
                x0,
                _Y_FRONT,
                x1,
                _Y_BACK,
                0.0,
                21.0,
                1.2,
                "tezontle",
                {side: _bay_windows(length, 8.0, aisle_window)},
                "wood",
            )
        )
        b.add(
            box(
                (x0 - 0.3 * (sx < 0), _Y_FRONT - 0.3, 21.0),
                (x1 + 0.3 * (sx > 0), _Y_BACK + 0.3, 21.8),
                "stone",
            )
        )
        xc = 0.5 * (x0 + x1)
        for k in range(int(length // 8.0)):
            y = _Y_FRONT + 4.0 + 8.0 * k
            if 16.0 < y < 32.0:
                continue  # the crossing
            b.add(polygon_prism(2.0, 8, 21.8, 23.2, "stone", center=(xc, y)))
            b.add(revolve(dome_profile(2.2, 23.2, 1.8, steps=5), "tiles", n=16).placed(0.0, (xc, y, 0.0)))
            b.add(cylinder(0.5, 25.0 - 0.1, 26.2, "stone", n=8).placed(0.0, (xc, y, 0.0)))
        # Side chapels: 8 m deep, 14 m high, a round window and a portal-like recess per bay.
        c0, c1 = (18.0, 26.0) if sx > 0 else (-26.0, -18.0)
        chapel_window = dict(width=2.2, sill=6.0, spring=9.5, depth=0.8, arch=True)
        b.add(
            box_walls(
                c0,
                _Y_FRONT + 5.0,
                c1,
                _Y_BACK - 3.0,
                0.0,
                14.0,
                1.0,
                "tezontle",
                {side: _bay_windows(length - 8.0, 8.0, chapel_window)},
                "wood",
            )
        )
        b.add(
            box((min(c0, c1) - 0.3, _Y_FRONT + 4.7, 14.0), (max(c0, c1) + 0.3, _Y_BACK - 2.7, 14.7), "stone")
        )
        # Parapet along the chapel roof edge (leaves a shallow roof terrace behind it).
        edge = c1 if sx > 0 else c0
        b.add(
            box(
                (edge - 0.4 * (sx > 0), _Y_FRONT + 5.0, 14.7),
                (edge + 0.4 * (sx < 0), _Y_BACK - 3.0, 15.8),
                "stone",
            )
        )
        cc = 0.5 * (c0 + c1)
        for k in range(int((length - 8.0) // 8.0)):
            y = _Y_FRONT + 9.0 + 8.0 * k
            b.add(revolve(dome_profile(2.0, 14.7, 1.6, steps=5), "tiles", n=16).placed(0.0, (cc, y, 0.0)))
        # Buttresses between the chapel bays: stepped, 1.4 m wide, 1.8 + 1.0 m deep.
        for k in range(int((length - 8.0) // 8.0) + 1):
            y = _Y_FRONT + 5.0 + 8.0 * k
            lo1 = (edge, y - 0.7, 0.0) if sx > 0 else (edge - 1.8, y - 0.7, 0.0)
            b.add(box(lo1, (lo1[0] + 1.8, y + 0.7, 10.0), "stone"))
            lo2 = (edge, y - 0.5, 10.0) if sx > 0 else (edge - 1.0, y - 0.5, 10.0)
            b.add(box(lo2, (lo2[0] + 1.0, y + 0.5, 13.5), "stone"))
    # Altar of the Kings: a lower apse block at the north end.
    b.add(
        box_walls(
            -9.0,
            _Y_BACK,
            9.0,
            _Y_BACK + 5.0,
            0.0,
            20.0,
            1.0,
            "tezontle",
            {"north": [dict(width=2.5, sill=8.0, spring=12.0, depth=0.8, arch=True, x=7.75)]},
            "wood",
        )
    )
    b.add(box((-9.3, _Y_BACK - 0.3, 20.0), (9.3, _Y_BACK + 5.3, 20.8), "stone"))


def _dome(b: Builder, y: float) -> None:
    """Crossing dome: a square base over the roofs, an octagonal drum with windows, dome, lantern."""
    b.add(box((-9.0, y - 9.0, 26.0), (9.0, y + 9.0, 32.0), "tezontle"))
    b.add(box((-9.4, y - 9.4, 32.0), (9.4, y + 9.4, 32.8), "stone"))
    window = dict(width=2.0, sill=1.5, spring=5.0, depth=0.8, arch=True, x=-1.0)
    b.add(polygon_drum(7.5, 8, 32.8, 8.0, 1.4, "stone", window, "wood", center=(0.0, y)))
    b.add(polygon_prism(8.0, 8, 40.8, 41.6, "stone", center=(0.0, y)))
    b.add(revolve(dome_profile(7.8, 41.6, 9.0, steps=12), "tiles", n=40).placed(0.0, (0.0, y, 0.0)))
    lantern = dict(width=0.8, sill=0.5, spring=2.2, depth=0.4, arch=True, x=-0.4)
    b.add(polygon_drum(1.6, 8, 50.3, 3.2, 0.5, "stone", lantern, "wood", center=(0.0, y)))
    b.add(revolve(dome_profile(1.9, 53.5, 1.6, steps=5), "tiles", n=16).placed(0.0, (0.0, y, 0.0)))
    b.add(cylinder(0.15, 55.0, 57.0, "stone", n=8).placed(0.0, (0.0, y, 0.0)))


def _facade(b: Builder) -> None:
    """Main facade block between the towers: three portals, pilasters, two cornices, a pediment."""
    y0, y1, width, height = -48.5, _Y_FRONT + 0.5, 28.0, 30.0
    portals = [
        dict(width=4.5, sill=0.0, spring=8.0, depth=1.8, arch=True, x=11.75),
        dict(width=3.2, sill=0.0, spring=6.0, depth=1.6, arch=True, x=3.0),
        dict(width=3.2, sill=0.0, spring=6.0, depth=1.6, arch=True, x=21.8),
    ]
    windows = [
        dict(width=2.6, sill=3.0, spring=6.5, depth=1.2, arch=True, x=12.7),
        dict(width=1.6, sill=2.5, spring=5.5, depth=0.8, arch=True, x=3.8),
        dict(width=1.6, sill=2.5, spring=5.5, depth=0.8, arch=True, x=22.6),
    ]
    lower = 12.5
    # The block is 4 m deep: front and back walls of 2 m each, so no wall fills another's recess.
    b.add(box_walls(-0.5 * width, y0, 0.5 * width, y1, 0.0, lower, 2.0, "stone", {"south": portals}, "wood"))
    b.add(
        box_walls(
            -0.5 * width, y0, 0.5 * width, y1, lower, height - lower, 2.0, "stone", {"south": windows}, "wood"
        )
    )
    # Pilasters (0.5 m proud) between the portals, on two storeys.
    for x in (-12.8, -6.8, 6.8, 12.8):
        b.add(box((x - 0.6, y0 - 0.5, 0.0), (x + 0.6, y0, 11.5), "stone"))
        b.add(box((x - 0.5, y0 - 0.4, 12.5), (x + 0.5, y0, 23.0), "stone"))
    # Cornices: the overhangs of the facade.
    for z, proud in ((11.5, 0.9), (23.0, 0.8), (height, 0.7)):
        b.add(box((-0.5 * width - 0.2, y0 - proud, z), (0.5 * width + 0.2, y1, z + 1.0), "stone"))
    # Attic with a clock niche and a triangular pediment above the central portal.
    b.add(
        box_walls(
            -6.0,
            y0 + 0.5,
            6.0,
            y1,
            height + 1.0,
            5.0,
            1.5,
            "stone",
            {"south": [dict(width=2.2, sill=1.0, spring=3.0, depth=0.6, arch=True, x=4.9)]},
            "wood",
        )
    )
    ped = np.array([[-4.0, 0.0], [4.0, 0.0], [0.0, 2.5]])
    pediment = loft(
        [(np.column_stack([ped[:, 0], ped[:, 1]]), 0.0), (np.column_stack([ped[:, 0], ped[:, 1]]), 0.6)],
        "stone",
    )
    # The pediment is a triangular prism in the x-z plane: swap y and z of the lofted prism.
    v = pediment.vertices[:, [0, 2, 1]].copy()
    v[:, 1] = y0 - 0.6 + v[:, 1]
    v[:, 2] += 12.5
    pediment.vertices, pediment.faces = v, pediment.faces[:, ::-1]
    b.add(pediment)


def _tower(b: Builder, sx: int, top: float) -> None:
    """Bell tower: square body to 34 m, bell stage with deep arched openings, bell cap, lantern."""
    x0, x1 = (14.0, 27.0) if sx > 0 else (-27.0, -14.0)
    y0, y1 = -55.0, -42.0
    body_h = 34.0
    niches = [dict(width=1.8, sill=h, spring=h + 3.2, depth=0.6, arch=True, x=5.6) for h in (10.0, 20.0)]
    outer = "east" if sx > 0 else "west"
    b.add(box_walls(x0, y0, x1, y1, 0.0, body_h, 2.0, "stone", {"south": niches, outer: niches}, "wood"))
    for z, proud in ((12.0, 0.5), (24.0, 0.5), (body_h, 0.8)):
        b.add(box((x0 - proud, y0 - proud, z), (x1 + proud, y1 + proud, z + 0.8), "stone"))
    # Corner pilasters of the body.
    for cx in (x0, x1 - 1.2):
        for cy in (y0, y1 - 1.2):
            b.add(box((cx - 0.3, cy - 0.3, 0.0), (cx + 1.5, cy + 1.5, 12.0), "stone"))
    # Bell stage: inset 1.5 m, a 0.9 m deep arched opening on each face (the bells' chamber).
    s0, s1, z_stage = (x0 + 1.5, x1 - 1.5), (y0 + 1.5, y1 - 1.5), body_h + 0.8
    stage_h = 0.27 * (top - z_stage) + 7.0
    opening = dict(width=3.4, sill=1.5, spring=stage_h - 4.0, depth=1.6, arch=True, x=3.3)
    b.add(
        box_walls(
            s0[0],
            s1[0],
            s0[1],
            s1[1],
            z_stage,
            stage_h,
            2.0,
            "stone",
            {s: [opening] for s in ("north", "south", "east", "west")},
            "wood",
        )
    )
    z_cap = z_stage + stage_h
    b.add(box((s0[0] - 0.6, s1[0] - 0.6, z_cap), (s0[1] + 0.6, s1[1] + 0.6, z_cap + 0.8), "stone"))
    # Bell-shaped cap on a square plan (convex loft of shrinking squares), then a lantern and a cross.
    cxy = np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])
    half = 0.5 * (s0[1] - s0[0]) - 0.3
    cap_h = 0.55 * (top - z_cap - 0.8)
    rings = [
        (
            rect(-half * np.cos(a), -half * np.cos(a), half * np.cos(a), half * np.cos(a)) * 1.0 + cxy,
            z_cap + 0.8 + cap_h * np.sin(a),
        )
        for a in np.linspace(0, np.pi / 2 * 0.85, 8)
    ]
    b.add(loft(rings, "stone", mapping="box"))
    z_l = rings[-1][1]
    lantern_h = 0.45 * (top - z_l)
    b.add(cylinder(1.0, z_l - 0.2, z_l + lantern_h, "stone", n=12).placed(0.0, (cxy[0], cxy[1], 0.0)))
    b.add(
        revolve(dome_profile(1.2, z_l + lantern_h, 0.8, steps=4), "stone", n=12).placed(
            0.0, (cxy[0], cxy[1], 0.0)
        )
    )
    z_cross = z_l + lantern_h + 0.7
    t = 0.15
    b.add(box((cxy[0] - t, cxy[1] - t, z_cross), (cxy[0] + t, cxy[1] + t, top), "stone"))
    arm_z = top - 0.3 * (top - z_cross)
    b.add(box((cxy[0] - 0.9, cxy[1] - t, arm_z - t), (cxy[0] + 0.9, cxy[1] + t, arm_z + t), "stone"))
