"""Procedural photo-like textures for the ground-truth scenes, cached on disk.

Every texture is periodic (it wraps seamlessly, so UVs may run past 1) and carries detail at every
scale from a few texels (grain, pores, mortar chips) up to metres (weathering, stains), so that SIFT
finds thousands of features at a 1 cm ground sampling distance and no patch repeats within a view:
one 4096 px map at 1.5 cm/texel repeats only every 61 m, and every surface reads it at its own
random offset. Generation is numpy/OpenCV (a 4096 px map takes about 1-3 s on one core); results are
cached as PNG under ``cache_dir`` keyed by (scene, seed, kind, size, params).

Image axes: rows follow the texture's v axis, columns its u axis. Patterns that have a direction
(tile courses, masonry courses, wood grain, metal seams) run their courses along u, i.e. along the
horizontal when a wall is mapped with v = height.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import scipy.fft

from scene.io import write_atomic

# Bumped whenever a generator changes, so stale cache entries are never reused.
GENERATOR_VERSION = 7
# Relative amplitude of the mid-frequency speckle added to every material (see make_texture).
SPECKLE = 0.18

_RGB = tuple[float, float, float]


# ----------------------------------------------------------------------------------------- noise


def _upsample_periodic(field: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bicubic resize of a periodic field to ``shape`` (rows, cols) that stays periodic."""
    h, w = field.shape
    if (h, w) == shape:
        return field.astype(np.float32)
    pad = 4
    padded = np.pad(field.astype(np.float32), pad, mode="wrap")
    fy, fx = shape[0] / h, shape[1] / w
    big = cv2.resize(padded, None, fx=fx, fy=fy, interpolation=cv2.INTER_CUBIC)
    oy, ox = round(pad * fy), round(pad * fx)
    return np.ascontiguousarray(big[oy : oy + shape[0], ox : ox + shape[1]])


def fractal_noise(
    rng: np.random.Generator,
    size: int,
    beta: float = 2.0,
    base: int = 1024,
    aspect: tuple[int, int] = (1, 1),
) -> np.ndarray:
    """Periodic fractal (1/f^beta power spectrum) noise, (size, size) float32, zero mean, unit std.

    Synthesised by FFT at ``base`` px (at most ``size``) and upsampled, so it carries the low and
    middle frequencies; add :func:`grain` for the finest texel-scale detail. ``aspect`` = (ry, rx)
    shrinks the synthesis grid per axis, stretching features ry times along v (image rows) and rx
    times along u: (12, 1) gives streaks running along v (wood grain, rain streaks).
    """
    n = min(size, base)
    shape = (max(8, n // aspect[0]), max(8, n // aspect[1]))
    white = rng.standard_normal(shape, dtype=np.float32)
    spectrum = scipy.fft.rfft2(white)
    fy = scipy.fft.fftfreq(shape[0]).astype(np.float32)[:, None] * aspect[0]
    fx = scipy.fft.rfftfreq(shape[1]).astype(np.float32)[None, :] * aspect[1]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    spectrum *= f ** (-beta / 2.0)
    spectrum[0, 0] = 0.0
    field = scipy.fft.irfft2(spectrum, s=shape).astype(np.float32)
    field = _upsample_periodic(field, (size, size))
    field -= field.mean()
    field /= max(float(field.std()), 1e-6)
    return field


def grain(rng: np.random.Generator, size: int, sigma: float = 0.8) -> np.ndarray:
    """Periodic fine grain: white noise blurred by ``sigma`` texels, (size, size) float32, unit std."""
    white = rng.integers(0, 256, (size, size), dtype=np.uint8).astype(np.float32)
    if sigma > 0:
        pad = int(np.ceil(3 * sigma)) + 1
        white = np.pad(white, pad, mode="wrap")
        white = cv2.GaussianBlur(white, (0, 0), sigma)[pad:-pad, pad:-pad]
    white -= white.mean()
    white /= max(float(white.std()), 1e-6)
    return white


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.subtract(x, np.float32(edge0), dtype=np.float32)
    t *= np.float32(1.0 / (edge1 - edge0))
    np.clip(t, 0.0, 1.0, out=t)
    rise = np.float32(3.0) - np.float32(2.0) * t
    t *= t
    t *= rise
    return t


def _colorize(shade: np.ndarray, color: np.ndarray) -> np.ndarray:
    """RGB float image from a per-pixel shade (H, W) and colour (H, W, 3) or (3,) in 0..1."""
    return shade[..., None] * color


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------- patterns


def _courses(
    rng: np.random.Generator,
    size: int,
    row_height: float,
    width_range: tuple[float, float],
    warp: float,
    stagger: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A periodic running-bond layout of blocks in courses along u.

    Returns (block_id, n_blocks, edge distance in texels, fraction across the block in u, fraction
    up the course in v), each (size, size) float32 except n_blocks (int). Row heights vary +-15 %,
    block widths are drawn from ``width_range`` texels, and the layout is domain-warped by ``warp``
    texels (periodic remap) so that joints are not ruler-straight.
    """
    n_rows = max(1, round(size / row_height))
    heights = rng.uniform(0.85, 1.15, n_rows)
    row_edges = np.concatenate([[0.0], np.cumsum(heights)]) * (size / heights.sum())
    pix = np.round(row_edges).astype(int)
    block = np.empty((size, size), np.float32)
    edge = np.empty((size, size), np.float32)
    u_frac = np.empty((size, size), np.float32)
    v_frac = np.empty((size, size), np.float32)
    x = np.arange(size, dtype=np.float64) + 0.5
    n_blocks = 0
    for r in range(n_rows):
        widths = []
        while sum(widths) < size:
            widths.append(rng.uniform(*width_range))
        widths = np.asarray(widths) * (size / sum(widths))
        bounds = np.concatenate([[0.0], np.cumsum(widths)])
        bounds[-1] = size
        shift = rng.uniform(0, size) if stagger else 0.0
        xs = (x - shift) % size
        i = np.clip(np.searchsorted(bounds, xs, side="right") - 1, 0, len(widths) - 1)
        left, right = bounds[i], bounds[i + 1]
        y0, y1 = pix[r], pix[r + 1]
        if y1 <= y0:
            continue
        ys = np.arange(y0, y1) + 0.5
        dy = np.minimum(ys - row_edges[r], row_edges[r + 1] - ys)
        dx = np.minimum(xs - left, right - xs)
        block[y0:y1] = (n_blocks + i)[None, :]
        edge[y0:y1] = np.minimum(dx[None, :], dy[:, None])
        u_frac[y0:y1] = ((xs - left) / (right - left))[None, :]
        v_frac[y0:y1] = ((ys - row_edges[r]) / (row_edges[r + 1] - row_edges[r]))[:, None]
        n_blocks += len(widths)
    if warp > 0:
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        map_x = xx + warp * fractal_noise(rng, size, beta=2.6, base=256)
        map_y = yy + warp * fractal_noise(rng, size, beta=2.6, base=256)
        del xx, yy

        def remap(a: np.ndarray, interp: int) -> np.ndarray:
            return cv2.remap(a, map_x, map_y, interp, borderMode=cv2.BORDER_WRAP)

        block = remap(block, cv2.INTER_NEAREST)
        edge = remap(edge, cv2.INTER_LINEAR)
        u_frac = remap(u_frac, cv2.INTER_NEAREST)
        v_frac = remap(v_frac, cv2.INTER_NEAREST)
    return block.astype(np.int32), n_blocks, edge, u_frac, v_frac


def _block_colors(rng: np.random.Generator, n: int, palette: list[_RGB], spread: float) -> np.ndarray:
    """(n, 3) per-block colours: a random mix of two palette entries, random brightness."""
    pal = np.asarray(palette, dtype=np.float32)
    a = pal[rng.integers(0, len(pal), n)]
    b = pal[rng.integers(0, len(pal), n)]
    t = rng.random((n, 1)).astype(np.float32)
    tone = (1.0 + spread * rng.standard_normal((n, 1))).astype(np.float32)
    return (a * (1 - t) + b * t) * tone


# ----------------------------------------------------------------------------------- generators


def _masonry(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Stone blocks / bricks / flagstones with mortar joints, chipped edges, weathering."""
    block, n_blocks, edge, _, _ = _courses(
        rng, size, p["row_height"], tuple(p["block_width"]), p.get("warp", 1.5), p.get("stagger", True)
    )
    colors = _block_colors(rng, n_blocks, p["palette"], p.get("block_spread", 0.12))
    rgb = colors[block]
    # Per-block surface: fractal relief + grain + pores.
    detail = 0.10 * fractal_noise(rng, size, beta=1.6) + p.get("grain", 0.10) * grain(rng, size, 0.7)
    pores = grain(rng, size, 1.2)
    detail -= p.get("pores", 0.25) * _smoothstep(1.6, 2.6, pores)
    weather = fractal_noise(rng, size, beta=2.4, base=512)
    shade = 1.0 + detail + p.get("weathering", 0.12) * weather
    # Bevel: edges of each block catch less light; mortar sits below.
    mortar_w = p.get("mortar_width", 1.5)
    chip = 0.9 * fractal_noise(rng, size, beta=1.2, base=2048)
    e = edge + chip
    bevel = 0.82 + 0.18 * _smoothstep(mortar_w, mortar_w + 3.0, e)
    in_mortar = _smoothstep(mortar_w + 0.7, mortar_w - 0.3, e)
    mortar = np.asarray(p.get("mortar", (0.55, 0.53, 0.50)), np.float32)
    mortar_shade = 0.9 + 0.15 * grain(rng, size, 1.0)
    rgb = _colorize(shade * bevel, rgb) * (1 - in_mortar[..., None]) + _colorize(
        mortar_shade * in_mortar, mortar
    )
    # Lichen / dirt blotches (dark, low frequency, sharp-ish boundary).
    if p.get("lichen", 0.0) > 0:
        blot = _smoothstep(0.8, 1.6, fractal_noise(rng, size, beta=2.2, base=1024))
        speck = _smoothstep(0.5, 1.5, grain(rng, size, 1.5))
        amount = p["lichen"] * blot * (0.6 + 0.4 * speck)
        dark = np.asarray(p.get("lichen_color", (0.22, 0.24, 0.18)), np.float32)
        rgb = rgb * (1 - amount[..., None]) + dark * amount[..., None]
    return rgb


def _roof_tiles(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Barrel/pan roof tiles in courses along u with overlap shadows, moss and grime."""
    tile_w = p["tile_width"]
    block, n_blocks, edge, u_frac, v_frac = _courses(
        rng, size, p["row_height"], (tile_w * 0.85, tile_w * 1.15), p.get("warp", 1.5), stagger=True
    )
    colors = _block_colors(rng, n_blocks, p["palette"], p.get("block_spread", 0.10))
    # Hand-made, weathered tiles: curvature and overlap shadow differ from tile to tile.
    curve = rng.uniform(0.15, 0.40, n_blocks).astype(np.float32)[block]
    lap = rng.uniform(0.15, 0.35, n_blocks).astype(np.float32)[block]
    barrel = 1.0 - curve + curve * np.sin(np.pi * u_frac)  # curved tile catches light in the middle
    overlap = 1.0 - 1.8 * lap + 1.8 * lap * _smoothstep(0.0, 0.25, v_frac)  # the course above shades
    detail = 1.0 + 0.16 * grain(rng, size, 0.8) + 0.14 * fractal_noise(rng, size, beta=1.5)
    rgb = _colorize(barrel * overlap * detail, colors[block])
    gap = _smoothstep(1.2, 0.2, edge)
    rgb *= (1 - 0.6 * gap)[..., None]
    moss = _smoothstep(0.6, 1.5, fractal_noise(rng, size, beta=2.0)) * _smoothstep(
        0.0, 1.0, grain(rng, size, 2.0) + 0.5
    )
    moss_color = np.asarray(p.get("moss", (0.25, 0.28, 0.17)), np.float32)
    amount = p.get("moss_amount", 0.5) * moss
    rgb = rgb * (1 - amount[..., None]) + moss_color * amount[..., None]
    grime = 1.0 + 0.15 * fractal_noise(rng, size, beta=2.6, base=512, aspect=(1, 4))
    return rgb * grime[..., None]


def _plaster(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Lime plaster / render: trowel texture, fine grain, hairline cracks, rain streaks."""
    color = np.asarray(p["color"], np.float32)
    trowel = fractal_noise(rng, size, beta=1.8)
    fine = grain(rng, size, 0.7)
    ridged = 1.0 - np.abs(fractal_noise(rng, size, beta=2.2, base=2048))
    cracks = _smoothstep(0.96, 0.995, ridged) * _smoothstep(0.3, 1.0, fractal_noise(rng, size, 2.0, 512))
    streaks = fractal_noise(rng, size, beta=2.0, base=1024, aspect=(8, 1))
    patches = fractal_noise(rng, size, beta=2.8, base=256)
    shade = (
        1.0
        + p.get("trowel", 0.08) * trowel
        + p.get("grain", 0.09) * fine
        + 0.08 * streaks
        + 0.10 * patches
        - 0.35 * cracks
    )
    tint = 1.0 + 0.04 * np.stack([patches, -patches * 0.5, -patches], axis=-1)
    return _colorize(shade, color) * tint


def _wood(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Lacquered / painted wood planks with grain along v and worn paint."""
    # Planks are courses along v: transpose a course layout.
    block, n_blocks, edge, _, _ = _courses(rng, size, p["plank_width"], (size / 3, size / 1.2), 0.5)
    block, edge = block.T, edge.T
    colors = _block_colors(rng, n_blocks, p["palette"], p.get("block_spread", 0.08))
    grain_v = fractal_noise(rng, size, beta=1.4, base=2048, aspect=(16, 1))
    knots = _smoothstep(2.2, 3.0, fractal_noise(rng, size, beta=2.0, base=512))
    wear = _smoothstep(0.8, 1.6, fractal_noise(rng, size, beta=2.2)) * p.get("wear", 0.4)
    fibres = fractal_noise(rng, size, beta=1.0, base=4096, aspect=(4, 1))
    shade = 1.0 + 0.12 * grain_v + 0.10 * fibres + 0.14 * grain(rng, size, 0.7) - 0.3 * knots
    rgb = _colorize(shade, colors[block])
    under = np.asarray(p.get("under", (0.35, 0.25, 0.17)), np.float32)
    rgb = rgb * (1 - wear[..., None]) + _colorize(shade, under) * wear[..., None]
    return rgb * (1 - 0.5 * _smoothstep(1.0, 0.0, edge))[..., None]


def _metal(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Sheet metal roofing (copper patina, gilding) with standing seams along v and streaks."""
    color = np.asarray(p["color"], np.float32)
    alt = np.asarray(p.get("patina", p["color"]), np.float32)
    seam_period = p["seam_spacing"]
    u = np.arange(size, dtype=np.float32)
    n_seams = max(1, round(size / seam_period))
    phase = (u * n_seams / size) % 1.0
    seam = _smoothstep(0.04, 0.0, np.minimum(phase, 1 - phase))[None, :]
    blotch = _smoothstep(-0.5, 1.2, fractal_noise(rng, size, beta=2.2))
    streak = fractal_noise(rng, size, beta=1.8, base=2048, aspect=(12, 1))
    # Horizontal cross seams every sheet length, at random per column of sheets.
    sheet = fractal_noise(rng, size, beta=1.2, base=2048)
    shade = 1.0 + 0.10 * streak + 0.09 * grain(rng, size, 0.8) + 0.06 * sheet - 0.35 * seam
    mix = blotch[..., None]
    return _colorize(shade, color * (1 - mix) + alt * mix)


def _glazed_tiles(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Small glazed ceramic tiles (azulejo / talavera) with grout lines and crazing."""
    tile = p["tile_size"]
    block, n_blocks, edge, u_frac, v_frac = _courses(rng, size, tile, (tile, tile), 0.4, stagger=False)
    colors = _block_colors(rng, n_blocks, p["palette"], p.get("block_spread", 0.06))
    motif = 0.5 + 0.5 * np.cos(2 * np.pi * u_frac) * np.cos(2 * np.pi * v_frac)
    glaze = 1.0 + 0.07 * grain(rng, size, 0.6) + 0.08 * fractal_noise(rng, size, beta=1.6)
    crazing = _smoothstep(0.97, 0.995, 1.0 - np.abs(fractal_noise(rng, size, beta=1.8, base=2048)))
    rgb = _colorize(glaze * (0.85 + 0.15 * motif) - 0.2 * crazing, colors[block])
    grout = _smoothstep(1.5, 0.5, edge)[..., None]
    return rgb * (1 - grout) + np.asarray(p.get("grout", (0.6, 0.58, 0.55)), np.float32) * grout


def _ground(rng: np.random.Generator, size: int, p: Mapping) -> np.ndarray:
    """Grass and bare soil with gravel, at metre-scale patches and texel-scale blades and pebbles."""
    grass = np.asarray(p.get("grass", (0.30, 0.38, 0.16)), np.float32)
    grass_dry = np.asarray(p.get("grass_dry", (0.48, 0.46, 0.26)), np.float32)
    soil = np.asarray(p.get("soil", (0.45, 0.38, 0.30)), np.float32)
    gravel = np.asarray(p.get("gravel", (0.62, 0.60, 0.56)), np.float32)
    cover = fractal_noise(rng, size, beta=2.4)
    grass_mask = _smoothstep(p.get("bare", 0.0) - 0.3, p.get("bare", 0.0) + 0.3, cover)[..., None]
    dry = _smoothstep(-1.0, 1.5, fractal_noise(rng, size, beta=2.0))[..., None]
    blades = grain(rng, size, 0.6)
    clumps = fractal_noise(rng, size, beta=1.2, base=2048)
    grass_rgb = _colorize(1.0 + 0.22 * blades + 0.15 * clumps, grass * (1 - dry) + grass_dry * dry)
    pebble_field = grain(rng, size, 1.3)
    pebbles = _smoothstep(1.0, 1.8, pebble_field)[..., None]
    pebble_tone = 1.0 + 0.25 * grain(rng, size, 2.5)
    soil_rgb = _colorize(1.0 + 0.15 * grain(rng, size, 0.8) + 0.12 * clumps, soil)
    soil_rgb = soil_rgb * (1 - pebbles) + _colorize(pebble_tone, gravel) * pebbles
    rgb = grass_rgb * grass_mask + soil_rgb * (1 - grass_mask)
    shadow = 1.0 + 0.10 * fractal_noise(rng, size, beta=2.8, base=256)
    return rgb * shadow[..., None]


GENERATORS = {
    "masonry": _masonry,
    "roof_tiles": _roof_tiles,
    "plaster": _plaster,
    "wood": _wood,
    "metal": _metal,
    "glazed_tiles": _glazed_tiles,
    "ground": _ground,
}

# Material presets the scenes use: generator + its parameters. Sizes in texels (x texel_m = metres).
PRESETS: dict[str, dict] = {
    "stone_grey": {  # weathered ashlar (Hue tombs: grey stone and brick, lichen-stained)
        "generator": "masonry",
        "row_height": 22,
        "block_width": [28, 70],
        "palette": [(0.55, 0.54, 0.50), (0.48, 0.47, 0.44), (0.62, 0.60, 0.55), (0.45, 0.43, 0.38)],
        "lichen": 0.55,
        "mortar": (0.60, 0.58, 0.54),
    },
    "stone_beige": {  # chiluca (grey-beige limestone) of the cathedral facade
        "generator": "masonry",
        "row_height": 26,
        "block_width": [30, 80],
        "palette": [(0.72, 0.68, 0.60), (0.66, 0.62, 0.55), (0.78, 0.74, 0.66), (0.60, 0.58, 0.52)],
        "lichen": 0.25,
        "lichen_color": (0.35, 0.33, 0.30),
        "mortar": (0.70, 0.68, 0.62),
    },
    "tezontle": {  # porous red volcanic stone in irregular blocks
        "generator": "masonry",
        "row_height": 18,
        "block_width": [14, 40],
        "warp": 3.0,
        "palette": [(0.50, 0.25, 0.20), (0.42, 0.20, 0.17), (0.58, 0.30, 0.24), (0.36, 0.18, 0.16)],
        "pores": 0.5,
        "grain": 0.14,
        "lichen": 0.2,
        "lichen_color": (0.20, 0.15, 0.14),
        "mortar": (0.62, 0.58, 0.52),
        "mortar_width": 1.8,
    },
    "brick": {
        "generator": "masonry",
        "row_height": 6,
        "block_width": [15, 19],
        "warp": 0.6,
        "palette": [(0.62, 0.36, 0.26), (0.55, 0.30, 0.22), (0.70, 0.44, 0.32), (0.48, 0.28, 0.22)],
        "mortar_width": 0.7,
        "lichen": 0.3,
    },
    "paving": {  # large flagstones
        "generator": "masonry",
        "row_height": 30,
        "block_width": [25, 60],
        "warp": 2.0,
        "palette": [(0.58, 0.56, 0.52), (0.50, 0.49, 0.46), (0.64, 0.61, 0.56)],
        "lichen": 0.4,
        "lichen_color": (0.28, 0.30, 0.22),
        "mortar": (0.35, 0.34, 0.30),
        "mortar_width": 1.2,
    },
    "roof_tiles": {  # yin-yang clay tiles, weathered dark ochre
        "generator": "roof_tiles",
        "row_height": 16,
        "tile_width": 14,
        "palette": [(0.55, 0.38, 0.24), (0.48, 0.33, 0.22), (0.60, 0.45, 0.30), (0.40, 0.32, 0.26)],
    },
    "plaster_ochre": {"generator": "plaster", "color": (0.80, 0.68, 0.46)},
    "plaster_white": {"generator": "plaster", "color": (0.86, 0.84, 0.78), "grain": 0.10},
    "roof_concrete": {"generator": "plaster", "color": (0.62, 0.58, 0.54), "grain": 0.14, "trowel": 0.12},
    "wood_red": {  # red lacquer columns and doors
        "generator": "wood",
        "plank_width": 14,
        "palette": [(0.62, 0.18, 0.12), (0.55, 0.15, 0.10), (0.68, 0.24, 0.15)],
        "speckle": 0.35,
    },
    "wood_dark": {
        "generator": "wood",
        "plank_width": 12,
        "palette": [(0.42, 0.30, 0.19), (0.36, 0.26, 0.16), (0.48, 0.34, 0.22)],
        "under": (0.18, 0.14, 0.10),
        "speckle": 0.3,
    },
    "metal_green": {
        "generator": "metal",
        "color": (0.30, 0.52, 0.42),
        "patina": (0.42, 0.62, 0.52),
        "seam_spacing": 35,
    },
    "metal_gold": {
        "generator": "metal",
        "color": (0.78, 0.62, 0.28),
        "patina": (0.62, 0.48, 0.22),
        "seam_spacing": 30,
    },
    "dome_tiles": {
        "generator": "glazed_tiles",
        "tile_size": 8,
        "palette": [(0.85, 0.70, 0.25), (0.20, 0.30, 0.60), (0.88, 0.86, 0.80), (0.70, 0.55, 0.20)],
    },
    "ground_grass": {"generator": "ground", "bare": -0.3},
    "ground_dry": {"generator": "ground", "bare": 0.4, "grass": (0.36, 0.40, 0.20)},
}


# -------------------------------------------------------------------------------------- public


def make_texture(preset: str | Mapping, size: int, seed: int) -> np.ndarray:
    """Generate a texture image (size, size, 3) uint8 from a preset name or a parameter mapping.

    Args:
        preset: a key of ``PRESETS`` or a mapping with ``generator`` and that generator's params.
        size: side length in texels (power of two recommended, >= 256).
        seed: random seed; the same (preset, size, seed) always gives the same bytes.
    """
    params = _resolve(preset)
    if not isinstance(size, int | np.integer) or size < 256:
        raise ValueError(f"texture size must be an integer >= 256, got {size!r}")
    generator = GENERATORS[params["generator"]]
    rng = np.random.default_rng(seed)
    rgb = generator(rng, int(size), params)
    # Mid-frequency speckle (pits, grit, dirt: 2-5 texels) on every material. It survives texture
    # filtering at ~1 texel per pixel and keeps SIFT features in shade, where the lighting divides
    # the texture's contrast by about three.
    speckle = grain(rng, int(size), 1.2)
    speckle += 0.6 * grain(rng, int(size), 2.2)
    rgb *= (1.0 + params.get("speckle", SPECKLE) * speckle)[..., None]
    return _to_uint8(rgb)


def texture_key(scene: str, name: str, preset: str | Mapping, size: int, seed: int) -> str:
    """Cache key (hex) of one texture: scene, material name, parameters, size, seed, version."""
    record = {
        "scene": scene,
        "name": name,
        "params": _resolve(preset),
        "size": int(size),
        "seed": int(seed),
        "version": GENERATOR_VERSION,
    }
    blob = json.dumps(record, sort_keys=True, default=list).encode()
    return hashlib.sha1(blob).hexdigest()[:16]


def cached_texture(
    scene: str,
    name: str,
    preset: str | Mapping,
    size: int,
    seed: int,
    cache_dir: str | os.PathLike | None,
) -> np.ndarray:
    """Load a texture from ``cache_dir/textures`` or generate it and store it atomically (PNG).

    ``cache_dir=None`` disables caching. A cache file that cannot be decoded is regenerated.
    """
    if cache_dir is None:
        return make_texture(preset, size, seed)
    path = (
        Path(cache_dir)
        / "textures"
        / f"{scene}_{name}_{size}_s{seed}_{texture_key(scene, name, preset, size, seed)}.png"
    )
    if path.is_file():
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is not None and bgr.shape == (size, size, 3):
            return np.ascontiguousarray(bgr[..., ::-1])
    image = make_texture(preset, size, seed)

    def _write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), image[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write texture cache file {tmp}")

    write_atomic(path, _write)
    return image


def material_seed(scene_seed: int, name: str) -> int:
    """Deterministic per-material seed derived from the scene seed and the material name."""
    digest = hashlib.sha1(f"{int(scene_seed)}:{name}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def detail_overlay(
    image: np.ndarray, seed: int, strength: float = 0.25, texels_per_pixel: float = 1.0
) -> np.ndarray:
    """Multiply fine periodic procedural detail (grain + fractal mottling) onto a plain texture.

    Used for low-detail meshes whose own textures are too smooth for SIFT. The overlay has unit mean,
    so the average colour is kept. ``texels_per_pixel`` > 1 upsamples the image first (more texels
    for the detail to live in). Returns a new uint8 (H, W, 3) image.
    """
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.float32) / 255.0
    if texels_per_pixel > 1:
        img = cv2.resize(img, None, fx=texels_per_pixel, fy=texels_per_pixel, interpolation=cv2.INTER_CUBIC)
    h, w = img.shape[:2]
    side = 1 << int(np.ceil(np.log2(max(h, w, 256))))
    rng = np.random.default_rng(seed)
    detail = 0.6 * grain(rng, side, 0.8) + 0.4 * fractal_noise(rng, side, beta=1.5)
    factor = np.clip(1.0 + strength * detail[:h, :w], 0.2, 2.0)
    # Lift very dark or very bright plain colours a little so multiplication has something to act on.
    return _to_uint8((0.08 + 0.84 * img) * factor[..., None])


def _resolve(preset: str | Mapping) -> dict:
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown texture preset {preset!r}; known: {sorted(PRESETS)}")
        params = dict(PRESETS[preset])
    else:
        params = dict(preset)
    if params.get("generator") not in GENERATORS:
        raise ValueError(
            f"unknown texture generator {params.get('generator')!r}; known: {sorted(GENERATORS)}"
        )
    return params
