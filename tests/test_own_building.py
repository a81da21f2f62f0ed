"""A user's own mesh: materials for untextured parts, the ground meeting every part, enclosed
surface, and refusals that name the fixing option."""

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh
from omegaconf import OmegaConf

from render.settings import RenderSettings
from scene.camera import Intrinsics, project_points
from scene.enclosure import exposed_samples, raycasting_scene
from scene.mesh_loader import MeshSceneSpec, load_mesh_scene

RENDER_CFG = RenderSettings.from_config(OmegaConf.load("conf/render/default.yaml"))


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(
        extents=hi - lo, transform=trimesh.transformations.translation_matrix(0.5 * (lo + hi))
    )


def write_obj(path, meshes) -> str:
    """An OBJ of untextured parts (one ``o`` group each, no materials)."""
    scene = trimesh.Scene()
    for i, mesh in enumerate(meshes):
        scene.add_geometry(mesh, geom_name=f"part{i}")
    path.write_text(trimesh.exchange.obj.export_obj(scene, include_texture=False, include_color=False))
    return str(path)


def test_an_untextured_face_renders_with_sift_texture(tmp_path):
    from render import SceneRenderer

    path = write_obj(tmp_path / "cube.obj", [box((-5, -5, 0), (5, 5, 10))])
    scene = load_mesh_scene(path, MeshSceneSpec(ground=False), cache_dir=tmp_path / "cache")
    assert scene.info["n_parts_materials"] == 1
    camera = Intrinsics(1024, 768, 60.0)
    view = np.array([17.0, 0.0, 5.0, 180.0, 0.0])  # 12 m in front of the +x face, facing it
    with SceneRenderer(scene, camera, RENDER_CFG) as renderer:
        image = renderer.render(view)
    corners = np.array([[5.0, y, z] for y in (-5, 5) for z in (0, 10)])
    pixels, _ = project_points(corners, view[None], camera)
    (u0, v0), (u1, v1) = pixels[0].min(axis=0).astype(int) + 4, pixels[0].max(axis=0).astype(int) - 4
    crop = cv2.cvtColor(image[max(v0, 0) : v1, max(u0, 0) : u1], cv2.COLOR_RGB2GRAY)
    assert crop.shape[0] > 500 and crop.shape[1] > 500
    assert len(cv2.SIFT_create().detect(crop, None)) >= 1000


def test_a_box_sealed_inside_another_is_enclosed_and_the_outer_one_exposed():
    outer, inner = box((-10, -10, 0), (10, 10, 10)), box((-3, -3, 2), (3, 3, 6))
    mesh = trimesh.util.concatenate([outer, inner])
    scene = raycasting_scene(mesh)
    results = {}
    for name, part in (("outer", outer), ("inner", inner)):
        points, faces = trimesh.sample.sample_surface_even(part, 2000, seed=0)
        normals = part.face_normals[faces]
        results[name] = exposed_samples(scene, points, normals)
        if name == "outer":  # its bottom face lies on the earth (z = 0, facing down): no camera there
            on_earth = normals[:, 2] < -0.5
            assert results[name][on_earth].mean() == 0.0
            results[name] = results[name][~on_earth]
    assert results["inner"].mean() == 0.0  # 100 % enclosed
    assert results["outer"].mean() == 1.0  # 100 % exposed


def test_walls_of_a_walled_courtyard_and_under_deep_eaves_are_exposed():
    # A 30 x 30 m yard walled 6 m high (walls 1 m thick), a 4 m pavilion with a 3 m eave in it.
    walls = [box((-15, -15, 0), (15, -14, 6)), box((-15, 14, 0), (15, 15, 6))]
    walls += [box((-15, -14, 0), (-14, 14, 6)), box((14, -14, 0), (15, 14, 6))]
    pavilion, roof = box((-2, -2, 0), (2, 2, 4)), box((-5, -5, 4), (5, 5, 4.5))
    ground = box((-40, -40, -0.1), (40, 40, 0))
    mesh = trimesh.util.concatenate([*walls, pavilion, roof, ground])
    scene = raycasting_scene(mesh)
    # the pavilion's walls under the eave, the eave's underside, the yard side of a wall
    samples = {
        "pavilion wall": ([2.0, 0.0, 2.0], [1.0, 0.0, 0.0]),
        "eave underside": ([4.0, 0.0, 4.0], [0.0, 0.0, -1.0]),
        "yard wall": ([-14.0, 0.0, 3.0], [1.0, 0.0, 0.0]),
    }
    points = np.array([p for p, _ in samples.values()])
    normals = np.array([n for _, n in samples.values()])
    assert exposed_samples(scene, points, normals).all()


def test_two_parts_at_different_base_heights_both_meet_the_ground(tmp_path):
    # a nave from z = 0 and a choir beside it whose base is 1 m higher (nothing under it)
    path = write_obj(tmp_path / "church.obj", [box((0, 0, 0), (20, 10, 12)), box((20, 2, 1), (28, 8, 9))])
    scene = load_mesh_scene(path, cache_dir=tmp_path / "cache")
    assert scene.info["n_plinths"] == 1
    mesh = scene.ground_truth_mesh
    rays = raycasting_scene(mesh)
    # straight down from just inside the choir's base: the plinth's top is met within 1 cm
    grid = [[x, y] for x in np.linspace(20.3, 27.7, 8) for y in np.linspace(2.3, 7.7, 6)]
    xy = np.array(grid) + np.array(scene.info["shift_m"][:2])
    origins = np.column_stack([xy, np.full(len(xy), 1.0 - 1e-4)])
    t = rays.cast_rays(
        o3d.core.Tensor(np.column_stack([origins, np.tile([0, 0, -1.0], (len(xy), 1))]).astype(np.float32))
    )["t_hit"].numpy()
    assert np.all(t <= 0.01)
    # and the nave stands on the ground at z = 0
    assert mesh.bounds[0][2] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("meshes", "options", "message"),
    [
        ([box((0, 0, 0), (3000, 10, 10))], {}, "3000 m across .* set scene.scale"),
        ([box((0, 0, 0), (0.3, 0.2, 0.5))], {}, "0.5 m across .* set scene.scale"),
        ([box((0, 0, 0), (10, 10, 10)).invert()], {}, "face inwards .* set scene.flip_normals=true"),
    ],
)
def test_bad_models_are_refused_naming_the_fix(tmp_path, meshes, options, message):
    path = write_obj(tmp_path / "bad.obj", meshes)
    with pytest.raises(ValueError, match=message):
        load_mesh_scene(path, MeshSceneSpec(**options), cache_dir=None)


def test_flip_normals_fixes_an_inverted_model_and_nan_vertices_are_named(tmp_path):
    path = write_obj(tmp_path / "inv.obj", [box((0, 0, 0), (10, 10, 10)).invert()])
    scene = load_mesh_scene(
        path, MeshSceneSpec(flip_normals=True, ground=False), cache_dir=tmp_path / "cache"
    )
    assert scene.ground_truth_mesh.volume > 0
    lines = (tmp_path / "inv.obj").read_text().splitlines()
    first_v = next(i for i, line in enumerate(lines) if line.startswith("v "))
    lines[first_v] = "v nan 0 0"
    (tmp_path / "nan.obj").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="1 vertices are NaN .* scene.drop_invalid_faces=true"):
        load_mesh_scene(tmp_path / "nan.obj", cache_dir=None)


def test_a_part_of_one_triangle_renders():
    # A user's model may hold a part of a single triangle (the power plant does): MuJoCo compiles no
    # mesh of fewer than 4 vertices, so the renderer pads it with an unused corner.
    from render import SceneRenderer
    from scene.base import Box, MeshPart, Scene

    vertices = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0]])
    part = MeshPart("tri", vertices, np.array([[0, 1, 2]]), vertex_colors=np.full((3, 3), 200, np.uint8))
    scene = Scene("tri", [part], {}, Box((-5, -5, 0), (5, 5, 1)), Box((-5, -5, 0), (5, 5, 1)))
    with SceneRenderer(scene, Intrinsics(64, 48, 60.0), RENDER_CFG) as renderer:
        image = renderer.render(np.array([0.0, 0.0, 10.0, 0.0, -90.0])).astype(int)
    centre, corner = image[24, 32], image[0, 0]
    assert abs(centre[0] - centre[2]) < 10  # the grey triangle under the camera
    assert corner[2] - corner[0] > 20  # the blue sky beside it
