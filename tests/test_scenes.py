"""Ground-truth scenes: procedural geometry, textures, the registry and the mesh loader."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from scene.base import Box, MeshPart
from scene.mesh_loader import MeshSceneSpec, load_mesh_scene
from scene.procedural.geometry import (
    Builder,
    Material,
    arched_wall,
    box,
    cylinder,
    gable_roof,
    hip_roof,
    place,
)
from scene.registry import KNOWN_SCENES, load_scene
from scene.textures import PRESETS, cached_texture, detail_overlay, make_texture

SMALL = {"texture_size": 256, "small_texture_size": 256}
SCHOOL = "/work/shared/data/meshes/school/meshes/school.dae"


def _scene_cfg(name: str, seed: int = 0, **extra) -> dict:
    return {"name": name, "seed": seed, **SMALL, **extra}


@pytest.fixture(scope="module")
def scenes():
    cfgs = {"tomb": {}, "church": {}, "cathedral": {"max_edge_m": 1.5, "ground_cell_m": 2.0}}
    return {name: load_scene(_scene_cfg(name, **extra), cache_dir=None) for name, extra in cfgs.items()}


def ground_of(scene) -> MeshPart:
    """The scene's ground tiles merged into one part."""
    tiles = [p for p in scene.parts if p.name in scene.info["ground_parts"]]
    offsets = np.cumsum([0] + [len(t.vertices) for t in tiles[:-1]])
    return MeshPart(
        "ground",
        np.concatenate([t.vertices for t in tiles]),
        np.concatenate([t.faces + o for t, o in zip(tiles, offsets, strict=True)]),
    )


# ------------------------------------------------------------------------------------ textures


def test_texture_same_seed_same_bytes_other_seed_differs():
    a = make_texture("stone_grey", 512, seed=3)
    b = make_texture("stone_grey", 512, seed=3)
    c = make_texture("stone_grey", 512, seed=4)
    assert a.shape == (512, 512, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert np.mean(a != c) > 0.5


def _check_sift_and_repetition(preset: str, size: int) -> None:
    image = make_texture(preset, size, seed=11)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    keypoints = cv2.SIFT_create().detect(gray[:768, :1024], None)
    assert len(keypoints) >= 1000, f"{preset}: {len(keypoints)} SIFT keypoints"
    # In shade: 1.3 texels per pixel (area-filtered) and 35 % light (the renderer's sky ambient).
    shaded = cv2.resize(gray, None, fx=1 / 1.3, fy=1 / 1.3, interpolation=cv2.INTER_AREA)
    shaded = np.clip(shaded.astype(np.float32) * 0.35 + 0.5, 0, 255).astype(np.uint8)[:768, :1024]
    keypoints = cv2.SIFT_create().detect(shaded, None)
    assert len(keypoints) >= 1000, f"{preset} in shade: {len(keypoints)} SIFT keypoints"
    # A 192 px patch must match nowhere else in the (periodic) map: tile the map 2 x 2 so that
    # shifts across the wrap are searched too, and blank the patch's own neighbourhood.
    patch = gray[400:592, 500:692]
    score = cv2.matchTemplate(np.tile(gray, (2, 2)), patch, cv2.TM_CCOEFF_NORMED)
    for dy in (0, size):
        for dx in (0, size):
            y, x = 400 + dy, 500 + dx
            score[max(0, y - 96) : y + 97, max(0, x - 96) : x + 97] = -1.0
    assert score.max() < 0.5, f"{preset}: a distinct patch correlates {score.max():.2f}"


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_texture_has_sift_features_and_no_repetition(preset):
    """A 1024 x 768 crop at one texel per pixel (1-3 cm, about the flights' GSD) gives >= 1000 SIFT
    keypoints, also when filtered and darkened as in shade, and a 192 px patch correlates < 0.5 with
    every other place of the map."""
    _check_sift_and_repetition(preset, 1024)


@pytest.mark.slow
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_texture_full_size_sift_and_no_repetition(preset):
    """The same at the scenes' default 4096 px maps."""
    _check_sift_and_repetition(preset, 4096)


def test_texture_cache_round_trip(tmp_path):
    first = cached_texture("t", "stone", "brick", 256, 5, tmp_path)
    files = list((tmp_path / "textures").glob("*.png"))
    assert len(files) == 1 and not list((tmp_path / "textures").glob(".*tmp*"))
    again = cached_texture("t", "stone", "brick", 256, 5, tmp_path)
    assert np.array_equal(first, again)
    assert np.array_equal(first, make_texture("brick", 256, 5))
    # A corrupt cache file is regenerated, not trusted.
    files[0].write_bytes(b"not a png")
    assert np.array_equal(cached_texture("t", "stone", "brick", 256, 5, tmp_path), first)


def test_detail_overlay_adds_features_and_keeps_mean_colour():
    plain = np.full((512, 512, 3), (180, 150, 120), np.uint8)
    detailed = detail_overlay(plain, seed=1, strength=0.3)
    assert len(cv2.SIFT_create().detect(cv2.cvtColor(detailed, cv2.COLOR_RGB2GRAY), None)) >= 300
    expected = 255 * (0.08 + 0.84 * np.array([180, 150, 120]) / 255)
    assert np.allclose(detailed.reshape(-1, 3).mean(0), expected, atol=3.0)


# ---------------------------------------------------------------------------------- geometry


def test_uv_scale_is_metres_over_texel_size():
    b = Builder([Material("m", "brick", 0.01, 256)], seed=0, max_edge_m=10.0)
    b.add(box((0, 0, 1), (4, 3, 5), "m"))
    (part,) = b.build()
    # The +x face: u runs along y (3 m), v along z (4 m); one UV unit = 256 texels x 1 cm.
    on_face = np.isclose(part.vertices[part.faces, 0], 4.0).all(axis=1)
    uv = part.uv[part.faces[on_face].ravel()].astype(float)
    assert on_face.sum() == 2
    assert np.ptp(uv[:, 0]) == pytest.approx(3.0 / 2.56, abs=1e-5)
    assert np.ptp(uv[:, 1]) == pytest.approx(4.0 / 2.56, abs=1e-5)


def test_hidden_faces_are_culled_and_surfaces_read_distinct_patches():
    b = Builder([Material("m", "brick", 0.01, 256)], seed=0, max_edge_m=10.0)
    b.add(box((0, 0, 0), (2, 2, 2), "m"))
    b.add(box((0, 0, 2), (2, 2, 4), "m"))  # stacked: the shared faces and the bottom are hidden
    b.add(box((5, 0, 1), (7, 2, 3), "m"))  # same shape elsewhere, floating: all 12 faces visible
    (part,) = b.build()
    assert len(part.faces) == 12 + 12 - 6 + 12
    normals = trimesh.Trimesh(part.vertices, part.faces, process=False).face_normals
    centers = part.vertices[part.faces].mean(1)
    assert not np.any((normals[:, 2] < -0.9) & (centers[:, 2] < 1e-6))
    # The two 2 x 2 x 2 blocks' +x faces read different texture patches.
    face_a = np.isclose(part.vertices[part.faces, 0], 2.0).all(1) & (part.vertices[part.faces, 2] <= 2.0).all(
        1
    )
    face_b = np.isclose(part.vertices[part.faces, 0], 7.0).all(1)
    uv_a = part.uv[part.faces[face_a].ravel()].min(0)
    uv_b = part.uv[part.faces[face_b].ravel()].min(0)
    assert np.abs(uv_a - uv_b).max() > 1e-3


@pytest.mark.parametrize(
    ("make", "volume"),
    [
        (lambda: box((0, 0, 0), (1, 2, 3), "m"), 6.0),
        (lambda: cylinder(1.0, 0.0, 2.0, "m", n=64), 2 * np.pi * np.sin(np.pi / 32) * 32 / np.pi),
        (
            lambda: hip_roof(0, 0, 4, 2, 0.0, 1.0, "m", fascia=0.5, ridge_fraction=0.0),
            # fascia box + prismatoid up to the 2 mm ridge segment: h/6 (A_base + 4 A_mid + 0)
            4 * 2 * 0.5 + (8.0 + 4 * 2.0 * 1.001) / 6,
        ),
        (lambda: gable_roof(4.0, 2.0, 0.0, 1.0, "m", fascia=0.5), 4 * 2 * 0.5 + 4 * 1.0),
    ],
)
def test_primitives_are_closed_with_outward_faces(make, volume):
    piece = make()
    mesh = trimesh.Trimesh(piece.vertices, piece.faces)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(volume, rel=1e-6)  # positive: faces point outwards


def test_arched_wall_pieces_are_closed_and_outward():
    pieces = arched_wall(
        6.0,
        5.0,
        0.8,
        [
            dict(x=1.0, width=1.6, sill=0.5, spring=2.5, depth=0.4),
            dict(x=1.0, width=1.6, sill=3.5, spring=4.0, depth=0.3, arch=False),
            dict(x=3.5, width=2.0, spring=2.0, depth=0.5),
        ],
        "m",
    )
    volume = 0.0
    for p in place(pieces, np.pi / 3, (10.0, 0.0, 0.0)):
        mesh = trimesh.Trimesh(p.world_vertices(), p.faces)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        volume += mesh.volume
    recess = 1.6 * 2.0 * 0.4 + 0.5 * np.pi * 0.8**2 * 0.4 + 1.6 * 0.5 * 0.3 + (2.0 * 2.0 + 0.5 * np.pi) * 0.5
    # Arcs are 8-segment polygons: the solid keeps slightly more than the exact circle segments.
    assert volume == pytest.approx(6.0 * 5.0 * 0.8 - recess, abs=0.05)


# ------------------------------------------------------------------------------------ scenes


def test_scenes_are_deterministic_by_seed(scenes):
    a = scenes["tomb"]  # seed 0
    b = load_scene(_scene_cfg("tomb", seed=0), cache_dir=None)
    c = load_scene(_scene_cfg("tomb", seed=1), cache_dir=None)
    for pa, pb in zip(a.parts, b.parts, strict=True):
        assert np.array_equal(pa.vertices, pb.vertices) and np.array_equal(pa.faces, pb.faces)
        assert np.array_equal(pa.uv, pb.uv)
    assert all(np.array_equal(a.textures[k], b.textures[k]) for k in a.textures)
    assert all(not np.array_equal(a.textures[k], c.textures[k]) for k in a.textures)
    assert not np.array_equal(a.parts[0].uv, c.parts[0].uv)


@pytest.mark.parametrize(
    ("name", "footprint", "tol", "height_range"),
    [
        ("tomb", (40.0, 30.0), 1.5, (10.0, 16.0)),
        ("church", (36.0, 33.0), 2.0, (30.0, 40.0)),
        ("cathedral", (55.0, 110.0), 3.0, (59.5, 60.5)),
    ],
)
def test_scene_size_matches_spec(scenes, name, footprint, tol, height_range):
    s = scenes[name]
    extent = s.structure_bounds.extent
    assert abs(extent[0] - footprint[0]) <= tol and abs(extent[1] - footprint[1]) <= tol, extent
    assert height_range[0] <= extent[2] <= height_range[1] and s.structure_bounds.lo[2] == pytest.approx(0.0)
    ground = ground_of(s)
    g_lo, g_hi = ground.vertices.min(0), ground.vertices.max(0)
    assert np.allclose(g_lo[:2], s.structure_bounds.lo_array[:2] - 30.0, atol=1e-6)
    assert np.allclose(g_hi[:2], s.structure_bounds.hi_array[:2] + 30.0, atol=1e-6)
    assert np.allclose(ground.vertices[:, 2], 0.0)


@pytest.mark.parametrize("name", ["tomb", "church", "cathedral"])
def test_no_patch_of_ground_repeats(scenes, name):
    """Each ground tile reads its own texture and spans at most one period of it (tiles sharing one
    texture repeat it shifted, and SfM then registers bare-ground views a tile shift away)."""
    s = scenes[name]
    tiles = [p for p in s.parts if p.name in s.info["ground_parts"]]
    assert len(tiles) > 1  # 256 px textures at 2.5-3 cm: 6.4-7.7 m tiles
    assert len({t.texture for t in tiles}) == len(tiles)
    period_m = s.info["textures"]["ground"]["texel_m"] * s.info["textures"]["ground"]["size"]
    for tile in tiles:
        assert np.ptp(tile.vertices[:, :2], axis=0).max() <= period_m + 1e-9
        assert np.ptp(tile.uv, axis=0).max() <= 1.0 + 1e-6
    pixels = np.stack([s.textures[t.texture].reshape(-1, 3)[::97].astype(float) for t in tiles[:8]])
    for i in range(len(pixels)):
        for j in range(i + 1, len(pixels)):
            assert np.corrcoef(pixels[i].ravel(), pixels[j].ravel())[0, 1] < 0.5


def test_cathedral_towers_reach_60_m(scenes):
    s = scenes["cathedral"]
    for sx in (-1, 1):
        v = np.concatenate([p.vertices for p in s.parts if p.name not in s.info["ground_parts"]])
        tower = v[(np.sign(v[:, 0]) == sx) & (np.abs(v[:, 0]) > 14.0) & (v[:, 1] < -42.0)]
        assert tower[:, 2].max() == pytest.approx(60.0, abs=0.01)


@pytest.mark.parametrize("name", ["tomb", "church", "cathedral"])
def test_evaluation_region_is_structure_plus_apron(scenes, name):
    s = scenes[name]
    structure = np.concatenate([p.vertices for p in s.parts if p.name not in s.info["ground_parts"]])
    assert s.structure_bounds.contains(structure).all()
    assert s.evaluation_region.contains(structure).all()
    lo, hi = s.evaluation_region.lo_array, s.evaluation_region.hi_array
    assert np.allclose(lo, list(s.structure_bounds.lo_array[:2] - 3.0) + [-0.5])
    assert np.allclose(hi, list(s.structure_bounds.hi_array[:2] + 3.0) + [s.structure_bounds.hi[2] + 1.0])
    ground = ground_of(s)
    assert 0 < s.evaluation_region.contains(ground.vertices).mean() < 1  # an apron, not all the ground


def test_tomb_has_deep_eaves(scenes):
    """Downward-facing surface above head height (eave soffits) covers well over 100 m^2."""
    mesh = scenes["tomb"].ground_truth_mesh
    down = (mesh.face_normals[:, 2] < -0.99) & (mesh.triangles_center[:, 2] > 3.0)
    assert mesh.area_faces[down].sum() > 100.0
    # The lower roof's soffit reaches 1.5 m beyond the colonnade: faces at x beyond the columns.
    assert np.abs(mesh.triangles_center[down, 0]).max() > 6.9 + 1.0


def test_scene_parts_and_texture_budget(scenes):
    for s in scenes.values():
        for part in s.parts:
            assert part.texture in s.textures and np.all(np.isfinite(part.uv))
            tri = part.vertices[part.faces]
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            assert area.min() > 1e-8
        assert (
            s.info["texture_bytes"]
            == sum(t.nbytes for t in s.textures.values())
            == len(s.textures) * 256**2 * 3
        )
        assert 20_000 <= s.n_faces <= 400_000


def test_no_face_hidden_inside_the_tomb_platform(scenes):
    mesh = scenes["tomb"].ground_truth_mesh
    inside = Box((-7.9, 2.35, 0.05), (7.9, 11.35, 0.95))  # pavilion platform interior (centre y = 6.75)
    assert not inside.contains(mesh.triangles_center).any()


def test_registry_refuses_unknown_and_incomplete_configs():
    with pytest.raises(ValueError, match="known scenes.*tomb.*church.*cathedral.*mesh"):
        load_scene({"name": "pyramid"})
    with pytest.raises(ValueError, match="name"):
        load_scene({"seed": 0})
    with pytest.raises(ValueError, match="scene.path"):
        load_scene({"name": "mesh"})
    with pytest.raises(ValueError, match="texture_size"):
        load_scene(_scene_cfg("tomb", texture_size=1000), cache_dir=None)
    assert set(KNOWN_SCENES) == {"tomb", "church", "cathedral", "mesh"}


# ------------------------------------------------------------------------------- mesh loader


def _write_textured_obj(folder, texture_bytes: bytes | None):
    folder.mkdir(parents=True, exist_ok=True)
    cube = trimesh.creation.box((2.0, 4.0, 6.0))
    lines = ["mtllib cube.mtl", "usemtl skin"]
    lines += [f"v {x} {y} {z}" for x, y, z in cube.vertices]
    lines += [f"vt {u} {v}" for u, v in np.random.default_rng(0).random((len(cube.vertices), 2))]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in cube.faces]
    (folder / "cube.obj").write_text("\n".join(lines) + "\n")
    (folder / "cube.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd skin.png\n")
    if texture_bytes is not None:
        (folder / "skin.png").write_bytes(texture_bytes)
    return folder / "cube.obj"


def _png_bytes(tmp_path) -> bytes:
    Image.fromarray(make_texture("brick", 256, 1)).save(tmp_path / "skin_src.png")
    return (tmp_path / "skin_src.png").read_bytes()


def test_mesh_loader_textured_obj(tmp_path):
    path = _write_textured_obj(tmp_path / "ok", _png_bytes(tmp_path))
    s = load_mesh_scene(path, MeshSceneSpec(scale=0.5, ground=False))
    (part,) = s.parts
    assert part.texture is not None and s.textures[part.texture].shape == (256, 256, 3)
    assert np.allclose(s.structure_bounds.extent, [1.0, 2.0, 3.0])
    assert s.structure_bounds.lo[2] == pytest.approx(0.0) and np.allclose(s.structure_bounds.center[:2], 0.0)
    # The bottom face lies on the ground and faces down: dropped (it would z-fight with the ground).
    assert len(part.faces) == 10


def test_mesh_loader_y_up_and_vertex_colours(tmp_path):
    cube = trimesh.creation.box((2.0, 4.0, 6.0))
    cube.visual.vertex_colors = np.random.default_rng(1).integers(0, 255, (8, 4), dtype=np.uint8)
    cube.export(tmp_path / "cube.ply")
    s = load_mesh_scene(tmp_path / "cube.ply", MeshSceneSpec(up_axis="y", apron_m=2.0, ground_margin_m=10.0))
    assert np.allclose(s.structure_bounds.extent, [2.0, 6.0, 4.0])  # y (4 m) is now up
    part = s.parts[0]
    assert part.vertex_colors is not None and part.vertex_colors.shape == (len(part.vertices), 3)
    assert np.allclose(s.evaluation_region.extent, [6.0, 10.0, 5.5])
    assert s.info["ground_parts"] == ["ground"]  # one 51 m tile of ground covers the 22 x 26 m
    assert s.parts[-1].name == "ground" and np.allclose(s.parts[-1].vertices.max(0)[:2], [11.0, 13.0])


def test_mesh_loader_bad_input(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.obj"):
        load_mesh_scene(tmp_path / "nowhere.obj")
    with pytest.raises(ValueError, match="not a readable file"):
        (tmp_path / "folder.obj").mkdir()
        load_mesh_scene(tmp_path / "folder.obj")
    (tmp_path / "garbage.glb").write_bytes(b"\x00garbage" * 10)
    with pytest.raises(ValueError, match="garbage.glb"):
        load_mesh_scene(tmp_path / "garbage.glb")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="points.obj has no faces"):
        load_mesh_scene(tmp_path / "points.obj")
    (tmp_path / "mesh.xyz").write_text("0 0 0\n")
    with pytest.raises(ValueError, match="unsupported mesh format"):
        load_mesh_scene(tmp_path / "mesh.xyz")
    with pytest.raises(ValueError, match="skin.png.*cannot be read"):
        load_mesh_scene(_write_textured_obj(tmp_path / "corrupt", b"\x89PNG\r\n\x1a\n" + b"\x00" * 64))
    with pytest.raises(FileNotFoundError, match="skin.png.*not found"):
        load_mesh_scene(_write_textured_obj(tmp_path / "missing", None))
    with pytest.raises(ValueError, match="up_axis"):
        load_mesh_scene(
            _write_textured_obj(tmp_path / "ok", _png_bytes(tmp_path)), MeshSceneSpec(up_axis="x")
        )


def test_mesh_loader_school_in_metres_with_detail():
    """The shared school (Collada in inches, Z-up) is about 33 x 17.5 x 14 m (its README)."""
    plain = load_mesh_scene(SCHOOL, MeshSceneSpec(ground=False, add_detail=False))
    assert plain.info["unit_to_m"] == pytest.approx(0.0254)
    assert np.allclose(plain.structure_bounds.extent, [33.0, 17.5, 14.2], atol=0.3)
    detailed = load_scene(
        {"name": "mesh", "path": SCHOOL, "add_detail": True, "ground": False}, cache_dir=None
    )
    assert np.allclose(detailed.structure_bounds.extent, plain.structure_bounds.extent)
    key = next(p.texture for p in detailed.parts if p.texture)
    plain_key = next(p.texture for p in plain.parts if p.texture)
    assert plain.textures[plain_key].shape == (1024, 1024, 3)
    assert detailed.textures[key].shape == (4096, 4096, 3)  # upsampled 4x for the detail to live in

    def sift(img):
        crop = cv2.cvtColor(img[:768, :1024], cv2.COLOR_RGB2GRAY)
        return len(cv2.SIFT_create().detect(crop, None))

    upsampled = cv2.resize(plain.textures[plain_key], None, fx=4, fy=4, interpolation=cv2.INTER_CUBIC)
    assert sift(detailed.textures[key]) > 2 * sift(upsampled)
