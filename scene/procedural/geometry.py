"""Boolean-free composition of convex solids into textured, render-ready mesh parts.

A scene is a list of :class:`Piece` s: closed solids (boxes, lofted prisms and frusta, surfaces of
revolution) in a local frame, placed by a rotation about z and a translation. :class:`Builder`
turns them into one :class:`~scene.base.MeshPart` per material:

1. every piece is subdivided so no edge is longer than ``max_edge_m`` (finer hidden-face culling),
2. faces hidden inside another convex piece or below the ground (z < 0) are dropped, so the ground
   truth keeps only surfaces a camera could see (no caps buried in walls, no ground under
   buildings),
3. UVs in metres / texel size come from a projection in the piece's local frame (box, per-plane or
   cylindrical), with a random offset per piece and projection group so that no two surfaces read
   the same patch of the (periodic) texture; vertices are duplicated where UVs differ (MuJoCo needs
   per-vertex texture coordinates).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh

from scene.base import MeshPart

MAPPINGS = ("box", "planar", "cyl")


@dataclass
class Piece:
    """One closed solid of a scene, in a local frame (metres).

    Attributes:
        vertices: (N, 3) local coordinates.
        faces: (M, 3) vertex indices, counter-clockwise seen from outside.
        material: texture key of the scene.
        mapping: UV projection: ``box`` (dominant local axis), ``planar`` (one plane per distinct
            face normal: roofs, slanted faces) or ``cyl`` (around the local z axis: columns, drums).
        convex: whether the solid is convex, so it may hide faces of other pieces inside it.
        rotation_z: rotation of the local frame about world z (radians).
        translation: (3,) position of the local origin in world metres.
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: str
    mapping: str = "box"
    convex: bool = True
    rotation_z: float = 0.0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def placed(self, rotation_z: float = 0.0, translation=(0.0, 0.0, 0.0)) -> Piece:
        """A copy moved by a further rotation about world z then a translation (metres)."""
        c, s = np.cos(rotation_z), np.sin(rotation_z)
        t = np.asarray(self.translation, float)
        t = np.array([c * t[0] - s * t[1], s * t[0] + c * t[1], t[2]]) + np.asarray(translation, float)
        return Piece(
            self.vertices,
            self.faces,
            self.material,
            self.mapping,
            self.convex,
            self.rotation_z + rotation_z,
            t,
        )

    def world_vertices(self, local: np.ndarray | None = None) -> np.ndarray:
        """Local vertices (default: this piece's) in world metres."""
        v = self.vertices if local is None else local
        c, s = np.cos(self.rotation_z), np.sin(self.rotation_z)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return v @ rot.T + np.asarray(self.translation, float)


def place(pieces: Sequence[Piece], rotation_z: float = 0.0, translation=(0.0, 0.0, 0.0)) -> list[Piece]:
    """Move a group of pieces together (rotation about z in radians, then translation in metres)."""
    return [p.placed(rotation_z, translation) for p in pieces]


# ---------------------------------------------------------------------------------- primitives


def box(lo, hi, material: str, mapping: str = "box") -> Piece:
    """Axis-aligned box from ``lo`` to ``hi`` (local metres)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if np.any(hi - lo <= 0):
        raise ValueError(f"degenerate box lo={lo} hi={hi}")
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    vertices = lo + corners * (hi - lo)
    faces = np.array(
        [
            [0, 2, 1], [1, 2, 3],  # bottom (-z)
            [4, 5, 6], [5, 7, 6],  # top (+z)
            [0, 1, 4], [1, 5, 4],  # -y
            [2, 6, 3], [3, 6, 7],  # +y
            [0, 4, 2], [2, 4, 6],  # -x
            [1, 3, 5], [3, 7, 5],  # +x
        ]
    )  # fmt: skip
    return Piece(vertices, faces, material, mapping)


def loft(
    rings: Sequence[tuple[np.ndarray, float]], material: str, mapping: str = "planar", convex=True
) -> Piece:
    """A closed solid through horizontal rings [(polygon (K, 2) counter-clockwise, z), ...].

    All rings have the same K vertices; consecutive rings are joined by quads, the first and last
    rings are capped by fans. Rings may collapse to a point or a segment (roof ridges, apexes):
    degenerate triangles are dropped.
    """
    polys = [np.asarray(p, float) for p, _ in rings]
    k = len(polys[0])
    if any(len(p) != k for p in polys) or len(polys) < 2:
        raise ValueError("loft needs at least two rings with the same vertex count")
    vertices = np.concatenate(
        [np.column_stack([p, np.full(k, z)]) for p, (_, z) in zip(polys, rings, strict=True)]
    )
    faces = []
    i = np.arange(k)
    j = (i + 1) % k
    for r in range(len(polys) - 1):
        a, b = r * k + i, r * k + j
        c, d = (r + 1) * k + j, (r + 1) * k + i
        faces.append(np.column_stack([a, b, c]))
        faces.append(np.column_stack([a, c, d]))
    bottom = np.column_stack([np.zeros(k - 2, int), np.arange(2, k), np.arange(1, k - 1)])
    top_base = (len(polys) - 1) * k
    top = np.column_stack(
        [np.full(k - 2, top_base), top_base + np.arange(1, k - 1), top_base + np.arange(2, k)]
    )
    faces = np.concatenate(faces + [bottom, top])
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return Piece(vertices, faces[area > 1e-9], material, mapping, convex)


def regular_polygon(radius: float, n: int, phase: float = 0.0) -> np.ndarray:
    """(n, 2) counter-clockwise regular polygon of circumradius ``radius`` metres."""
    a = phase + 2 * np.pi * np.arange(n) / n
    return radius * np.column_stack([np.cos(a), np.sin(a)])


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """(4, 2) counter-clockwise rectangle."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def cylinder(
    radius: float, z0: float, z1: float, material: str, n: int = 24, radius_top: float | None = None
) -> Piece:
    """Vertical cylinder or cone frustum about the local z axis (cylindrical UVs)."""
    rt = radius if radius_top is None else radius_top
    return loft(
        [(regular_polygon(radius, n), z0), (regular_polygon(max(rt, 0.0), n), z1)], material, mapping="cyl"
    )


def revolve(profile: Sequence[tuple[float, float]], material: str, n: int = 32, convex: bool = True) -> Piece:
    """Surface of revolution about local z from a (radius, z) profile, bottom to top (domes, bulbs).

    The last radius may be 0 (apex). Box UV projection keeps texel size uniform on a dome.
    """
    rings = [(regular_polygon(max(r, 0.0), n), z) for r, z in profile]
    return loft(rings, material, mapping="box", convex=convex)


def dome_profile(radius: float, z0: float, height: float | None = None, steps: int = 10) -> list:
    """(radius, z) profile of a half-ellipsoid dome of base ``radius`` rising ``height`` (default radius)."""
    h = radius if height is None else height
    t = np.linspace(0, np.pi / 2, steps + 1)
    return [(radius * np.cos(a), z0 + h * np.sin(a)) for a in t]


def onion_profile(radius: float, z0: float, height: float, steps: int = 14) -> list:
    """(radius, z) profile of an onion dome: bulges to 1.15 r, then tapers to a point."""
    s = np.linspace(0, 1, steps + 1)
    r = radius * (1.0 + 0.45 * np.sin(np.pi * np.minimum(s / 0.6, 1.0)) * (s < 0.6))
    r = np.where(s >= 0.35, radius * 1.15 * np.cos(np.pi / 2 * (s - 0.35) / 0.65) ** 1.3, r)
    return [(float(ri), z0 + height * si) for ri, si in zip(r, s, strict=True)]


def hip_roof(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    z_eave: float,
    height: float,
    material: str,
    fascia: float = 0.25,
    ridge_fraction: float = 0.4,
    top_rect: np.ndarray | None = None,
) -> Piece:
    """Hipped roof solid: a vertical fascia band of ``fascia`` m at the eave, then slopes to a ridge.

    The ridge runs along the longer side and is ``ridge_fraction`` of it (0: pyramid); or the slopes
    end at ``top_rect`` (a lower tier's roof meeting an upper storey). Its underside (soffit) faces
    down: overhangs wherever the roof is wider than the walls below.
    """
    outer = rect(x0, y0, x1, y1)
    if top_rect is None:
        cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        if (x1 - x0) >= (y1 - y0):
            half = 0.5 * ridge_fraction * (x1 - x0)
            top = rect(cx - half, cy - 1e-3, cx + half, cy + 1e-3)
        else:
            half = 0.5 * ridge_fraction * (y1 - y0)
            top = rect(cx - 1e-3, cy - half, cx + 1e-3, cy + half)
    else:
        top = np.asarray(top_rect, float)
    return loft([(outer, z_eave), (outer, z_eave + fascia), (top, z_eave + fascia + height)], material)


def gable_roof(
    length: float, width: float, z_eave: float, height: float, material: str, fascia: float = 0.2
) -> Piece:
    """Gable roof solid along local x from -length/2..length/2, width across y, ridge at the centre."""
    hl, hw = 0.5 * length, 0.5 * width
    # Profile in the (y, z) plane, extruded along x: a pentagon (fascia band + triangle).
    profile = np.array([[-hw, z_eave], [hw, z_eave], [hw, z_eave + fascia], [0.0, z_eave + fascia + height],
                        [-hw, z_eave + fascia]])  # fmt: skip
    k = len(profile)
    vertices = np.concatenate(
        [np.column_stack([np.full(k, -hl), profile]), np.column_stack([np.full(k, hl), profile])]
    )
    i = np.arange(k)
    j = (i + 1) % k
    # Profile is CCW in (y, z) seen from +x; the +x cap uses it as is, the -x cap reversed.
    sides = np.concatenate([np.column_stack([i, i + k, j + k]), np.column_stack([i, j + k, j])])
    cap_pos = np.column_stack([np.full(k - 2, k), k + np.arange(1, k - 1), k + np.arange(2, k)])
    cap_neg = np.column_stack([np.zeros(k - 2, int), np.arange(2, k), np.arange(1, k - 1)])
    faces = np.concatenate([sides, cap_pos, cap_neg])
    return _orient_outward(Piece(vertices, faces, material, "planar"))


def arched_wall(
    length: float,
    height: float,
    thickness: float,
    openings: Sequence[dict],
    material: str,
    back_material: str | None = None,
    arch_segments: int = 8,
) -> list[Piece]:
    """A straight wall with arched or square-headed recesses, as convex pieces (no booleans).

    Local frame: the wall runs along x from 0 to ``length``, its outer face is the plane y = 0
    (facing -y), its inner face y = ``thickness``; z from 0 to ``height``. Each opening is a dict
    with ``x`` (left edge), ``width``, ``sill`` (bottom, m above the wall base), ``spring`` (top of
    the straight jambs), ``arch`` (bool: semicircular head) and ``depth`` (recess depth, < thickness).
    Openings with the same ``x`` and ``width`` stack in one column (portal below, window above);
    columns must not overlap. The recess back is ``back_material`` (dark wood for doors; default the
    wall's). Pieces are split at each recess plane so that every face is either seen or hidden.
    """
    back_material = back_material or material
    columns: dict[tuple[float, float], list[dict]] = {}
    for o in openings:
        columns.setdefault((round(float(o["x"]), 6), round(float(o["width"]), 6)), []).append(o)
    pieces: list[Piece] = []
    x_prev = 0.0
    for (x0, w), stack in sorted(columns.items()):
        x1 = x0 + w
        if x0 < x_prev - 1e-9 or x1 > length + 1e-9:
            raise ValueError(f"opening at x={x0} width={w} overlaps another or leaves a {length} m wall")
        if x0 > x_prev + 1e-6:
            pieces.append(box((x_prev, 0, 0), (x0, thickness, height), material))
        z_prev, depth_prev = 0.0, None
        for o in sorted(stack, key=lambda o: float(o.get("sill", 0.0))):
            sill, spring, depth = float(o.get("sill", 0.0)), float(o["spring"]), float(o["depth"])
            arch = bool(o.get("arch", True))
            top = spring + (0.5 * w if arch else 0.0)
            if sill < z_prev - 1e-9 or top > height + 1e-9 or spring <= sill or not 0 < depth < thickness:
                raise ValueError(f"opening {o} does not fit a wall {length} x {height} x {thickness} m")
            pieces += _slab(x0, x1, z_prev, sill, thickness, (depth_prev, depth), material)
            panel = min(depth + 0.05, thickness)
            pieces.append(box((x0, depth, sill), (x1, panel, top), back_material))
            if thickness - panel > 1e-6:
                pieces.append(box((x0, panel, sill), (x1, thickness, top), material))
            if arch:
                pieces += _spandrels(x0, x1, spring, top, depth, material, arch_segments)
            z_prev, depth_prev = top, depth
        pieces += _slab(x0, x1, z_prev, height, thickness, (depth_prev, None), material)
        x_prev = x1
    if length - x_prev > 1e-6:
        pieces.append(box((x_prev, 0, 0), (length, thickness, height), material))
    return pieces


def _slab(x0, x1, z0, z1, thickness, depths, material) -> list[Piece]:
    """Solid wall between two recesses, split at their depth planes (faces fully seen or hidden)."""
    if z1 - z0 <= 1e-6:
        return []
    cuts = sorted({0.0, thickness} | {d for d in depths if d is not None and 0 < d < thickness})
    return [box((x0, a, z0), (x1, b, z1), material) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


def _spandrels(x0, x1, spring, top, depth, material, segments) -> list[Piece]:
    """Convex strips between a semicircular arch and its top line, from the face to the recess depth."""
    xc, r = 0.5 * (x0 + x1), 0.5 * (x1 - x0)
    angles = np.linspace(np.pi, 0.0, segments + 1)
    ax, az = xc + r * np.cos(angles), spring + r * np.sin(angles)
    out = []
    for a in range(segments):
        quad = [(ax[a], az[a]), (ax[a + 1], az[a + 1]), (ax[a + 1], top), (ax[a], top)]
        out.append(_prism_xz(quad, 0.0, depth, material))
    return out


def _prism_xz(polygon_xz, y0: float, y1: float, material: str) -> Piece:
    """Convex polygon in the (x, z) plane (counter-clockwise seen from -y) extruded from y0 to y1."""
    p = np.asarray(polygon_xz, float)
    # Drop repeated points (an arc segment touching the top line).
    keep = np.ones(len(p), bool)
    for i in range(len(p)):
        if np.linalg.norm(p[i] - p[i - 1]) < 1e-9:
            keep[i] = False
    p = p[keep]
    k = len(p)
    front = np.column_stack([p[:, 0], np.full(k, y0), p[:, 1]])
    back = np.column_stack([p[:, 0], np.full(k, y1), p[:, 1]])
    vertices = np.concatenate([front, back])
    # Orientation: seen from -y, (x right, z up) is CCW => the front face normal is -y with (0, i, i+1).
    fan_front = np.column_stack([np.zeros(k - 2, int), np.arange(1, k - 1), np.arange(2, k)])
    fan_back = np.column_stack([np.full(k - 2, k), k + np.arange(2, k), k + np.arange(1, k - 1)])
    i = np.arange(k)
    j = (i + 1) % k
    sides = np.concatenate([np.column_stack([i, j + k, j]), np.column_stack([i, i + k, j + k])])
    faces = np.concatenate([fan_front, fan_back, sides])
    piece = Piece(vertices, faces, material, "box")
    return _orient_outward(piece)


def _orient_outward(piece: Piece) -> Piece:
    """Flip faces of a convex piece whose normal points towards its centroid."""
    v, f = piece.vertices, piece.faces
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", n, tri.mean(1) - v.mean(0)) < 0
    f = f.copy()
    f[inward] = f[inward][:, ::-1]
    piece.faces = f
    return piece


# ------------------------------------------------------------------------------------- builder


@dataclass
class Material:
    """A texture slot: key, texture preset name, texel size in metres and image side in texels."""

    key: str
    preset: str
    texel_m: float
    size: int


class Builder:
    """Collects pieces, then culls hidden faces, maps UVs and merges them into one part per material."""

    def __init__(self, materials: Sequence[Material], seed: int, max_edge_m: float = 1.0):
        self.materials = {m.key: m for m in materials}
        self.seed = int(seed)
        self.max_edge_m = float(max_edge_m)
        self.pieces: list[Piece] = []

    def add(self, pieces: Piece | Sequence[Piece]) -> None:
        """Add one piece or a list of pieces (world placement already applied)."""
        for p in [pieces] if isinstance(pieces, Piece) else pieces:
            if p.material not in self.materials:
                raise ValueError(
                    f"piece uses unknown material {p.material!r}; known: {sorted(self.materials)}"
                )
            if p.mapping not in MAPPINGS:
                raise ValueError(f"unknown UV mapping {p.mapping!r}; known: {MAPPINGS}")
            self.pieces.append(p)

    def build(self, ground: Sequence[Piece] = ()) -> list[MeshPart]:
        """Mesh parts (structure per material, then ground parts), hidden faces removed.

        ``ground`` pieces (flat tiles at z = 0) are culled against the structure like any face but
        are never occluders and never below-ground culled.
        """
        rng = np.random.default_rng(self.seed)
        occluders = [_halfspaces(p) for p in self.pieces if p.convex]
        occ_boxes = np.array([o[2] for o in occluders]) if occluders else np.zeros((0, 2, 3))
        all_pieces = [(p, False) for p in self.pieces] + [(p, True) for p in ground]
        local, world, faces, face_piece, below = [], [], [], [], []
        n_vertices = 0
        for index, (piece, is_ground) in enumerate(all_pieces):
            local_v, f = trimesh.remesh.subdivide_to_size(piece.vertices, piece.faces, self.max_edge_m, 12)
            local.append(local_v)
            world.append(piece.world_vertices(local_v))
            faces.append(f + n_vertices)
            face_piece.append(np.full(len(f), index))
            below.append(np.full(len(f), not is_ground))
            n_vertices += len(local_v)
        local_v, world_v = np.concatenate(local), np.concatenate(world)
        faces, face_piece = np.concatenate(faces), np.concatenate(face_piece)
        keep = _visible_faces(world_v, faces, occluders, occ_boxes, below_ground=np.concatenate(below))
        faces, face_piece = faces[keep], face_piece[keep]
        # Pieces in order, each with its own UV projection and random offsets.
        order = np.argsort(face_piece, kind="stable")
        faces, face_piece = faces[order], face_piece[order]
        bounds = np.searchsorted(face_piece, np.arange(len(all_pieces) + 1))
        corner_uv = np.empty(faces.shape + (2,))
        for index, (piece, _) in enumerate(all_pieces):
            a, b = bounds[index], bounds[index + 1]
            if b > a:
                mat = self.materials[piece.material]
                period = mat.texel_m * mat.size
                corner_uv[a:b] = _corner_uv(local_v, faces[a:b], piece.mapping, period, rng, index)
        material_of_piece = np.array([p.material for p, _ in all_pieces])
        face_material = material_of_piece[face_piece]
        parts = []
        for key in dict.fromkeys(material_of_piece[face_piece]):
            sel = face_material == key
            v, f, uv = _split_by_uv(world_v, faces[sel], corner_uv[sel])
            parts.append(MeshPart(name=str(key), vertices=v, faces=f, uv=uv, texture=str(key)))
        return parts


def ground_tile_material(material: str, index: int) -> str:
    """Texture key of ground tile ``index``: ``material`` for the first, ``material_<index>`` after."""
    return material if index == 0 else f"{material}_{index}"


def ground_tiles(lo_xy, hi_xy, material: str, tile_m: float, cell_m: float) -> list[Piece]:
    """Flat ground at z = 0 over [lo, hi] (metres), as tiles of at most ``tile_m`` side.

    Tile k has its own texture key (``ground_tile_material(material, k)``): the caller gives every
    key its own texture, of one period ``tile_m`` or more, so no patch of ground repeats anywhere.
    (Tiles reading one shared texture repeat it, shifted, once per tile: structure-from-motion then
    registers views of bare ground a whole tile shift away.) Faces are at most ``cell_m`` long so
    that ground hidden under the structure can be culled.
    """
    lo, hi = np.asarray(lo_xy, float), np.asarray(hi_xy, float)
    nx, ny = (int(np.ceil((hi[i] - lo[i]) / tile_m)) for i in range(2))
    xs, ys = np.linspace(lo[0], hi[0], nx + 1), np.linspace(lo[1], hi[1], ny + 1)
    tiles = []
    for i in range(nx):
        for j in range(ny):
            mx = max(1, int(np.ceil((xs[i + 1] - xs[i]) / cell_m)))
            my = max(1, int(np.ceil((ys[j + 1] - ys[j]) / cell_m)))
            gx, gy = np.meshgrid(np.linspace(xs[i], xs[i + 1], mx + 1), np.linspace(ys[j], ys[j + 1], my + 1))
            vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
            a = (np.arange(my)[:, None] * (mx + 1) + np.arange(mx)[None, :]).ravel()
            faces = np.concatenate(
                [np.column_stack([a, a + 1, a + mx + 2]), np.column_stack([a, a + mx + 2, a + mx + 1])]
            )
            key = ground_tile_material(material, len(tiles))
            tiles.append(Piece(vertices, faces, key, "box", convex=False))
    return tiles


def _halfspaces(piece: Piece) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(normals (K, 3), offsets (K,), aabb (2, 3)) of a convex piece in world coordinates."""
    v = piece.world_vertices()
    tri = v[piece.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n = n[ok] / norm[ok, None]
    d = np.einsum("ij,ij->i", n, tri[ok, 0])
    plane = np.unique(np.round(np.column_stack([n, d]), 6), axis=0)
    return plane[:, :3], plane[:, 3], np.stack([v.min(0), v.max(0)])


def _visible_faces(vertices, faces, occluders, occ_boxes, below_ground, eps: float = 2e-3) -> np.ndarray:
    """Mask of faces not hidden: a face is hidden when its centroid and three points near its corners,
    each pushed ``eps`` m outwards, all lie inside convex occluders (or below z = 0). Faces only
    partly covered are kept, so the rendering never shows a hole."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    n = n / np.maximum(area2, 1e-12)[:, None]
    centroid = tri.mean(1, keepdims=True)
    probes = np.concatenate([centroid, 0.9 * tri + 0.1 * centroid], axis=1) + eps * n[:, None, :]
    probes = probes.reshape(-1, 3)
    hidden = np.zeros(len(probes), bool)
    below = np.broadcast_to(np.asarray(below_ground, bool), (len(faces),))
    hidden |= np.repeat(below, 4) & (probes[:, 2] <= 0.0)
    if len(occ_boxes):
        lo, hi = probes.min(0), probes.max(0)
        near = np.all((occ_boxes[:, 0] <= hi) & (occ_boxes[:, 1] >= lo), axis=1)
        # Bin probes on a 2 m grid in xy, sorted by cell, so each occluder reads only its cells.
        cell = 2.0
        ij = np.floor((probes[:, :2] - lo[:2]) / cell).astype(np.int64)
        ny = int(ij[:, 1].max()) + 1
        key = ij[:, 0] * ny + ij[:, 1]
        order = np.argsort(key, kind="stable")
        sorted_key = key[order]
        for k in np.flatnonzero(near):
            normals, offsets, aabb = occluders[k]
            c0 = np.floor((aabb[0, :2] - lo[:2]) / cell).astype(np.int64)
            c1 = np.floor((aabb[1, :2] - lo[:2]) / cell).astype(np.int64)
            c0, c1 = np.maximum(c0, 0), np.minimum(c1, [int(ij[:, 0].max()), ny - 1])
            rows = np.arange(c0[0], c1[0] + 1) * ny
            starts = np.searchsorted(sorted_key, rows + c0[1], side="left")
            ends = np.searchsorted(sorted_key, rows + c1[1], side="right")
            if len(starts) == 1:
                cand = order[starts[0] : ends[0]]
            else:
                cand = np.concatenate([order[a:b] for a, b in zip(starts, ends, strict=True)])
            cand = cand[~hidden[cand]]
            if len(cand) == 0:
                continue
            pc = probes[cand]
            cand = cand[np.all((pc >= aabb[0]) & (pc <= aabb[1]), axis=1)]
            if len(cand) == 0:
                continue
            inside = np.all(probes[cand] @ normals.T - offsets < 0.0, axis=1)
            hidden[cand[inside]] = True
    return (area2 > 1e-10) & ~hidden.reshape(-1, 4).all(axis=1)


def _corner_uv(local_v, faces, mapping: str, period_m: float, rng, index: int) -> np.ndarray:
    """(F, 3, 2) texture coordinates of each face corner; 1 UV unit = one texture period (metres)."""
    tri = local_v[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    x, y, z = tri[..., 0], tri[..., 1], tri[..., 2]
    uv = np.empty(tri.shape[:2] + (2,))
    # Box projection (horizontal courses on vertical faces; u runs left-to-right seen from outside).
    axis = np.argmax(np.abs(n), axis=1)
    sign = np.where(n[np.arange(len(n)), axis] >= 0, 1.0, -1.0)[:, None]
    group = axis * 2 + (sign[:, 0] > 0)
    ax, ay, az = axis == 0, axis == 1, axis == 2
    uv[ax, :, 0], uv[ax, :, 1] = sign[ax] * y[ax], z[ax]
    uv[ay, :, 0], uv[ay, :, 1] = -sign[ay] * x[ay], z[ay]
    uv[az, :, 0], uv[az, :, 1] = x[az], sign[az] * y[az]
    if mapping == "planar":
        # One frame per face plane: u along the horizontal (eave) direction, v up the slope.
        t = np.cross(np.array([0.0, 0.0, 1.0]), n)
        tn = np.linalg.norm(t, axis=1)
        flat = tn < 1e-3
        t[flat] = np.array([1.0, 0.0, 0.0]) * np.where(n[flat, 2:3] >= 0, 1.0, -1.0)
        t /= np.maximum(np.linalg.norm(t, axis=1), 1e-12)[:, None]
        b = np.cross(n, t)
        uv[..., 0] = np.einsum("fkc,fc->fk", tri, t)
        uv[..., 1] = np.einsum("fkc,fc->fk", tri, b)
        _, group = np.unique(np.round(np.column_stack([n, np.einsum("fc,fc->f", n, tri[:, 0])]), 3), axis=0,
                             return_inverse=True)  # fmt: skip
        group = group.ravel() + 6
    elif mapping == "cyl":
        side = np.abs(n[:, 2]) < 0.7
        theta = np.arctan2(y, x)
        center = np.arctan2(y.mean(1), x.mean(1))[:, None]
        theta = center + (theta - center + np.pi) % (2 * np.pi) - np.pi
        radius = np.sqrt(x**2 + y**2).max()
        uv[side, :, 0] = theta[side] * radius
        uv[side, :, 1] = z[side]
        group = np.where(side, 6, group)
    # Random offset per projection group, in texture periods, drawn per piece.
    local_rng = np.random.default_rng([int(rng.integers(2**31)), index])
    n_groups = int(group.max()) + 1
    offsets = local_rng.random((n_groups, 2)) * period_m
    uv = (uv + offsets[group][:, None, :]) / period_m
    return uv.astype(np.float64)


def _split_by_uv(world_v, faces, corner_uv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices shared by faces only where position and UV agree (duplicated at UV seams)."""
    corner_vid = faces.ravel()
    uvq = np.round(corner_uv.reshape(-1, 2) * 2**22).astype(np.int64)
    key = np.column_stack([corner_vid.astype(np.int64), uvq])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    vertices = world_v[corner_vid[first]]
    uv = corner_uv.reshape(-1, 2)[first]
    # Keep UVs small (float32 precision): shift each part so its minimum sits in [0, 1).
    uv -= np.floor(uv.min(0))
    return vertices, inverse.reshape(-1, 3).astype(np.int32), uv.astype(np.float32)
