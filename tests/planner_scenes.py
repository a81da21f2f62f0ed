"""Tiny proxy scenes for the planner tests: box buildings on a ground plane (world metres)."""

from __future__ import annotations

import numpy as np
import trimesh


def box_building(
    size=(10.0, 8.0, 6.0), center_xy=(0.0, 0.0), ground_half: float | None = 20.0
) -> trimesh.Trimesh:
    """A closed box standing on z = 0, plus an optional square ground of half-side ``ground_half``."""
    sx, sy, sz = size
    box = trimesh.creation.box(extents=(sx, sy, sz))
    box.apply_translation((center_xy[0], center_xy[1], sz / 2.0))
    if ground_half is None:
        return box
    g = float(ground_half)
    ground = trimesh.Trimesh(
        vertices=np.array([[-g, -g, 0.0], [g, -g, 0.0], [g, g, 0.0], [-g, g, 0.0]]),
        faces=np.array([[0, 1, 2], [0, 2, 3]]),
        process=False,
    )
    return trimesh.util.concatenate([box, ground])
