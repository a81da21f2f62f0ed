"""Load any textured mesh file (OBJ, GLB/glTF, PLY, DAE, STL, OFF) as a ground-truth ``Scene``.

Frame: the file's up axis (``z`` or ``y``) becomes +z, coordinates are multiplied by the file's
unit (Collada ``<unit meter=...>``; other formats are taken as metres) and by ``scale``, then the
mesh is moved so that its lowest point sits at z = 0 and its footprint is centred on x = y = 0.
A textured ground plane (``ground_margin_m`` beyond the footprint) is added unless disabled, and
faces lying on z = 0 facing down are dropped (they would z-fight with the ground).

Textures referenced by the file are looked up beside it and in the usual asset folders
(``textures/``, ``../materials/textures/`` as in Gazebo models). ``add_detail`` multiplies fine
procedural detail onto the plain textures of low-detail assets (see ``scene.textures.detail_overlay``).
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from scene.base import Box, MeshPart, Scene
from scene.procedural.geometry import Material, Piece, _split_by_uv, _visible_faces, ground_tiles
from scene.textures import cached_texture, detail_overlay, material_seed

SUPPORTED_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".dae", ".stl", ".off")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tga", ".bmp", ".tif", ".tiff", ".gif", ".webp")
# Texture side limit after detail upsampling (MuJoCo uploads every texture to the GPU).
_MAX_DETAIL_SIDE = 4096


class _AssetResolver(trimesh.resolvers.FilePathResolver):
    """File resolver that also searches the usual texture folders and records unusable images."""

    def __init__(self, mesh_path: Path):
        super().__init__(str(mesh_path))
        here = mesh_path.parent
        self.search = [
            here,
            here / "textures",
            here / "materials" / "textures",
            here.parent / "textures",
            here.parent / "materials" / "textures",
        ]
        self.missing: list[str] = []
        self.unreadable: dict[str, str] = {}

    def get(self, name):
        data = None
        try:
            data = super().get(name)
        except (FileNotFoundError, ValueError):
            base = Path(str(name).replace("\\", "/")).name
            for folder in self.search:
                if (folder / base).is_file():
                    data = (folder / base).read_bytes()
                    break
        if data is None:
            self.missing.append(str(name))
            raise FileNotFoundError(name)
        if str(name).lower().endswith(_IMAGE_SUFFIXES):
            try:
                with Image.open(io.BytesIO(data)) as img:
                    img.load()
            except Exception as err:  # PIL raises many types for corrupt files
                self.unreadable[str(name)] = f"{type(err).__name__}: {err}"
        return data


def load_mesh_scene(
    path: str | os.PathLike,
    up_axis: str = "z",
    scale: float = 1.0,
    add_detail: bool = False,
    apron_m: float = 3.0,
    ground: bool = True,
    ground_margin_m: float = 30.0,
    detail_strength: float = 0.3,
    seed: int = 0,
    cache_dir: str | os.PathLike | None = None,
    name: str | None = None,
) -> Scene:
    """Load a mesh file as a Scene in metres, Z up, ground at z = 0.

    Args:
        path: mesh file (OBJ/MTL, GLB/glTF, PLY, DAE, STL, OFF) with texture or vertex colours.
        up_axis: the file's up axis, ``z`` or ``y``.
        scale: extra factor to metres, applied after the file's own unit (Collada ``<unit>``).
        add_detail: multiply fine procedural detail onto the textures (and give untextured
            uniform-colour parts a detailed texture of their colour).
        apron_m: sideways margin of the evaluation region around the structure (metres).
        ground: add a textured ground plane reaching ``ground_margin_m`` beyond the structure.
        detail_strength: relative amplitude of the detail (0.3 = +-30 % brightness at 1 sigma).
        seed: seed of the detail and the ground texture.
        cache_dir: where the ground texture is cached (``cache_dir/textures``), None for no cache.
        name: scene name (default: the file's stem).

    Raises:
        FileNotFoundError: the file or a texture it needs does not exist.
        ValueError: unreadable file, unsupported format, no faces, undecodable texture, bad option.
    """
    started = time.perf_counter()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if not path.is_file() or not os.access(path, os.R_OK):
        raise ValueError(f"mesh file is not a readable file: {path}")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise ValueError(
            f"unsupported mesh format {path.suffix!r} of {path}; supported: {SUPPORTED_SUFFIXES}"
        )
    if up_axis not in ("z", "y"):
        raise ValueError(f"scene.up_axis must be 'z' or 'y', got {up_axis!r}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scene.scale must be a positive number, got {scale!r}")
    if apron_m < 0 or ground_margin_m < apron_m:
        raise ValueError(f"need 0 <= apron_m ({apron_m}) <= ground_margin_m ({ground_margin_m})")

    resolver = _AssetResolver(path)
    try:
        loaded = trimesh.load(str(path), resolver=resolver, process=False)
    except Exception as err:
        raise ValueError(f"cannot read mesh file {path}: {type(err).__name__}: {err}") from err
    geometries = _geometries(loaded)
    geometries = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not geometries:
        raise ValueError(f"mesh file {path} has no faces")

    factor = _unit_to_metres(path) * float(scale)
    transform = np.eye(3) if up_axis == "z" else np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    all_v = np.concatenate([g.vertices for g in geometries]) @ transform.T * factor
    lo, hi = all_v.min(0), all_v.max(0)
    shift = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])

    parts: list[MeshPart] = []
    textures: dict[str, np.ndarray] = {}
    image_keys: dict[str, str] = {}  # image content hash -> texture key (shared images load once)
    color_keys: dict[tuple, str] = {}
    stem = name or path.stem
    n_images = len({_image_hash(_visual(g)[1]) for g in geometries if _visual(g)[1] is not None})
    # Detail upsampling budget: one or a few maps may grow to 4096 px, many maps to 2048 px.
    max_side = _MAX_DETAIL_SIDE if n_images <= 4 else _MAX_DETAIL_SIDE // 2
    for gi, g in enumerate(geometries):
        vertices = np.asarray(g.vertices, float) @ transform.T * factor + shift
        faces = np.asarray(g.faces, np.int64)
        keep = _visible_faces(vertices, faces, [], np.zeros((0, 2, 3)), below_ground=True)
        if not keep.any():
            continue
        faces = faces[keep]
        part_name = f"{stem}_{gi}"
        uv, image, color = _visual(g)
        if uv is not None and image is not None:
            digest = _image_hash(image)
            key = image_keys.get(digest)
            if key is None:
                key = f"{stem}_tex{len(image_keys)}"
                image_keys[digest] = key
                rgb = np.asarray(image.convert("RGB"))
                if add_detail:
                    up = max(1.0, min(4.0, max_side / max(rgb.shape[:2])))
                    rgb = detail_overlay(rgb, material_seed(seed, key), detail_strength, up)
                textures[key] = np.ascontiguousarray(rgb)
            # Faces keep the file's UVs; trimesh already duplicated vertices at UV seams.
            parts.append(MeshPart(part_name, vertices, faces, uv=uv, texture=key))
        elif add_detail and color is not None and color.ndim == 1:
            rgb = tuple(int(c) for c in color[:3])
            key = color_keys.get(rgb)
            if key is None:
                key = f"{stem}_detail{len(color_keys)}"
                color_keys[rgb] = key
                plain = np.broadcast_to(np.asarray(rgb, np.uint8), (1024, 1024, 3))
                textures[key] = detail_overlay(plain, material_seed(seed, key), detail_strength)
            corner_uv = _box_uv(vertices, faces, period_m=1024 * 0.01)
            v, f, u = _split_by_uv(vertices, faces, corner_uv)
            parts.append(MeshPart(part_name, v, f, uv=u, texture=key))
        else:
            colors = None if color is None else np.broadcast_to(color[..., :3], (len(vertices), 3))
            parts.append(MeshPart(part_name, vertices, faces, vertex_colors=colors))
    if not parts:
        raise ValueError(f"mesh file {path} has no faces above the ground")
    problems = _texture_problems(resolver, geometries)
    if problems:
        raise problems[0]

    structure = Box.from_points(np.concatenate([p.vertices for p in parts]))
    info = {
        "source": str(path),
        "unit_to_m": _unit_to_metres(path),
        "unit_name": _collada_unit_name(path) if path.suffix.lower() == ".dae" else None,
        "scale": float(scale),
        "up_axis": up_axis,
        "add_detail": bool(add_detail),
        "n_faces_structure": int(sum(len(p.faces) for p in parts)),
        "extent_m": [float(v) for v in structure.extent],
    }
    if ground:
        mat = Material("ground", "ground_dry", 0.025, 2048)
        tiles = ground_tiles(
            structure.lo_array[:2] - ground_margin_m,
            structure.hi_array[:2] + ground_margin_m,
            "ground",
            tile_m=mat.texel_m * mat.size,
            cell_m=4.0,
        )
        info["ground_parts"] = [tile.material for tile in tiles]
        for tile in tiles:  # one texture per tile (own seed), so no patch of ground repeats
            parts.append(_ground_part(tile, mat, seed))
            textures[tile.material] = cached_texture(
                stem, tile.material, mat.preset, mat.size, material_seed(seed, tile.material), cache_dir
            )
    evaluation = Box(
        (structure.lo[0] - apron_m, structure.lo[1] - apron_m, -0.5),
        (structure.hi[0] + apron_m, structure.hi[1] + apron_m, structure.hi[2] + 1.0),
    )
    info["n_faces"] = int(sum(len(p.faces) for p in parts))
    info["texture_bytes"] = int(sum(t.nbytes for t in textures.values()))
    info["build_seconds"] = round(time.perf_counter() - started, 3)
    return Scene(stem, parts, textures, structure, evaluation, seed=None, info=info)


def _image_hash(image) -> str:
    """Content hash of a PIL image (two parts using the same picture share one texture)."""
    return hashlib.sha1(image.tobytes() + repr((image.size, image.mode)).encode()).hexdigest()


def _geometries(loaded) -> list:
    if isinstance(loaded, trimesh.Scene):
        return list(loaded.dump(concatenate=False))
    return [loaded]


def _visual(g: trimesh.Trimesh):
    """(uv (N, 2) or None, PIL image or None, colour: (4,) uniform / (N, 4) per vertex / None)."""
    visual = g.visual
    if visual is None:
        return None, None, None
    if visual.kind == "texture":
        material = visual.material
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
        uv = None if visual.uv is None else np.asarray(visual.uv, np.float32)
        if uv is not None and len(uv) == len(g.vertices) and image is not None:
            return uv, image, None
        main = getattr(material, "main_color", None)
        return None, None, None if main is None else np.asarray(main, np.uint8)
    if visual.kind in ("vertex", "face"):
        colors = np.asarray(visual.vertex_colors, np.uint8)
        if len(colors) == len(g.vertices):
            if np.all(colors == colors[0]):
                return None, None, colors[0]
            return None, None, colors
    return None, None, None


def _texture_problems(resolver: _AssetResolver, geometries) -> list[Exception]:
    """Errors for textures the mesh needs but could not get (undecodable or missing diffuse maps)."""
    source = resolver.search[0]
    problems: list[Exception] = []
    for name, err in resolver.unreadable.items():
        problems.append(
            ValueError(f"texture {name!r} referenced by the mesh in {source} cannot be read: {err}")
        )
    needs_texture = any(
        g.visual is not None
        and g.visual.kind == "texture"
        and g.visual.uv is not None
        and (
            getattr(g.visual.material, "baseColorTexture", None) or getattr(g.visual.material, "image", None)
        )
        is None
        for g in geometries
    )
    if needs_texture and resolver.missing:
        problems.append(
            FileNotFoundError(
                f"texture(s) {resolver.missing} referenced by the mesh in {source} not found (searched "
                f"{[str(p) for p in resolver.search]})"
            )
        )
    return problems


def _unit_to_metres(path: Path) -> float:
    """Metres per file unit: Collada ``<asset><unit meter=...>``, 1 for every other format."""
    if path.suffix.lower() != ".dae":
        return 1.0
    try:
        for _, elem in ET.iterparse(str(path), events=("end",)):
            tag = elem.tag.rsplit("}", 1)[-1]
            if tag == "unit":
                return float(elem.attrib.get("meter", 1.0))
            if tag in ("library_geometries", "library_visual_scenes"):
                break
    except (ET.ParseError, ValueError) as err:
        raise ValueError(f"cannot read the Collada header of {path}: {err}") from err
    return 1.0


def _box_uv(vertices, faces, period_m: float) -> np.ndarray:
    """(F, 3, 2) box-projected UVs (1 unit = ``period_m`` metres) for untextured parts."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(n), axis=1)
    uv = np.empty(tri.shape[:2] + (2,))
    for a, (i, j) in enumerate(((1, 2), (0, 2), (0, 1))):
        m = axis == a
        uv[m, :, 0], uv[m, :, 1] = tri[m][..., i], tri[m][..., j]
    return uv / period_m


def _ground_part(tile: Piece, mat: Material, seed: int) -> MeshPart:
    """The MeshPart of one ground tile, reading its own texture (``tile.material``) from a random offset."""
    rng = np.random.default_rng([seed, 7])
    corner_uv = tile.vertices[tile.faces][..., :2] / (mat.texel_m * mat.size) + rng.random(2)
    vertices, faces, uv = _split_by_uv(tile.vertices, tile.faces.astype(np.int64), corner_uv)
    return MeshPart(tile.material, vertices, faces, uv=uv, texture=tile.material)


def _collada_unit_name(path: Path) -> str | None:
    """The Collada unit's name (for the record), e.g. ``inch``."""
    text = path.read_text(errors="ignore")[:4096]
    match = re.search(r"<unit[^>]*name=\"([^\"]+)\"", text)
    return match.group(1) if match else None
