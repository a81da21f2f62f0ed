"""Lawnmower (boustrophedon grid) flights: the exploratory flight that builds the proxy, and a planner.

A grid of camera positions at a fixed altitude covers the structure's footprint plus a margin. The
spacing between images along a flight line and between lines follows from the configured front and
side overlap of the nadir footprints on flat ground at z = 0:

    along-track footprint  = 2 * altitude * tan(vfov / 2)   (the image height points along the track)
    across-track footprint = 2 * altitude * tan(hfov / 2)
    spacing                = (1 - overlap) * footprint

The spacing is kept exactly (the grid is centred on the region and may overhang it), so the flown
overlap on flat ground equals the configured one. Two camera modes:

- ``centre``: every camera aims at the structure's centre (the paper's exploratory flight, "viewpoints
  directed towards the object centre"); pitch is clipped to the gimbal range.
- ``nadir``: every camera looks straight down, the image's up axis along the direction of travel.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numpy as np
import open3d as o3d
import trimesh
from scipy import ndimage

from planner.base import merge_params
from scene.base import Box
from scene.camera import Intrinsics, yaw_pitch_from_direction
from scene.plan import Plan, PlanningError

DEFAULTS = {
    "mode": "centre",  # centre | nadir
    "altitude_m": None,  # flight height above the ground z = 0; None: structure top + altitude_above_top_m
    "altitude_above_top_m": 15.0,
    "front_overlap": 0.8,
    "side_overlap": 0.8,
    "margin_m": None,  # grid region = structure footprint grown by this; None: margin_footprints x footprint
    "margin_footprints": 0.5,
    "flight_direction": "auto",  # auto (along the longer side of the region) | x | y
    "aim_height_fraction": 0.5,  # centre mode: aim at this fraction of the structure height
    "min_clearance_above_top_m": 2.0,  # refuse flights lower than structure top + this
    "pitch_min_deg": -90.0,
    "pitch_max_deg": 30.0,
    "structure_min_height_m": 0.5,  # plan(): see structure_bounds_from_proxy
    # Orbit rings after the grid (0: none, the paper's flight): horizontal rings around the
    # structure's footprint at evenly spaced heights, each view facing the footprint, for structures
    # whose walls a grid above the top sees only at grazing angles (tall plants, courtyards).
    "orbit_rings": 0,
    "orbit_distance_m": None,  # ring distance from the footprint (m); None: altitude_above_top_m
    "orbit_pitch_deg": -15.0,  # camera pitch on the rings (some ground in view links them to the grid)
    "orbit_min_height_m": 2.0,  # lowest ring height above the ground (m)
}

MODES = ("centre", "nadir")
STRUCTURE_CELL_M = 1.0  # column size (m) of the height map that finds the structure on a proxy
STRUCTURE_SUPPORT_GAP_M = 1.0  # a proxy piece farther than this (m) from the rest is a floater


def _merged(params: Mapping | None) -> dict:
    merged = merge_params("lawnmower", DEFAULTS, params)
    return merged


def check_params(params: Mapping | None, intrinsics: Intrinsics) -> None:
    """Refuse a bad setting before any work (the planner contract, ``planner.base``): the ones that
    need no structure; the altitude against the structure is checked when planning."""
    del intrinsics
    p = _merged(params)
    if str(p["mode"]) not in MODES:
        raise ValueError(f"lawnmower: mode must be one of {MODES}, got {p['mode']!r}")
    _check_overlap("front_overlap", p["front_overlap"])
    _check_overlap("side_overlap", p["side_overlap"])
    if str(p["flight_direction"]) not in ("auto", "x", "y"):
        raise ValueError(f"lawnmower: flight_direction must be auto, x or y, got {p['flight_direction']!r}")


def _check_overlap(name: str, value) -> float:
    value = float(value)
    if not (0.0 <= value < 1.0) or not math.isfinite(value):
        raise ValueError(f"lawnmower: {name} must lie in [0, 1) (a fraction, 0.8 = 80 %), got {value}")
    return value


def footprint_m(intrinsics: Intrinsics, height_m: float) -> tuple[float, float]:
    """Nadir footprint (across-track width, along-track length) in metres at ``height_m`` above ground."""
    half_h = math.tan(math.radians(intrinsics.hfov_deg) / 2.0)
    half_v = 0.5 * intrinsics.height / intrinsics.focal_px
    return 2.0 * height_m * half_h, 2.0 * height_m * half_v


def grid_positions(
    region_lo_xy,
    region_hi_xy,
    altitude_m: float,
    spacing_along_m: float,
    spacing_across_m: float,
    direction: str = "x",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boustrophedon grid of camera positions covering a rectangle at a fixed altitude.

    Args:
        region_lo_xy, region_hi_xy: corners (2,) of the region in metres.
        altitude_m: flight height in metres.
        spacing_along_m: distance between consecutive images on a line (m).
        spacing_across_m: distance between lines (m).
        direction: ``x`` or ``y``, the axis the lines run along.

    Returns:
        positions (N, 3) in flight order, heading (N,) in degrees (direction of travel), line index (N,).
    """
    lo = np.asarray(region_lo_xy, dtype=float)
    hi = np.asarray(region_hi_xy, dtype=float)
    if direction not in ("x", "y"):
        raise ValueError(f"lawnmower: flight_direction must be auto, x or y, got {direction!r}")
    along, across = (0, 1) if direction == "x" else (1, 0)
    extent = hi - lo
    centre = 0.5 * (lo + hi)
    n_along = int(math.ceil(extent[along] / spacing_along_m - 1e-9)) + 1
    n_lines = int(math.ceil(extent[across] / spacing_across_m - 1e-9)) + 1
    offsets_along = (np.arange(n_along) - 0.5 * (n_along - 1)) * spacing_along_m
    offsets_across = (np.arange(n_lines) - 0.5 * (n_lines - 1)) * spacing_across_m
    forward_heading = 0.0 if direction == "x" else 90.0
    positions, headings, lines = [], [], []
    for line, off_across in enumerate(offsets_across):
        order = offsets_along if line % 2 == 0 else offsets_along[::-1]
        xy = np.empty((n_along, 2))
        xy[:, along] = centre[along] + order
        xy[:, across] = centre[across] + off_across
        positions.append(np.column_stack([xy, np.full(n_along, float(altitude_m))]))
        headings.append(np.full(n_along, forward_heading if line % 2 == 0 else forward_heading + 180.0))
        lines.append(np.full(n_along, line))
    return np.concatenate(positions), np.concatenate(headings), np.concatenate(lines)


def orbit_ring(
    lo_xy: np.ndarray, hi_xy: np.ndarray, distance_m: float, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing_m`` (at most) along the rectangle ``lo_xy``-``hi_xy`` grown by
    ``distance_m`` (straight sides, quarter circles at the corners), and the inward unit normal at
    each: (N, 2) positions and (N, 2) directions towards the rectangle, counter-clockwise."""
    if not (distance_m > 0 and spacing_m > 0):
        raise ValueError(f"orbit ring: distance ({distance_m}) and spacing ({spacing_m}) must be > 0")
    lo_xy, hi_xy = np.asarray(lo_xy, float), np.asarray(hi_xy, float)
    w, h = hi_xy - lo_xy
    arc = 0.5 * math.pi * distance_m
    # Pieces in order: bottom side, corner (hi x, lo y), right side, corner, top, corner, left, corner.
    lengths = np.array([w, arc, h, arc, w, arc, h, arc])
    total = float(lengths.sum())
    n = max(4, math.ceil(total / spacing_m))
    s = np.arange(n) * (total / n)
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    piece = np.searchsorted(starts, s, side="right") - 1
    t = s - starts[piece]
    corners = np.array(
        [[hi_xy[0], lo_xy[1]], [hi_xy[0], hi_xy[1]], [lo_xy[0], hi_xy[1]], [lo_xy[0], lo_xy[1]]]
    )
    side_start = np.array(
        [[lo_xy[0], lo_xy[1]], [hi_xy[0], lo_xy[1]], [hi_xy[0], hi_xy[1]], [lo_xy[0], hi_xy[1]]]
    )
    side_dir = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    outward = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    positions = np.empty((n, 2))
    inward = np.empty((n, 2))
    k = piece // 2
    straight = piece % 2 == 0
    positions[straight] = (
        side_start[k[straight]]
        + side_dir[k[straight]] * t[straight, None]
        + outward[k[straight]] * distance_m
    )
    inward[straight] = -outward[k[straight]]
    bend = ~straight
    # A corner's arc turns from one side's outward normal to the next one's.
    start_angle = np.arctan2(outward[k[bend], 1], outward[k[bend], 0])
    angle = start_angle + t[bend] / distance_m
    radial = np.column_stack([np.cos(angle), np.sin(angle)])
    positions[bend] = corners[k[bend]] + radial * distance_m
    inward[bend] = -radial
    return positions, inward


def _orbit_views(structure_bounds: Box, intrinsics: Intrinsics, p: dict) -> np.ndarray:
    """(V, 5) viewpoints of ``orbit_rings`` rings around the structure (see ``DEFAULTS``)."""
    rings = int(p["orbit_rings"])
    if rings < 0:
        raise ValueError(f"lawnmower: orbit_rings must be >= 0, got {rings}")
    if rings == 0:
        return np.empty((0, 5))
    distance = float(
        p["orbit_distance_m"] if p["orbit_distance_m"] is not None else p["altitude_above_top_m"]
    )
    if distance <= 0:
        raise ValueError(f"lawnmower: orbit_distance_m must be > 0, got {distance}")
    # Along a ring consecutive images overlap by front_overlap at the footprint's edge.
    width_m = 2.0 * distance * math.tan(math.radians(intrinsics.hfov_deg) / 2.0)
    spacing = (1.0 - _check_overlap("front_overlap", p["front_overlap"])) * width_m
    xy, inward = orbit_ring(structure_bounds.lo_array[:2], structure_bounds.hi_array[:2], distance, spacing)
    lo_z, height = float(structure_bounds.lo[2]), float(structure_bounds.extent[2])
    heights = np.maximum(lo_z + (np.arange(rings) + 0.5) / rings * height, float(p["orbit_min_height_m"]))
    yaw = np.degrees(np.arctan2(inward[:, 1], inward[:, 0]))
    pitch = float(np.clip(p["orbit_pitch_deg"], p["pitch_min_deg"], p["pitch_max_deg"]))
    views = []
    for i, z in enumerate(heights):
        ring = np.column_stack([xy, np.full(len(xy), z), yaw, np.full(len(xy), pitch)])
        views.append(ring if i % 2 == 0 else ring[::-1])  # alternate the direction: short hops between rings
    return np.concatenate(views)


def plan_exploration(
    structure_bounds: Box, intrinsics: Intrinsics, params: Mapping | None, seed: int = 0
) -> Plan:
    """The lawnmower flight over a structure (the exploratory flight that builds the proxy).

    Args:
        structure_bounds: box around the structure (m); the grid covers its footprint plus a margin.
        intrinsics: the survey camera.
        params: see ``DEFAULTS`` (overlaps as fractions, lengths in metres, angles in degrees).
        seed: unused (the flight is deterministic); kept for the planner interface.

    Returns:
        A ``Plan`` with kinds ``nadir`` or ``grid`` (centre-aimed), in boustrophedon order, then the
        ``orbit`` rings when ``orbit_rings`` > 0.
    """
    del seed
    t0 = time.perf_counter()
    p = _merged(params)
    mode = str(p["mode"])
    if mode not in MODES:
        raise ValueError(f"lawnmower: mode must be one of {MODES}, got {mode!r}")
    front = _check_overlap("front_overlap", p["front_overlap"])
    side = _check_overlap("side_overlap", p["side_overlap"])
    top = float(structure_bounds.hi[2])
    min_altitude = top + float(p["min_clearance_above_top_m"])
    if p["altitude_m"] is None:
        above = float(p["altitude_above_top_m"])
        if not above > float(p["min_clearance_above_top_m"]):
            raise ValueError(
                f"lawnmower: altitude_above_top_m = {above} m must exceed "
                f"min_clearance_above_top_m = {p['min_clearance_above_top_m']} m"
            )
        altitude = top + above
    else:
        altitude = float(p["altitude_m"])
        if not altitude > min_altitude:
            raise ValueError(
                f"lawnmower: altitude_m = {altitude} m is below the structure top {top:.2f} m plus "
                f"min_clearance_above_top_m = {p['min_clearance_above_top_m']} m; fly higher"
            )
    across_w, along_l = footprint_m(intrinsics, altitude)
    lo_xy = structure_bounds.lo_array[:2]
    hi_xy = structure_bounds.hi_array[:2]
    extent = hi_xy - lo_xy
    # The images must tile the structure's top: a structure inside one footprint at its top needs
    # no grid (a lower flight or a single image).
    top_w, top_l = footprint_m(intrinsics, altitude - top)
    if extent.max() <= min(top_w, top_l):
        raise PlanningError(
            f"lawnmower: the structure ({extent[0]:.1f} x {extent[1]:.1f} m) fits inside one image "
            f"footprint ({top_w:.1f} x {top_l:.1f} m at its top) at altitude_m = {altitude:.1f} m; "
            "lower altitude_m / altitude_above_top_m"
        )
    margin = (
        float(p["margin_m"])
        if p["margin_m"] is not None
        else float(p["margin_footprints"]) * max(across_w, along_l)
    )
    if margin < 0:
        raise ValueError(f"lawnmower: margin_m must be >= 0, got {margin}")
    region_lo, region_hi = lo_xy - margin, hi_xy + margin
    direction = str(p["flight_direction"])
    if direction == "auto":
        direction = "x" if (region_hi - region_lo)[0] >= (region_hi - region_lo)[1] else "y"
    spacing_along = (1.0 - front) * along_l
    spacing_across = (1.0 - side) * across_w
    positions, headings, lines = grid_positions(
        region_lo, region_hi, altitude, spacing_along, spacing_across, direction
    )
    if mode == "nadir":
        yaw = headings
        pitch = np.full(len(positions), -90.0)
        kinds = ["nadir"] * len(positions)
    else:
        target = structure_bounds.center.copy()
        target[2] = structure_bounds.lo[2] + float(p["aim_height_fraction"]) * structure_bounds.extent[2]
        direction_vec = target - positions
        yaw, pitch = yaw_pitch_from_direction(direction_vec)
        # Directly above the target the yaw is undefined: keep the direction of travel there.
        overhead = np.linalg.norm(direction_vec[:, :2], axis=1) < 1e-6
        yaw = np.where(overhead, headings, yaw)
        pitch = np.clip(pitch, float(p["pitch_min_deg"]), float(p["pitch_max_deg"]))
        kinds = ["grid"] * len(positions)
    viewpoints = np.column_stack([positions, np.mod(yaw + 180.0, 360.0) - 180.0, pitch])
    orbit = _orbit_views(structure_bounds, intrinsics, p)
    viewpoints = np.concatenate([viewpoints, orbit])
    kinds = list(kinds) + ["orbit"] * len(orbit)
    info = {
        "parameters": {**p, "mode": mode, "flight_direction": direction},
        "altitude_m": altitude,
        "footprint_across_m": across_w,
        "footprint_along_m": along_l,
        "spacing_along_m": spacing_along,
        "spacing_across_m": spacing_across,
        "n_lines": int(lines.max()) + 1,
        "n_orbit_views": len(orbit),
        "region_lo_xy": region_lo.tolist(),
        "region_hi_xy": region_hi.tolist(),
        "structure_bounds": structure_bounds.as_dict(),
        "timings_s": {"total": time.perf_counter() - t0},
    }
    return Plan(viewpoints=viewpoints, kinds=kinds, planner="lawnmower", info=info)


def grounded_faces(proxy: trimesh.Trimesh, support_gap_m: float = STRUCTURE_SUPPORT_GAP_M) -> np.ndarray:
    """Indices (F,) of the faces of the proxy's pieces that hang together with its largest piece.

    A reconstructed proxy is one large piece (ground and structure) plus separate pieces: parts of the
    structure that the surface reconstruction split off (a roof tier, a dome's lantern) and floaters,
    blobs that Poisson closed in empty space above the roofs. A piece is kept when one of its vertices
    lies within ``support_gap_m`` of the surface of a kept piece, starting from the largest (by area);
    floaters, metres away from everything, are not.
    """
    faces = np.asarray(proxy.faces)
    vertices = np.asarray(proxy.vertices, dtype=float)
    pieces = trimesh.graph.connected_components(proxy.face_adjacency, nodes=np.arange(len(faces)), min_len=1)
    pieces = sorted(pieces, key=lambda p: -proxy.area_faces[p].sum())
    kept, rest = [pieces[0]], pieces[1:]
    while rest:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(vertices.astype(np.float32)),
            o3d.core.Tensor(faces[np.concatenate(kept)].astype(np.uint32)),
        )
        near = [
            scene.compute_distance(o3d.core.Tensor(vertices[np.unique(faces[p])].astype(np.float32)))
            .numpy()
            .min()
            <= support_gap_m
            for p in rest
        ]
        if not any(near):
            break
        kept += [p for p, n in zip(rest, near, strict=True) if n]
        rest = [p for p, n in zip(rest, near, strict=True) if not n]
    return np.sort(np.concatenate(kept))


def _surface_points(
    mesh: trimesh.Trimesh, cell_m: float, per_cell: int = 4, cap: int = 400_000
) -> np.ndarray:
    """The mesh's vertices and ``per_cell`` points per ``cell_m``-sided square of its area (N, 3), metres."""
    count = int(min(cap, math.ceil(per_cell * mesh.area / cell_m**2)))
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    return np.vstack([np.asarray(mesh.vertices, dtype=float), samples])


def structure_bounds_from_proxy(
    proxy: trimesh.Trimesh, min_height_m: float = 0.5, cell_m: float = STRUCTURE_CELL_M
) -> Box:
    """Box around the proxy's structure: the largest connected raised region of its height map.

    Floaters are dropped first (``grounded_faces``). The rest of the surface, sampled at a few points
    per column, is binned into ``cell_m`` x ``cell_m`` columns (metres); a column is raised when its
    highest point lies more than ``min_height_m`` above the ground z = 0. The structure is the largest
    8-connected group of raised columns, and the box spans the raised points in it (z from the ground
    up). Without these two steps, bumps on a reconstructed ground apron far from the building and
    blobs above its roofs stretch the box, and every grid planned over it, to the apron's edge and the
    blob's height. Falls back to the whole proxy's bounds when nothing is that high (a flat proxy).
    """
    if len(proxy.vertices) == 0 or len(proxy.faces) == 0:
        raise PlanningError("lawnmower: the proxy mesh is empty")
    if not cell_m > 0:
        raise ValueError(f"lawnmower: the structure cell size must be positive, got {cell_m} m")
    points = _surface_points(proxy.submesh([grounded_faces(proxy)], append=True), cell_m)
    raised = points[:, 2] > float(min_height_m)
    if not raised.any():
        box = Box.from_points(np.asarray(proxy.vertices, dtype=float))
    else:
        high = points[raised]
        cells = np.floor((high[:, :2] - high[:, :2].min(axis=0)) / cell_m).astype(np.int64)
        occupied = np.zeros(cells.max(axis=0) + 1, dtype=bool)
        occupied[cells[:, 0], cells[:, 1]] = True
        labels, n_groups = ndimage.label(occupied, structure=np.ones((3, 3), dtype=bool))
        sizes = np.bincount(labels.ravel(), minlength=n_groups + 1)[1:]
        largest = 1 + int(np.argmax(sizes))
        box = Box.from_points(high[labels[cells[:, 0], cells[:, 1]] == largest])
    lo = box.lo_array.copy()
    lo[2] = min(lo[2], 0.0)
    return Box(tuple(lo.tolist()), box.hi)


def plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan:
    """``planner=lawnmower``: the lawnmower flight over the proxy's structure (see ``plan_exploration``)."""
    p = _merged(params)
    bounds = structure_bounds_from_proxy(proxy, float(p["structure_min_height_m"]))
    return plan_exploration(bounds, intrinsics, p, seed)
