"""Build a MuJoCo model of a ``Scene``: textured meshes, a sun and sky light, a sky background.

Everything stays in world coordinates: MuJoCo moves every mesh into its own inertial frame and
gives the geom the opposite transform, so the rendered surface is where the scene put it (to
float32 precision; ``tests/test_render.py`` checks it).

Texture coordinates follow the OBJ/trimesh convention: ``u`` to the right, ``v`` up, so ``v = 0``
is the bottom row of the texture image ((H, W, 3) arrays, row 0 at the top).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from render.settings import RenderSettings
from scene.base import MeshPart, Scene
from scene.camera import Intrinsics

# A surface without texture or vertex colours gets this neutral grey (RGB in [0, 1]).
_PLAIN_RGBA = (0.6, 0.6, 0.6, 1.0)
# mjMAXTEXTURE in mjrender.h (the sky box takes one).
_MAX_TEXTURES = 1000


@dataclass(frozen=True)
class LightingConfig:
    """The fixed world-frame lighting; see ``conf/render/default.yaml`` for the meaning of each value."""

    sun_azimuth_deg: float
    sun_elevation_deg: float
    sun_diffuse: float
    sky_ambient: float
    sky_diffuse: float
    sky_color: tuple[float, float, float]
    horizon_color: tuple[float, float, float]
    shadows: bool
    shadow_map_size: int
    shadow_margin_m: float

    @classmethod
    def of(cls, render: RenderSettings) -> LightingConfig:
        sun, sky, shadows = render.sun, render.sky, render.shadows
        out = cls(
            sun_azimuth_deg=sun.azimuth_deg,
            sun_elevation_deg=sun.elevation_deg,
            sun_diffuse=sun.diffuse,
            sky_ambient=sky.ambient,
            sky_diffuse=sky.diffuse,
            sky_color=_rgb(sky.color, "render.sky.color"),
            horizon_color=_rgb(sky.horizon_color, "render.sky.horizon_color"),
            shadows=shadows.enabled,
            shadow_map_size=shadows.map_size,
            shadow_margin_m=shadows.margin_m,
        )
        if not 0.0 < out.sun_elevation_deg <= 90.0:
            raise ValueError(f"render.sun.elevation_deg must lie in (0, 90], got {out.sun_elevation_deg}")
        if not 256 <= out.shadow_map_size <= 16384:
            raise ValueError(f"render.shadows.map_size must lie in [256, 16384], got {out.shadow_map_size}")
        return out

    @property
    def sun_direction(self) -> np.ndarray:
        """Unit vector (3,) along which sunlight travels (from the sun down to the scene)."""
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def _rgb(value, name: str) -> tuple[float, float, float]:
    rgb = tuple(float(v) for v in value)
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise ValueError(f"{name} must be three values in [0, 1], got {list(value)}")
    return rgb


@dataclass
class BuiltModel:
    """A compiled MuJoCo model of a scene and the facts the renderer needs about it."""

    model: object  # mujoco.MjModel
    camera_id: int
    geom_part_names: list[str]
    build_time_s: float
    max_texture_side: int


def vertex_color_palette(parts: list[MeshPart]) -> tuple[np.ndarray, list[np.ndarray]]:
    """One palette texture for the vertex-coloured parts and, per part, each face's texcoord (M, 2).

    MuJoCo meshes have no vertex colours; a palette with one texel per distinct face colour (the
    mean of the face's vertex colours) and all three corners of a face at that texel's centre
    reproduces flat-shaded vertex colours exactly (a constant texcoord has zero derivatives, so
    mipmapping never mixes texels).
    """
    face_rgb = [
        p.vertex_colors[p.faces].astype(np.float32).mean(axis=1).round().astype(np.uint8) for p in parts
    ]
    palette, face_index = np.unique(np.concatenate(face_rgb), axis=0, return_inverse=True)
    n = len(palette)
    side = int(2 ** math.ceil(math.log2(max(1.0, math.sqrt(n)))))
    texture = np.zeros((side * side, 3), np.uint8)
    texture[:n] = palette
    ij = np.stack([np.arange(n) % side, np.arange(n) // side], axis=1)
    # Texel centres in MuJoCo's raw texcoords (t = 0 is the first row of the image).
    texel_uv = ((ij + 0.5) / side).astype(np.float32)
    splits = np.cumsum([len(f) for f in face_rgb])[:-1]
    return texture.reshape(side, side, 3), np.split(texel_uv[face_index.ravel()], splits)


@dataclass
class RenderMesh:
    """A mesh laid out for MuJoCo: one normal and one texcoord per vertex (MuJoCo ignores per-corner
    indices), so vertices are split where a crease or a vertex-colour palette needs it."""

    vertices: np.ndarray  # (N, 3) float32, world metres
    faces: np.ndarray  # (M, 3) int32
    normals: np.ndarray  # (N, 3) float32, unit
    texcoords: np.ndarray | None  # (N, 2) float32, raw MuJoCo texcoords (t = 0 at image row 0)


def render_mesh(part: MeshPart, crease_deg: float, face_texcoord: np.ndarray | None = None) -> RenderMesh:
    """Lay out ``part`` for MuJoCo with smooth normals below ``crease_deg`` and flat ones above it.

    A corner takes the area-weighted mean normal of its vertex unless that deviates from its face's
    normal by more than ``crease_deg`` degrees (a box edge, a roof ridge); then it gets a vertex of
    its own with the face's normal.

    Args:
        part: the mesh part (its ``uv`` become texcoords unless ``face_texcoord`` is given).
        crease_deg: crease angle in degrees.
        face_texcoord: optional (M, 2) texcoord per face (vertex-colour palettes); every corner then
            gets its own vertex.
    """
    vertices, faces = part.vertices, part.faces
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vertex_n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vertex_n, faces[:, k], face_n)
    face_unit = face_n / np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-30)
    vertex_unit = vertex_n / np.maximum(np.linalg.norm(vertex_n, axis=1, keepdims=True), 1e-30)
    smooth = np.einsum("mkc,mc->mk", vertex_unit[faces], face_unit) >= math.cos(math.radians(crease_deg))
    n_vertices, n_faces = len(vertices), len(faces)
    corner_id = n_vertices + np.arange(3 * n_faces).reshape(n_faces, 3)
    key = corner_id if face_texcoord is not None else np.where(smooth, faces, corner_id)
    unique_key, first, inverse = np.unique(key.ravel(), return_index=True, return_inverse=True)
    corner_vertex = faces.ravel()[first]
    corner_face = first // 3
    normals = np.where(
        smooth.ravel()[first][:, None], vertex_unit[corner_vertex], face_unit[corner_face]
    ).astype(np.float32)
    if face_texcoord is not None:
        texcoords = np.asarray(face_texcoord, np.float32)[corner_face]
    elif part.uv is not None:
        uv = part.uv[corner_vertex].astype(np.float64)
        texcoords = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).astype(np.float32)
    else:
        texcoords = None
    out_vertices = vertices[corner_vertex].astype(np.float32)
    if len(out_vertices) < 4:  # MuJoCo compiles no mesh of fewer than 4 vertices: a lone triangle
        # gets an unused copy of its first corner (no face refers to it, nothing is drawn twice)
        pad = 4 - len(out_vertices)
        out_vertices = np.concatenate([out_vertices, np.repeat(out_vertices[:1], pad, axis=0)])
        normals = np.concatenate([normals, np.repeat(normals[:1], pad, axis=0)])
        texcoords = (
            None if texcoords is None else np.concatenate([texcoords, np.repeat(texcoords[:1], pad, axis=0)])
        )
    return RenderMesh(
        vertices=out_vertices,
        faces=inverse.reshape(n_faces, 3).astype(np.int32),
        normals=normals,
        texcoords=texcoords,
    )


def _add_texture(spec, mujoco, name: str, image: np.ndarray) -> None:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(
            f"texture {name!r} must be an (H, W, 3) uint8 array, got {image.dtype} {image.shape}"
        )
    tex = spec.add_texture()
    tex.name = name
    tex.type = mujoco.mjtTexture.mjTEXTURE_2D
    tex.colorspace = mujoco.mjtColorSpace.mjCOLORSPACE_LINEAR
    tex.width, tex.height, tex.nchannel = int(image.shape[1]), int(image.shape[0]), 3
    tex.data = np.ascontiguousarray(image).tobytes()


def _add_material(spec, mujoco, name: str, texture: str | None, rgba=(1.0, 1.0, 1.0, 1.0)) -> None:
    mat = spec.add_material()
    mat.name = name
    mat.rgba = list(rgba)
    # Lambertian only: a specular highlight would move with the camera.
    mat.specular = 0.0
    mat.shininess = 0.0
    mat.reflectance = 0.0
    mat.emission = 0.0
    if texture is not None:
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture


def scene_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo (3,), hi (3,)) in metres of every part of the scene."""
    lo = np.min([p.vertices.min(axis=0) for p in scene.parts], axis=0)
    hi = np.max([p.vertices.max(axis=0) for p in scene.parts], axis=0)
    return lo, hi


def _add_parts(spec, mujoco, scene: Scene, crease_deg: float) -> tuple[list[str], int]:
    """Add the scene's textures, materials, meshes and render-only geoms to ``spec``; the parts'
    names (geom order) and the largest texture side."""
    colored = [i for i, p in enumerate(scene.parts) if p.texture is None and p.vertex_colors is not None]
    # MuJoCo's renderer holds at most mjMAXTEXTURE textures and mjMAXMATERIAL textured materials.
    n_textures = len(scene.textures) + (1 if colored else 0) + 1
    if n_textures > _MAX_TEXTURES:
        raise ValueError(
            f"scene {scene.name!r} has {len(scene.textures)} textures; MuJoCo renders at most "
            f"{_MAX_TEXTURES - 2} (merge them into atlases)"
        )
    max_side = 0
    for key, image in scene.textures.items():
        _add_texture(spec, mujoco, f"tex:{key}", image)
        _add_material(spec, mujoco, f"mat:{key}", f"tex:{key}")
        max_side = max(max_side, *np.asarray(image).shape[:2])
    _add_material(spec, mujoco, "builtin:plain", None, _PLAIN_RGBA)
    face_texcoords = {}
    if colored:
        palette, per_part = vertex_color_palette([scene.parts[i] for i in colored])
        face_texcoords = dict(zip(colored, per_part, strict=True))
        _add_texture(spec, mujoco, "builtin:vertex_colors_palette", palette)
        _add_material(spec, mujoco, "builtin:vertex_colors", "builtin:vertex_colors_palette")
        max_side = max(max_side, palette.shape[0])

    names = []
    for i, part in enumerate(scene.parts):
        mesh = spec.add_mesh()
        mesh.name = f"mesh:{i}"
        # Open surfaces (the ground, a roof sheet) have no volume: weigh them as shells.
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
        if part.texture is not None:
            material = f"mat:{part.texture}"
        elif i in face_texcoords:
            material = "builtin:vertex_colors"
        else:
            material = "builtin:plain"
        face_texcoord = face_texcoords.get(i)
        prepared = render_mesh(part, crease_deg, face_texcoord)
        mesh.uservert = prepared.vertices.ravel()
        mesh.userface = prepared.faces.ravel()
        mesh.usernormal = prepared.normals.ravel()
        if prepared.texcoords is not None:
            mesh.usertexcoord = prepared.texcoords.ravel()
        geom = spec.worldbody.add_geom()
        geom.name = f"part:{i}"
        geom.type = mujoco.mjtGeom.mjGEOM_MESH
        geom.meshname = mesh.name
        geom.material = material
        if part.tint is not None:  # a geom colour other than MuJoCo's default replaces the material's
            geom.rgba = [*part.tint, 1.0]
        # Render-only geometry: no collisions, hence no convex hulls to compute.
        geom.contype = 0
        geom.conaffinity = 0
        names.append(part.name)
    return names, max_side


def build_model(scene: Scene, intrinsics: Intrinsics, render: RenderSettings) -> BuiltModel:
    """Compile ``scene`` into a MuJoCo model with one survey camera (id 0) sized for ``intrinsics``.

    Args:
        scene: the ground-truth scene (world metres).
        intrinsics: the camera; the off-screen buffer gets its size and the camera its vertical FOV.
        render: the ``render`` settings (lighting, shadows, clipping, anti-aliasing).

    Returns:
        The compiled model with the time it took (s).
    """

    # heavy (mujoco): imported on use
    import mujoco

    start = time.perf_counter()
    light = LightingConfig.of(render)
    spec = mujoco.MjSpec()
    spec.modelname = scene.name
    crease_deg = render.crease_angle_deg

    names, max_side = _add_parts(spec, mujoco, scene, crease_deg)

    lo, hi = scene_bounds(scene)
    structure_lo = scene.structure_bounds.lo_array
    structure_hi = scene.structure_bounds.hi_array
    scene_diagonal = float(np.linalg.norm(hi - lo))
    # MuJoCo's directional shadow map is an orthographic square of half-width shadowclip * extent
    # around the light's axis; nothing outside it is shadowed, so by default it spans the bounding
    # sphere of the whole scene.
    coverage = render.shadows.coverage
    if coverage == "scene":
        shadow_center = 0.5 * (lo + hi)
        shadow_radius = 0.5 * scene_diagonal + light.shadow_margin_m
    elif coverage == "structure":
        shadow_center = 0.5 * (structure_lo + structure_hi)
        shadow_radius = 0.5 * float(np.linalg.norm(structure_hi - structure_lo)) + light.shadow_margin_m
    else:
        raise ValueError(f"render.shadows.coverage must be scene or structure, got {coverage!r}")

    cam = spec.worldbody.add_camera()
    cam.name = "survey"
    cam.fovy = float(intrinsics.vfov_deg)

    sun_dir = light.sun_direction
    sun = spec.worldbody.add_light()
    sun.name = "sun"
    sun.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    sun.dir = sun_dir.tolist()
    # The shadow map looks from the light's position along its direction with the camera's clip
    # range: the sun stands a whole scene diagonal back so that everything lies beyond znear.
    sun_distance = scene_diagonal + render.znear_m + 1.0
    sun.pos = (shadow_center - sun_dir * sun_distance).tolist()
    sun.diffuse = [light.sun_diffuse] * 3
    # Ambient sits on the shadowless sky light: MuJoCo drops a shadowing light's ambient too.
    sun.ambient = [0.0] * 3
    sun.specular = [0.0] * 3
    sun.castshadow = light.shadows

    sky = spec.worldbody.add_light()
    sky.name = "sky"
    sky.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    sky.dir = [0.0, 0.0, -1.0]
    sky.pos = (shadow_center + np.array([0.0, 0.0, sun_distance])).tolist()
    sky.diffuse = [light.sky_diffuse] * 3
    sky.ambient = [light.sky_ambient] * 3
    sky.specular = [0.0] * 3
    sky.castshadow = False

    skybox = spec.add_texture()
    skybox.name = "sky"
    skybox.type = mujoco.mjtTexture.mjTEXTURE_SKYBOX
    skybox.builtin = mujoco.mjtBuiltin.mjBUILTIN_GRADIENT
    skybox.rgb1 = list(light.sky_color)
    skybox.rgb2 = list(light.horizon_color)
    skybox.width = skybox.height = 64

    vis = spec.visual
    vis.headlight.active = 0
    vis.headlight.ambient = [0.0] * 3
    vis.headlight.diffuse = [0.0] * 3
    vis.headlight.specular = [0.0] * 3
    vis.global_.offwidth = int(intrinsics.width)
    vis.global_.offheight = int(intrinsics.height)
    vis.quality.shadowsize = light.shadow_map_size
    vis.quality.offsamples = render.antialias_samples
    vis.map.haze = 0.0

    try:
        model = spec.compile()
    except Exception as err:  # mujoco raises ValueError with the compiler's message
        raise ValueError(f"MuJoCo could not compile scene {scene.name!r}: {err}") from err

    # Clip distances and the shadow box are stored relative to stat.extent; set them in metres.
    extent = max(scene_diagonal, 1.0)
    model.stat.extent = extent
    model.stat.center = 0.5 * (lo + hi)
    znear = render.znear_m
    zfar = max(render.zfar_m, 2.0 * scene_diagonal + 2.0 * sun_distance)
    if not 0.0 < znear < zfar:
        raise ValueError(f"render.znear_m must be positive and below the far plane, got {znear}")
    model.vis.map.znear = znear / extent
    model.vis.map.zfar = zfar / extent
    model.vis.map.shadowclip = shadow_radius / extent
    return BuiltModel(
        model=model,
        camera_id=0,
        geom_part_names=names,
        build_time_s=time.perf_counter() - start,
        max_texture_side=int(max_side),
    )
