"""Load any textured mesh file (OBJ, GLB/glTF, PLY, DAE, STL, OFF) as a ground-truth ``Scene``.

Frame: the file's up axis (``z`` or ``y``) becomes +z, coordinates are multiplied by the file's
unit (Collada ``<unit meter=...>``; other formats are taken as metres) and by ``scale``, then the
mesh is moved so that the ground (``ground_height``: the lowest point, the height under most of the
footprint, or a given height) sits at z = 0 and its footprint is centred on x = y = 0. A textured
ground plane (``ground_margin_m`` beyond the footprint) is added unless disabled, faces below it or
lying on it facing down are dropped, and parts that would float a little above it get a plinth
(``scene.ground.floating_pads``).

Textures referenced by the file are looked up beside it and in the usual asset folders
(``textures/``, ``../materials/textures/`` as in Gazebo models). Parts without a texture (uniform
grey or one flat colour) get a photo-like material by surface class (``scene.mesh_materials``);
``add_detail`` multiplies fine procedural detail onto maps coarser than ``detail_above_texel_m`` or
too plain for SIFT (``auto``), onto every map (``true``) or none (``false``). Models of unknown
units (over 2 km or under 1 m across), with NaN vertices or with inward-facing closed parts are
refused with the option that fixes them.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import re
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np
import trimesh
from PIL import Image

from scene.base import Box, MeshPart, Scene
from scene.ground import floating_pads, footprint_ground_height
from scene.mesh_materials import class_textures, map_texel_m, material_parts
from scene.procedural.geometry import Material, Piece, _split_by_uv, _visible_faces, ground_tiles
from scene.textures import cached_texture, detail_overlay, material_seed

log = logging.getLogger(__name__)

# A map whose median absolute Laplacian (grey levels) is below this is too plain for SIFT whatever
# its resolution, and gets detail in ``add_detail: auto`` (the procedural materials: 32-41; the
# shared game assets' maps: 3-17).
PLAIN_MAP_LAPLACIAN = 20.0
# A model outside this size (m, largest side) is in units other than the ones assumed.
SIZE_RANGE_M = (1.0, 2000.0)
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


@dataclass(frozen=True)
class MeshSceneSpec:
    """How a mesh file becomes a ``Scene`` (``conf/scene/mesh.yaml`` lists these, beside ``path``).

    Attributes:
        up_axis: the file's up axis, ``z`` or ``y``.
        scale: extra factor to metres, applied after the file's own unit (Collada ``<unit>``).
        add_detail: ``auto`` (fine procedural detail on maps coarser than ``detail_above_texel_m``
            metres per texel), ``true`` (every map) or ``false``.
        apron_m: sideways margin of the evaluation region around the structure (metres).
        ground: add a textured ground plane reaching ``ground_margin_m`` beyond the structure.
        detail_strength: relative amplitude of the detail (0.3 = +-30 % brightness at 1 sigma).
        seed: seed of the detail, the materials and the ground texture.
        detail_above_texel_m: ``auto`` detail threshold (m per texel on the surface).
        material_texel_m: texel size (m) of the materials of untextured parts.
        ground_height: ``lowest`` (the lowest point), ``footprint`` (the height under most of the
            footprint) or a number (a height in the file's frame, in metres after unit and scale).
        ground_snap_m: a part whose base hangs at most this high above the ground with nothing
            under it gets a plinth (0: none; the model's parts float on purpose).
        flip_normals: reverse every face (a model exported with inward normals).
        drop_invalid_faces: drop faces that use NaN or infinite vertices instead of refusing them.
        check_size: refuse a model over 2 km or under 1 m across (a sign of wrong units).
    """

    up_axis: str = "z"
    scale: float = 1.0
    add_detail: str | bool = "auto"
    apron_m: float = 3.0
    ground: bool = True
    ground_margin_m: float = 30.0
    detail_strength: float = 0.3
    seed: int = 0
    detail_above_texel_m: float = 0.03
    material_texel_m: float = 0.01
    ground_height: str | float = "lowest"
    ground_snap_m: float = 1.5
    flip_normals: bool = False
    drop_invalid_faces: bool = False
    check_size: bool = True

    @classmethod
    def options(cls) -> set[str]:
        """The option names a scene config may set."""
        return {f.name for f in fields(cls)}

    def check(self) -> None:
        """Refuse a bad option (``ValueError`` naming it)."""
        if self.up_axis not in ("z", "y"):
            raise ValueError(f"scene.up_axis must be 'z' or 'y', got {self.up_axis!r}")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"scene.scale must be a positive number, got {self.scale!r}")
        if self.apron_m < 0 or self.ground_margin_m < self.apron_m:
            raise ValueError(
                f"need 0 <= apron_m ({self.apron_m}) <= ground_margin_m ({self.ground_margin_m})"
            )
        if str(self.add_detail).lower() not in ("auto", "true", "false"):
            raise ValueError(f"scene.add_detail must be auto, true or false, got {self.add_detail!r}")


@dataclass
class _Model:
    """A mesh file read into metres, Z up: its geometries and their (vertices, faces)."""

    geometries: list
    model: list[tuple[np.ndarray, np.ndarray]]
    factor: float
    lo: np.ndarray
    hi: np.ndarray
    resolver: _AssetResolver


def load_mesh_scene(
    path: str | os.PathLike,
    spec: MeshSceneSpec | None = None,
    cache_dir: str | os.PathLike | None = None,
    name: str | None = None,
) -> Scene:
    """Load a mesh file as a Scene in metres, Z up, ground at z = 0.

    Args:
        path: mesh file (OBJ/MTL, GLB/glTF, PLY, DAE, STL, OFF) with texture or vertex colours.
        spec: how to read and dress it (``MeshSceneSpec``; None: its defaults).
        cache_dir: where generated textures are cached (``cache_dir/textures``), None for no cache.
        name: scene name (default: the file's stem).

    Raises:
        FileNotFoundError: the file or a texture it needs does not exist.
        ValueError: unreadable file, unsupported format, no faces, undecodable texture, bad option,
            wrong units, NaN vertices, inward normals (each message names the option that fixes it).
    """
    started = time.perf_counter()
    spec = MeshSceneSpec() if spec is None else spec
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if not path.is_file() or not os.access(path, os.R_OK):
        raise ValueError(f"mesh file is not a readable file: {path}")
    if path.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise ValueError(
            f"unsupported mesh format {path.suffix!r} of {path}; supported: {SUPPORTED_SUFFIXES}"
        )
    spec.check()
    add_detail = str(spec.add_detail).lower()
    read = _read_model(path, spec)
    base = _ground_base(read, spec.ground_height)
    lo, hi = read.lo, read.hi
    shift = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), base])
    stem = name or path.stem
    parts, textures, report, pads = _dressed_parts(read, shift, stem, spec, add_detail, cache_dir)
    if not parts:
        raise ValueError(f"mesh file {path} has no faces above the ground")
    problems = _texture_problems(read.resolver, read.geometries)
    if problems:
        raise problems[0]

    structure = Box.from_points(np.concatenate([p.vertices for p in parts]))
    factor = read.factor
    info = {
        "source": str(path),
        "unit_to_m": _unit_to_metres(path),
        "unit_name": _collada_unit_name(path) if path.suffix.lower() == ".dae" else None,
        "scale": float(spec.scale),
        "up_axis": spec.up_axis,
        "add_detail": add_detail,
        "detail_rule": f"maps coarser than {spec.detail_above_texel_m} m/texel or plainer than "
        f"{PLAIN_MAP_LAPLACIAN} grey levels of median |Laplacian|",
        "ground_height_in_file_m": float(base / factor) if factor else None,
        "shift_m": [float(v) for v in shift],
        "n_parts_kept_maps": len(report["kept_maps"]),
        "n_parts_detailed_maps": len(report["detailed_maps"]),
        "n_parts_materials": len(report["materials"]),
        "n_plinths": len(pads),
        "n_faces_structure": int(sum(len(p.faces) for p in parts)),
        "extent_m": [float(v) for v in structure.extent],
    }
    if spec.ground:
        info["ground_parts"] = _add_ground(parts, textures, structure, stem, spec, cache_dir)
    apron_m = spec.apron_m
    evaluation = Box(
        (structure.lo[0] - apron_m, structure.lo[1] - apron_m, -0.5),
        (structure.hi[0] + apron_m, structure.hi[1] + apron_m, structure.hi[2] + 1.0),
    )
    info["n_faces"] = int(sum(len(p.faces) for p in parts))
    info["texture_bytes"] = int(sum(t.nbytes for t in textures.values()))
    info["build_seconds"] = round(time.perf_counter() - started, 3)
    return Scene(stem, parts, textures, structure, evaluation, seed=None, info=info)


def _read_model(path: Path, spec: MeshSceneSpec) -> _Model:
    """The file's faced geometries, in metres with Z up (unit, scale, up axis, flipped normals),
    with the extent of the vertices its valid faces use; a model of wrong units refused."""
    resolver = _AssetResolver(path)
    try:
        loaded = trimesh.load(str(path), resolver=resolver, process=False)
    except Exception as err:
        raise ValueError(f"cannot read mesh file {path}: {type(err).__name__}: {err}") from err
    geometries = _geometries(loaded)
    geometries = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not geometries:
        raise ValueError(f"mesh file {path} has no faces")

    factor = _unit_to_metres(path) * float(spec.scale)
    transform = np.eye(3) if spec.up_axis == "z" else np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    geometry_faces = [_valid_faces(g, path, spec.drop_invalid_faces) for g in geometries]
    model = [
        (
            np.nan_to_num(np.asarray(g.vertices, float)) @ transform.T * factor,
            f[:, ::-1] if spec.flip_normals else f,
        )
        for g, f in zip(geometries, geometry_faces, strict=True)
    ]
    used = np.concatenate([v[np.unique(f)] for v, f in model if len(f)])
    if len(used) == 0:
        raise ValueError(f"mesh file {path} has no valid faces")
    lo, hi = used.min(0), used.max(0)
    _check_model(path, model, hi - lo, factor, spec.check_size, spec.flip_normals)
    return _Model(geometries, model, factor, lo, hi, resolver)


def _ground_base(read: _Model, ground_height: str | float) -> float:
    """The height (model frame, metres) that becomes z = 0."""
    if ground_height == "lowest":
        return read.lo[2]
    if ground_height == "footprint":
        model = read.model
        return footprint_ground_height(
            trimesh.Trimesh(np.concatenate([v for v, _ in model]), _stacked_faces(model), process=False)
        )
    try:
        return float(ground_height)
    except (TypeError, ValueError):
        raise ValueError(
            f"scene.ground_height must be lowest, footprint or a height in metres, got {ground_height!r}"
        ) from None


def _dressed_parts(read: _Model, shift, stem: str, spec: MeshSceneSpec, add_detail: str, cache_dir):
    """The model's parts moved by ``shift``, above the ground: textured ones keep their maps (with
    detail where coarse or plain), coloured scans their colours, the rest materials by surface
    class; plinths under floating parts. Returns the parts, textures, report and plinths."""
    geometries, model, seed = read.geometries, read.model, spec.seed
    parts: list[MeshPart] = []
    textures: dict[str, np.ndarray] = {}
    image_keys: dict[str, str] = {}  # image content hash -> texture key (shared images load once)
    n_images = len({_image_hash(_visual(g)[1]) for g in geometries if _visual(g)[1] is not None})
    # Detail upsampling budget: one or a few maps may grow to 4096 px, many maps to 2048 px.
    max_side = _MAX_DETAIL_SIDE if n_images <= 4 else _MAX_DETAIL_SIDE // 2
    rng = np.random.default_rng([seed, 11])
    placed: list[tuple[np.ndarray, np.ndarray]] = []
    support = [(vertices + shift, faces) for vertices, faces in model if len(faces)]
    plainness: dict[str, bool] = {}
    report = {"kept_maps": [], "detailed_maps": [], "materials": []}
    for gi, (g, (vertices, faces)) in enumerate(zip(geometries, model, strict=True)):
        vertices = vertices + shift
        keep = _visible_faces(vertices, faces, [], np.zeros((0, 2, 3)), below_ground=True)
        if not keep.any():
            continue
        faces = faces[keep]
        placed.append((vertices, faces))
        part_name = f"{stem}_{gi}"
        uv, image, color = _visual(g)
        if uv is not None and image is not None:
            digest = _image_hash(image)
            key = image_keys.get(digest)
            texel = map_texel_m(vertices, faces, uv, image.size)
            coarse = add_detail == "true" or (
                add_detail == "auto"
                and (texel > spec.detail_above_texel_m or _plain(image, digest, plainness))
            )
            if key is None or (coarse and not key.endswith("_detail")):
                key = f"{stem}_tex{len(image_keys)}" + ("_detail" if coarse else "")
                image_keys[digest] = key
                rgb = np.asarray(image.convert("RGB"))
                if coarse:
                    up = max(1.0, min(4.0, max_side / max(rgb.shape[:2])))
                    rgb = detail_overlay(rgb, material_seed(seed, key), spec.detail_strength, up)
                textures[key] = np.ascontiguousarray(rgb)
            report["detailed_maps" if key.endswith("_detail") else "kept_maps"].append(part_name)
            # Faces keep the file's UVs; trimesh already duplicated vertices at UV seams.
            parts.append(MeshPart(part_name, vertices, faces, uv=uv, texture=key))
        elif color is not None and color.ndim == 2:  # per-vertex colours (a coloured scan): kept
            parts.append(MeshPart(part_name, vertices, faces, vertex_colors=color[..., :3]))
        else:  # no texture: uniform grey or one flat colour
            parts += material_parts(part_name, vertices, faces, color, stem, spec.material_texel_m, rng)
            report["materials"].append(part_name)
    if report["materials"]:
        textures.update(class_textures(stem, seed, cache_dir))
    pads = floating_pads(placed, spec.ground_snap_m, support=support) if spec.ground else []
    for k, (vertices, faces) in enumerate(pads):
        parts += material_parts(f"{stem}_pad{k}", vertices, faces, None, stem, spec.material_texel_m, rng)
    if pads and not report["materials"]:
        textures.update(class_textures(stem, seed, cache_dir))
    log.info(
        "%s: %d parts keep their maps, %d get detail on a map coarser than %.3f m/texel or too plain, "
        "%d untextured parts get materials by surface class%s; %d plinth(s) under floating parts",
        stem,
        len(report["kept_maps"]),
        len(report["detailed_maps"]),
        spec.detail_above_texel_m,
        len(report["materials"]),
        f" ({', '.join(report['materials'][:8])}{', ...' if len(report['materials']) > 8 else ''})"
        if report["materials"]
        else "",
        len(pads),
    )
    return parts, textures, report, pads


def _add_ground(parts: list, textures: dict, structure: Box, stem: str, spec: MeshSceneSpec, cache_dir):
    """Add the textured ground tiles (``ground_margin_m`` beyond the structure); their materials."""
    mat = Material("ground", "ground_dry", 0.025, 2048)
    tiles = ground_tiles(
        structure.lo_array[:2] - spec.ground_margin_m,
        structure.hi_array[:2] + spec.ground_margin_m,
        "ground",
        tile_m=mat.texel_m * mat.size,
        cell_m=4.0,
    )
    for tile in tiles:  # one texture per tile (own seed), so no patch of ground repeats
        parts.append(_ground_part(tile, mat, spec.seed))
        textures[tile.material] = cached_texture(
            stem, tile.material, mat.preset, mat.size, material_seed(spec.seed, tile.material), cache_dir
        )
    return [tile.material for tile in tiles]


def _valid_faces(g: trimesh.Trimesh, path: Path, drop: bool) -> np.ndarray:
    """The faces of ``g`` (F, 3); faces on NaN or infinite vertices refused, or dropped when ``drop``."""
    faces = np.asarray(g.faces, np.int64)
    bad_vertex = ~np.isfinite(np.asarray(g.vertices, float)).all(axis=1)
    if not bad_vertex.any():
        return faces
    bad_face = bad_vertex[faces].any(axis=1)
    if not drop:
        raise ValueError(
            f"{path}: {int(bad_vertex.sum())} vertices are NaN or infinite ({int(bad_face.sum())} faces use "
            "them): the file is damaged; scene.drop_invalid_faces=true drops those faces"
        )
    return faces[~bad_face]


def _stacked_faces(model: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    offsets = np.cumsum([0] + [len(v) for v, _ in model[:-1]])
    return np.concatenate([f + o for (_, f), o in zip(model, offsets, strict=True)])


def _check_model(
    path: Path, model, extent: np.ndarray, factor: float, check_size: bool, flipped: bool
) -> None:
    """Refuse wrong units and inward-facing closed parts, naming the option that fixes each; warn
    about non-manifold edges (rendering and scoring handle them)."""
    size = float(extent.max())
    if check_size and not SIZE_RANGE_M[0] <= size <= SIZE_RANGE_M[1]:
        raise ValueError(
            f"{path}: the model is {size:.4g} m across (file unit x scene.scale = {factor:g} m): unknown "
            "units? set scene.scale (0.001 for millimetres, 0.01 for centimetres, 0.0254 for inches), "
            "or scene.check_size=false for a model that really is this size"
        )
    closed = [(v, f) for v, f in model if len(f) >= 4]
    inward, n_closed, non_manifold = 0, 0, 0
    for vertices, faces in closed:
        mesh = trimesh.Trimesh(vertices, faces, process=True, validate=False)
        edges = mesh.edges_sorted
        _, counts = np.unique(edges, axis=0, return_counts=True)
        non_manifold += int(np.count_nonzero(counts > 2))
        if mesh.is_watertight:
            n_closed += 1
            inward += int(mesh.volume < 0)
    if n_closed and inward > n_closed / 2:
        fix = "remove scene.flip_normals=true" if flipped else "set scene.flip_normals=true"
        raise ValueError(
            f"{path}: {inward} of {n_closed} closed parts face inwards (negative volume): the normals are "
            f"inverted; {fix}"
        )
    if non_manifold:
        log.warning(
            "%s: %d non-manifold edges (shared by more than two faces); rendered and scored as they are",
            path,
            non_manifold,
        )


def _plain(image, digest: str, memo: dict[str, bool]) -> bool:
    """Whether a map is too plain for SIFT (``PLAIN_MAP_LAPLACIAN``), computed once per image."""
    if digest not in memo:
        grey = np.asarray(image.convert("L"), np.float32)
        memo[digest] = float(np.median(np.abs(cv2.Laplacian(grey, cv2.CV_32F)))) < PLAIN_MAP_LAPLACIAN
    return memo[digest]


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
