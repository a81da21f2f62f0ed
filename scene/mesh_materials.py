"""Photo-like materials for the parts of a user's mesh that have no texture of their own.

A uniform grey or flat-coloured part renders as one colour, which SIFT cannot match. Each such part
is split by surface class (``SURFACE_PRESETS``: roof, wall, ground, detail) and given that class's
procedural material (``scene.textures``), box-projected at ``texel_m`` metres per texel from a
random offset per part (neighbouring parts never show the same patch), tinted by the part's own
colour so the model keeps its look. One grey texture per class serves every part (the tint is the
MuJoCo material colour), so a model with hundreds of coloured parts still uploads four textures.
"""

from __future__ import annotations

import functools

import numpy as np

from scene.base import MeshPart
from scene.procedural.geometry import _split_by_uv
from scene.textures import PRESETS, cached_texture, make_texture, material_seed

SURFACE_CLASSES = ("roof", "wall", "ground", "detail")
# Chosen for texture that SIFT can hold on at every distance a planner flies: courses of ashlar on
# walls, clay tiles on roofs, flagstones on the ground, wood grain on small parts.
SURFACE_PRESETS = {"roof": "roof_tiles", "wall": "stone_beige", "ground": "paving", "detail": "wood_dark"}
# A face faces up at normal z >= this (roof, or ground below GROUND_HEIGHT_M); a part smaller than
# DETAIL_DIAGONAL_M across (a railing, a sill, an ornament) is detail whatever it faces.
FACING_UP_Z = 0.5
GROUND_HEIGHT_M = 0.25
DETAIL_DIAGONAL_M = 1.5
# Grey textures have this mean (of 1): a tint of the part's colour / this restores its brightness.
GREY_MEAN = 0.75
TEXTURE_SIZE = 2048


def face_classes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) index into ``SURFACE_CLASSES`` of each face of one part (world metres, Z up)."""
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = normal[:, 2] / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)
    low = tri[:, :, 2].mean(axis=1) < GROUND_HEIGHT_M
    classes = np.full(len(faces), SURFACE_CLASSES.index("wall"), np.int8)
    classes[(nz >= FACING_UP_Z) & ~low] = SURFACE_CLASSES.index("roof")
    classes[(nz >= FACING_UP_Z) & low] = SURFACE_CLASSES.index("ground")
    used = vertices[np.unique(faces)]
    if np.linalg.norm(used.max(0) - used.min(0)) < DETAIL_DIAGONAL_M:
        classes[:] = SURFACE_CLASSES.index("detail")
    return classes


def class_textures(stem: str, seed: int, cache_dir) -> dict[str, np.ndarray]:
    """The grey texture of every surface class (``<stem>_surface_<class>`` keys), cached."""
    out = {}
    for name in SURFACE_CLASSES:
        key = f"{stem}_surface_{name}"
        rgb = cached_texture(
            stem, key, SURFACE_PRESETS[name], TEXTURE_SIZE, material_seed(seed, key), cache_dir
        ).astype(np.float32)
        grey = rgb.mean(axis=2)
        grey *= GREY_MEAN * 255.0 / max(float(grey.mean()), 1.0)
        out[key] = np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return out


@functools.cache
def preset_colour(name: str) -> np.ndarray:
    """Mean RGB (0-1) of a surface class's preset: the tint of a part that has no colour."""
    preset = SURFACE_PRESETS[name]
    colour = PRESETS[preset].get("color")
    if colour is None:
        colour = make_texture(preset, 256, 0).reshape(-1, 3).mean(axis=0) / 255.0
    return np.asarray(colour, dtype=float)


def material_parts(
    name: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    colour: np.ndarray | None,
    stem: str,
    texel_m: float,
    rng: np.random.Generator,
) -> list[MeshPart]:
    """One textured MeshPart per surface class present in the part ``vertices``/``faces``.

    Args:
        colour: the part's flat RGB (0-255), or None (the class preset's own colour).
        texel_m: metres per texel on the surface (a texture spans ``TEXTURE_SIZE * texel_m``).
        rng: draws each part's UV offset.
    """
    classes = face_classes(vertices, faces)
    parts = []
    for index in np.unique(classes):
        cls = SURFACE_CLASSES[index]
        sub = faces[classes == index]
        corner_uv = box_uv(vertices, sub, TEXTURE_SIZE * texel_m) + rng.random(2)
        v, f, uv = _split_by_uv(vertices, sub, corner_uv)
        base = preset_colour(cls) if colour is None else np.asarray(colour[:3], float) / 255.0
        tint = tuple(float(c) for c in np.clip(base / GREY_MEAN, 0.0, 1.0))
        parts.append(MeshPart(f"{name}_{cls}", v, f, uv=uv, texture=f"{stem}_surface_{cls}", tint=tint))
    return parts


def box_uv(vertices: np.ndarray, faces: np.ndarray, period_m: float) -> np.ndarray:
    """(F, 3, 2) box-projected UVs (1 unit = ``period_m`` metres): each face on its dominant axis."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(n), axis=1)
    uv = np.empty(tri.shape[:2] + (2,))
    for a, (i, j) in enumerate(((1, 2), (0, 2), (0, 1))):
        m = axis == a
        uv[m, :, 0], uv[m, :, 1] = tri[m][..., i], tri[m][..., j]
    return uv / period_m


def map_texel_m(
    vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, image_size: tuple[int, int]
) -> float:
    """Metres of surface per texel of a textured part (its area over the texels its UVs cover)."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    t = uv[faces]
    uv_area = (
        0.5
        * np.abs(
            (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
            - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1])
        ).sum()
    )
    texels = uv_area * image_size[0] * image_size[1]
    return float(np.sqrt(area / texels)) if texels > 0 else float("inf")
