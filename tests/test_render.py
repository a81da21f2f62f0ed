"""The MuJoCo renderer against the COLMAP camera model, the lighting model and bad input.

Scenes here are built from ``MeshPart``s: a textured ground, boxes, small red marker spheres.
The marker projection test renders in a subprocess per back-end (the OpenGL back-end is fixed
per process); the other rendering tests use this process's automatic back-end.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from render.backend import probe_backend
from render.settings import RenderSettings
from scene.base import Box, MeshPart, Scene
from scene.camera import Intrinsics, Viewpoint, cam_from_world, project_points

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "conf" / "render" / "default.yaml"
# Odd sizes: the principal point (cx, cy) = (400.5, 300.5) is a pixel centre, which catches
# half-pixel slips between MuJoCo's and COLMAP's pixel conventions.
MARKER_CAMERA = Intrinsics(801, 601, 70.0)
MARKER_RADIUS_M = 0.09
MARKER_POSES = np.array(
    [
        [2.0, -3.0, 25.0, 0.0, -90.0],  # nadir
        [-4.0, 6.0, 22.0, 120.0, -90.0],  # nadir, rotated image
        [-18.0, -12.0, 14.0, 33.0, -40.0],  # oblique
        [25.0, 4.0, 3.0, 200.0, 0.0],  # horizontal, yaw past 180
        [-6.0, 20.0, 1.5, -75.0, 12.0],  # looking up
    ]
)


def render_cfg(**overrides):
    """The default render config with dotted-key overrides (e.g. ``{"shadows.enabled": False}``)."""
    cfg = OmegaConf.load(CONFIG)
    for key, value in overrides.items():
        OmegaConf.update(cfg, key, value)
    return RenderSettings.from_config(cfg)


def ground_part(half_m: float, texture: str | None = None, name: str = "ground") -> MeshPart:
    """A square ground quad of half-side ``half_m`` at z = 0, split into 8 x 8 cells."""
    xs = np.linspace(-half_m, half_m, 9)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    i, j = np.meshgrid(np.arange(8), np.arange(8), indexing="xy")
    a = (j * 9 + i).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + 10], 1), np.stack([a, a + 10, a + 9], 1)])
    uv = (vertices[:, :2] + half_m) / (2.0 * half_m) * 8.0 if texture else None
    return MeshPart(name, vertices, faces, uv=uv, texture=texture)


def box_part(name: str, lo, hi, color=(200, 200, 200)) -> MeshPart:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi - lo)
    box.apply_translation(0.5 * (lo + hi))
    colors = np.tile(np.asarray(color, np.uint8), (len(box.vertices), 1))
    return MeshPart(name, box.vertices, box.faces, vertex_colors=colors)


def sphere_part(name: str, center, radius: float, color=(255, 0, 0)) -> MeshPart:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    colors = np.tile(np.asarray(color, np.uint8), (len(sphere.vertices), 1))
    return MeshPart(name, sphere.vertices + np.asarray(center, float), sphere.faces, vertex_colors=colors)


def noise_texture(seed: int = 0, size: int = 256) -> np.ndarray:
    """Grey (R = G = B) noise in [90, 200]: no pixel of it looks red."""
    grey = np.random.default_rng(seed).integers(90, 200, (size, size), dtype=np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def marker_points() -> np.ndarray:
    """(P, 3) marker centres: a few in front of every marker pose, at 8-24 m, above the ground."""
    rng = np.random.default_rng(7)
    cam = MARKER_CAMERA
    points = []
    for pose in MARKER_POSES:
        rot, t = cam_from_world(pose)
        centre = -rot.T @ t
        placed = 0
        while placed < 6:
            u = rng.uniform(0.1, 0.9) * cam.width
            v = rng.uniform(0.1, 0.9) * cam.height
            depth = rng.uniform(8.0, 24.0)
            ray = np.array([(u - cam.cx) / cam.focal_px, (v - cam.cy) / cam.focal_px, 1.0])
            point = centre + rot.T @ (ray * depth)
            if point[2] > 3 * MARKER_RADIUS_M:
                points.append(point)
                placed += 1
    return np.array(points)


def marker_scene() -> Scene:
    markers = [sphere_part(f"marker{i}", p, MARKER_RADIUS_M) for i, p in enumerate(marker_points())]
    parts = [ground_part(60.0, "noise"), *markers]
    return Scene(
        "markers",
        parts,
        {"noise": noise_texture()},
        Box((-5, -5, 0), (5, 5, 5)),
        Box((-60, -60, 0), (60, 60, 5)),
    )


def render_marker_flight(backend: str, out_dir: str) -> None:
    """Render the marker poses with ``backend`` into ``out_dir`` (run in a subprocess per back-end)."""
    from render import render_flight

    kinds = ["nadir", "nadir", "oblique", "horizontal", "up"]
    render_flight(marker_scene(), MARKER_POSES, MARKER_CAMERA, out_dir, render_cfg(backend=backend), kinds)


def red_blobs(image: np.ndarray) -> list[np.ndarray]:
    """Centroids (2,) in COLMAP pixels of the red blobs of an RGB image, largest first."""
    import cv2

    rgb = image.astype(np.int32)
    redness = rgb[:, :, 0] - np.maximum(rgb[:, :, 1], rgb[:, :, 2])
    mask = (redness > 40).astype(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1
    # connectedComponents gives pixel-index centroids; COLMAP puts pixel centres at +0.5.
    return [centroids[k] + 0.5 for k in order if stats[k, cv2.CC_STAT_AREA] >= 4]


@pytest.mark.parametrize("backend", ["egl", "osmesa"])
def test_marker_projection_matches_colmap(backend, tmp_path):
    import cv2

    reason = probe_backend(backend)
    if reason is not None:
        pytest.skip(f"{backend} cannot render on this machine: {reason}")
    code = f"import tests.test_render as t; t.render_marker_flight({backend!r}, {str(tmp_path)!r})"
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]

    from scene.cameras_file import read_cameras

    record = read_cameras(tmp_path)
    names, viewpoints, intrinsics, kinds = record
    assert record.backend == backend
    assert intrinsics == MARKER_CAMERA
    np.testing.assert_allclose(viewpoints, MARKER_POSES)
    assert kinds == ("nadir", "nadir", "oblique", "horizontal", "up")

    points = marker_points()
    pixels, depth = project_points(points, viewpoints, intrinsics)
    errors = []
    for v, name in enumerate(names):
        image = cv2.imread(str(tmp_path / name))[:, :, ::-1]
        assert image.shape == (MARKER_CAMERA.height, MARKER_CAMERA.width, 3)
        blobs = np.array(red_blobs(image))
        inside = (
            (depth[v] > 0)
            & (pixels[v, :, 0] > 10)
            & (pixels[v, :, 0] < intrinsics.width - 10)
            & (pixels[v, :, 1] > 10)
            & (pixels[v, :, 1] < intrinsics.height - 10)
        )
        own = np.arange(v * 6, v * 6 + 6)
        assert inside[own].all()
        offsets = []
        for p in own:
            nearest = np.argmin(np.linalg.norm(blobs - pixels[v, p], axis=1))
            offsets.append(blobs[nearest] - pixels[v, p])
        offsets = np.array(offsets)
        # A half-pixel convention slip would show as a common offset of the image's markers.
        assert np.linalg.norm(offsets.mean(axis=0)) < 0.3, (name, offsets)
        errors.extend(np.linalg.norm(offsets, axis=1))
    errors = np.array(errors)
    print(f"{backend}: marker reprojection error mean {errors.mean():.3f} px, max {errors.max():.3f} px")
    assert errors.max() < 1.0


@pytest.fixture(scope="module")
def lit_scene() -> Scene:
    """Plain albedo-200 ground with a 4 x 4 x 10 m tower at the origin (for light and shadow)."""
    albedo = np.full((16, 16, 3), 200, np.uint8)
    parts = [ground_part(80.0, "plain"), box_part("tower", (-2, -2, 0), (2, 2, 10), color=(160, 160, 160))]
    return Scene(
        "lit", parts, {"plain": albedo}, Box((-2, -2, 0), (2, 2, 10)), Box((-80, -80, 0), (80, 80, 10))
    )


@pytest.fixture(scope="module")
def lit_renderer(lit_scene):
    from render import SceneRenderer

    with SceneRenderer(lit_scene, Intrinsics(320, 240, 60.0), render_cfg(antialias_samples=0)) as renderer:
        yield renderer


def expected_level(albedo: float, normal, cfg, sunlit: bool) -> float:
    """8-bit level of a Lambertian surface under the configured sun and sky (no headlight)."""
    az, el = math.radians(cfg.sun.azimuth_deg), math.radians(cfg.sun.elevation_deg)
    to_sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    normal = np.asarray(normal, float)
    light = cfg.sky.ambient + cfg.sky.diffuse * max(0.0, normal[2])
    if sunlit:
        light += cfg.sun.diffuse * max(0.0, float(normal @ to_sun))
    return albedo * min(light, 1.0)


def sample(image: np.ndarray, pixel) -> np.ndarray:
    """Mean RGB of the 5 x 5 pixels around a COLMAP pixel position."""
    col, row = int(pixel[0]), int(pixel[1])
    return image[row - 2 : row + 3, col - 2 : col + 3].reshape(-1, 3).mean(axis=0)


def test_appearance_does_not_depend_on_the_camera(lit_renderer):
    cfg = render_cfg()
    cam = lit_renderer.intrinsics
    ground_point = np.array([[-30.0, -30.0, 0.0]])  # far from the tower and its shadow
    wall_point = np.array([[-2.0, 0.0, 6.0]])  # on the tower's sunlit -x face
    ground_views = np.array(
        [
            [-30.0, -30.0, 20.0, 0.0, -90.0],  # nadir from 20 m
            [-30.0 - 20.0 / math.sqrt(2), -30.0, 20.0 / math.sqrt(2), 0.0, -45.0],  # 45 deg from the west
            [-30.0, -30.0 + 10.0, 17.32, -90.0, -60.0],  # 60 deg from the north
        ]
    )
    wall_views = np.array(
        [[-14.0, 0.0, 6.0, 0.0, 0.0], [-10.0, -8.0, 6.0, 45.0, 0.0], [-8.0, 4.0, 9.0, -33.69, -24.0]]
    )
    for points, views, normal, albedo in (
        (ground_point, ground_views, (0, 0, 1), 200),
        (wall_point, wall_views, (-1, 0, 0), 160),
    ):
        pixels, _ = project_points(points, views, cam)
        colours = np.array(
            [sample(lit_renderer.render(v), px[0]) for v, px in zip(views, pixels, strict=True)]
        )
        expected = expected_level(albedo, normal, cfg, sunlit=True)
        # Same colour from every camera (no headlight, no specular), and the one the lights predict.
        assert np.ptp(colours, axis=0).max() <= 1.0, colours
        np.testing.assert_allclose(colours, expected, atol=2.0)


def test_tower_casts_a_shadow(lit_renderer):
    cfg = render_cfg()
    az, el = math.radians(cfg.sun.azimuth_deg), math.radians(cfg.sun.elevation_deg)
    away_from_sun = -np.array([math.cos(az), math.sin(az)])
    # The tower's top centre (10 m) throws its shadow 10 / tan(el) m away from the sun.
    reach = 10.0 / math.tan(el)
    shadowed = np.append(away_from_sun * 0.6 * reach, 0.0)
    lit = np.append(-away_from_sun * 0.6 * reach, 0.0)  # the sun side of the tower
    beyond = np.append(away_from_sun * (reach + 4.0), 0.0)  # past the shadow's tip
    view = np.array([[0.0, 0.0, 45.0, 0.0, -90.0]])
    pixels, _ = project_points(np.stack([shadowed, lit, beyond]), view, lit_renderer.intrinsics)
    image = lit_renderer.render(view[0])
    shadow_rgb, lit_rgb, beyond_rgb = (sample(image, p) for p in pixels[0])
    np.testing.assert_allclose(shadow_rgb, expected_level(200, (0, 0, 1), cfg, sunlit=False), atol=2.0)
    np.testing.assert_allclose(lit_rgb, expected_level(200, (0, 0, 1), cfg, sunlit=True), atol=2.0)
    np.testing.assert_allclose(beyond_rgb, lit_rgb, atol=1.0)
    assert lit_rgb.mean() - shadow_rgb.mean() > 60


def test_mesh_geometry_stays_at_world_coordinates():
    import mujoco

    from render.model import build_model, render_mesh

    # Asymmetric parts far from the origin: MuJoCo recentres each mesh on its centre of mass and
    # rotates it to its principal axes, so the geom must carry the exact inverse transform.
    rng = np.random.default_rng(3)
    tetra = MeshPart(
        "tetra",
        np.array(
            [[250.0, -180.0, 12.0], [262.0, -179.0, 12.5], [251.0, -160.0, 13.0], [255.0, -175.0, 30.0]]
        ),
        np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]),
    )
    blob = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    blob_vertices = blob.vertices * np.array([1.0, 2.5, 0.7]) + rng.normal(0, 0.2, blob.vertices.shape)
    blob_part = MeshPart(
        "blob",
        blob_vertices + [-140.0, 310.0, 8.0],
        blob.faces,
        uv=rng.random((len(blob_vertices), 2)),
        texture="t",
    )
    scene = Scene(
        "far",
        [ground_part(400.0), tetra, blob_part],
        {"t": noise_texture()},
        Box((-150, -200, 0), (270, 320, 30)),
        Box((-400, -400, 0), (400, 400, 30)),
    )
    built = build_model(scene, Intrinsics(64, 48, 60.0), render_cfg())
    model = built.model
    # Render-only geoms: no convex hull was computed (nor could be drawn instead of the mesh).
    assert (model.mesh_graphadr == -1).all()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for geom, part in enumerate(scene.parts):
        mesh = model.geom_dataid[geom]
        start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        local = model.mesh_vert[start : start + count].astype(np.float64)
        world = data.geom_xpos[geom] + local @ data.geom_xmat[geom].reshape(3, 3).T
        expected = render_mesh(part, 30.0).vertices
        assert world.shape == expected.shape
        assert np.abs(world - expected).max() < 1e-4, part.name


def test_vertex_colours_and_texture_orientation(tmp_path):
    from render import SceneRenderer

    # Texture rows: top half red, bottom half blue; v = 1 is the top row (OBJ convention).
    image = np.zeros((8, 8, 3), np.uint8)
    image[:4] = (200, 0, 0)
    image[4:] = (0, 0, 200)
    quad = MeshPart(
        "quad",
        [[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]],
        [[0, 1, 2], [0, 2, 3]],
        uv=[[0, 0], [1, 0], [1, 1], [0, 1]],
        texture="rb",
    )
    green = box_part("green", (12, -1, 0), (14, 1, 2), color=(0, 220, 0))
    scene = Scene(
        "orient",
        [quad, green],
        {"rb": image},
        Box((-10, -10, 0), (14, 10, 2)),
        Box((-10, -10, 0), (14, 10, 2)),
    )
    cfg = render_cfg(**{"shadows.enabled": False, "antialias_samples": 0})
    with SceneRenderer(scene, Intrinsics(200, 200, 90.0), cfg) as renderer:
        # Nadir with yaw 90: +y (v = 1) is the top of the image.
        img = renderer.render(Viewpoint(0, 0, 8, 90, -90)).astype(float)
        top_level = expected_level(200, (0, 0, 1), cfg, sunlit=True)
        np.testing.assert_allclose(sample(img, (100, 50)), [top_level, 0, 0], atol=2.0)
        np.testing.assert_allclose(sample(img, (100, 150)), [0, 0, top_level], atol=2.0)
        box_top = renderer.render(Viewpoint(13, 0, 6, 0, -90)).astype(float)
        np.testing.assert_allclose(
            sample(box_top, (100, 100)), [0, expected_level(220, (0, 0, 1), cfg, True), 0], atol=2.0
        )


def test_render_flight_refuses_bad_viewpoints_before_writing(tmp_path, lit_scene):
    from render import render_flight

    out = tmp_path / "images"
    viewpoints = np.array([[0.0, 0.0, 30.0, 0.0, -90.0], [1.0, float("nan"), 30.0, 0.0, -90.0]])
    with pytest.raises(ValueError, match=r"viewpoint 1 has a non-finite value: \[1.0, nan"):
        render_flight(lit_scene, viewpoints, Intrinsics(64, 48, 60.0), out, render_cfg())
    assert not out.exists()
    with pytest.raises(ValueError, match=r"shape \(V, 5\)"):
        render_flight(lit_scene, np.zeros((2, 4)), Intrinsics(64, 48, 60.0), out, render_cfg())
    with pytest.raises(ValueError, match="got 1 kinds for 2 viewpoints"):
        render_flight(
            lit_scene, viewpoints[:1].repeat(2, 0), Intrinsics(64, 48, 60.0), out, render_cfg(), ["a"]
        )
    with pytest.raises(ValueError, match="render.backend must be one of"):
        render_flight(lit_scene, viewpoints[:1], Intrinsics(64, 48, 60.0), out, render_cfg(backend="vulkan"))
    assert not (out / "cameras.json").exists()


def test_render_flight_writes_images_and_record(tmp_path, lit_scene):
    import cv2

    from render import render_flight
    from scene.cameras_file import read_cameras

    out = tmp_path / "images"
    out.mkdir()
    (out / "000007.png").write_bytes(b"stale image of an older flight")
    viewpoints = np.array([[0.0, -30.0, 20.0, 90.0, -30.0], [10.0, 10.0, 40.0, -45.0, -90.0]])
    cam = Intrinsics(160, 120, 60.0)
    result = render_flight(lit_scene, viewpoints, cam, out, render_cfg(), kinds=["coverage", "detail"])
    assert sorted(p.name for p in out.iterdir()) == ["000000.png", "000001.png", "cameras.json"]
    assert result.names == ("000000.png", "000001.png")
    record = json.loads((out / "cameras.json").read_text())
    assert record["backend"] == result.backend and record["backend"] in ("egl", "osmesa")
    assert record["intrinsics"] == cam.as_dict()
    assert record["render_time_s"] > 0
    rot, t = cam_from_world(viewpoints)
    for image, row, r, tt in zip(record["images"], viewpoints, rot, t, strict=True):
        np.testing.assert_allclose(image["viewpoint"], row)
        np.testing.assert_allclose(image["cam_from_world"]["rotation"], r, atol=1e-12)
        np.testing.assert_allclose(image["cam_from_world"]["translation"], tt, atol=1e-12)
    names, vps, intrinsics, kinds = read_cameras(out)
    assert names == result.names and intrinsics == cam and kinds == ("coverage", "detail")
    np.testing.assert_allclose(vps, viewpoints)
    # The PNG holds exactly the rendered pixels (lossless), top row first.
    from render import SceneRenderer

    with SceneRenderer(lit_scene, cam, render_cfg()) as renderer:
        again = renderer.render(viewpoints[1])
    np.testing.assert_array_equal(cv2.imread(str(out / "000001.png"))[:, :, ::-1], again)


def test_no_backend_gives_an_error_naming_both(tmp_path):
    # A PyOpenGL that cannot be imported breaks both back-ends for real.
    fake = tmp_path / "OpenGL"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('PyOpenGL disabled by the test')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO)])
    code = textwrap.dedent(
        """
        from render.backend import select_backend
        select_backend("auto")
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True)
    assert proc.returncode != 0
    assert "no off-screen OpenGL back-end works" in proc.stderr
    assert "egl: " in proc.stderr and "osmesa: " in proc.stderr
    assert "PyOpenGL disabled by the test" in proc.stderr


def test_cli_refuses_a_nan_viewpoint(tmp_path):
    csv_path = tmp_path / "viewpoints.csv"
    csv_path.write_text("index,x,y,z,yaw_deg,pitch_deg,kind\n0,0,0,30,0,-90,grid\n1,0,nan,30,0,-90,grid\n")
    out = tmp_path / "images"
    proc = subprocess.run(
        [sys.executable, "-m", "render", "tomb", str(csv_path), str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert str(csv_path) in proc.stderr and "viewpoint 1 has a non-finite value" in proc.stderr
    assert not out.exists()


def test_a_flight_rendered_twice_has_the_same_image_bytes(tmp_path, lit_scene):
    """The reconstruction's cache and a killed cell's resume key on the image bytes."""
    from render import render_flight

    viewpoints = np.array([[0.0, -20.0, 12.0, 90.0, -30.0], [15.0, 0.0, 25.0, 180.0, -60.0]])
    for name in ("first", "second"):
        render_flight(lit_scene, viewpoints, Intrinsics(96, 72, 60.0), tmp_path / name, render_cfg())
    first = sorted(p.name for p in (tmp_path / "first").glob("*.png"))
    assert len(first) == 2
    for image in first:
        assert (tmp_path / "first" / image).read_bytes() == (tmp_path / "second" / image).read_bytes()
