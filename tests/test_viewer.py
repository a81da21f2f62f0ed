"""The plan viewer: frustum geometry and a self-contained HTML file holding the plan's numbers."""

from __future__ import annotations

import base64
import json
import math
import re

import numpy as np
import pytest
import trimesh

from experiments import viewer
from scene.camera import Intrinsics, forward_vectors
from tests.experiments_fixtures import square_plan, write_run


def test_frustum_corners_of_a_known_camera():
    # hfov 90 deg on a 4x2 image: f = 2 px, so the corner rays are (+-1, +-0.5, 1) in the camera frame.
    intrinsics = Intrinsics(4, 2, 90.0)
    corners = viewer.frustum_corners(np.array([[1.0, 2.0, 3.0, 0.0, 0.0]]), intrinsics, depth_m=2.0)[0]
    # Looking along +x: image left is +y, image up is +z.
    expected = np.array([[2.0, 2.0, 1.0], [2.0, -2.0, 1.0], [2.0, -2.0, -1.0], [2.0, 2.0, -1.0]]) + [1, 2, 3]
    np.testing.assert_allclose(corners, expected, atol=1e-12)


def test_frustum_corners_match_the_field_of_view():
    intrinsics = Intrinsics(1024, 768, 60.0)
    plan = square_plan()
    depth = 3.0
    corners = viewer.frustum_corners(plan.viewpoints, intrinsics, depth)
    centre = corners.mean(axis=1)
    forward = forward_vectors(plan.viewpoints[:, 3], plan.viewpoints[:, 4])
    np.testing.assert_allclose(centre, plan.viewpoints[:, :3] + depth * forward, atol=1e-12)
    width = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
    height = np.linalg.norm(corners[:, 3] - corners[:, 0], axis=1)
    np.testing.assert_allclose(width, 2 * depth * math.tan(math.radians(30.0)), rtol=1e-12)
    np.testing.assert_allclose(height, width * 768 / 1024, rtol=1e-12)
    with pytest.raises(ValueError, match="depth"):
        viewer.frustum_corners(plan.viewpoints, intrinsics, 0.0)


def plot_data(html: str) -> list[dict]:
    """The trace list passed to Plotly.newPlot in a plotly HTML file."""
    start = html.index("Plotly.newPlot(")
    bracket = html.index("[", html.index(",", start))
    traces, _ = json.JSONDecoder().raw_decode(html[bracket:])
    return traces


def test_viewer_html_is_self_contained_and_holds_the_plan(tmp_path):
    plan = square_plan()
    mesh = trimesh.creation.box((8.0, 8.0, 6.0))
    mesh.export(tmp_path / "gt.ply")
    run_dir = write_run(
        tmp_path,
        "tomb",
        "ours",
        0,
        plan=plan,
        camera={"width": 1024, "height": 768, "hfov_deg": 60.0},
        gt_mesh_path=str(tmp_path / "gt.ply"),
    )
    out = tmp_path / "view" / "plan.html"
    assert viewer.main([str(run_dir), "--out", str(out), "--frustum-depth", "2.5"]) == 0
    html = out.read_text()
    assert not re.search(r"<script[^>]+src=", html)  # nothing loaded from anywhere
    assert "<link" not in html
    assert "plotly.js v" in html  # the library itself is embedded
    traces = {t.get("name"): t for t in plot_data(html)}
    kinds = np.array(plan.kinds)
    for kind in ("detail", "coverage", "grid"):
        xyz = np.column_stack([traces[kind]["x"], traces[kind]["y"], traces[kind]["z"]])
        np.testing.assert_allclose(xyz, plan.viewpoints[kinds == kind, :3], atol=1e-4)
        assert traces[kind]["customdata"] == np.flatnonzero(kinds == kind).tolist()
    trajectory = np.column_stack([traces["trajectory"][c] for c in "xyz"])
    np.testing.assert_allclose(trajectory, plan.viewpoints[:, :3], atol=1e-4)
    # Each detail camera's frustum (2.5 m deep) is in the file: its centre and its four image corners.
    frusta = traces["detail frusta"]
    points = np.array([[np.nan if v is None else v for v in frusta[c]] for c in "xyz"]).T
    detail = plan.viewpoints[kinds == "detail"]
    corners = viewer.frustum_corners(detail, Intrinsics(1024, 768, 60.0), 2.5)
    for apex, camera_corners in zip(detail[:, :3], corners, strict=True):
        for point in [apex, *camera_corners]:
            assert np.isclose(points, point, atol=1e-4).all(axis=1).any()
    assert traces["ground truth"]["type"] == "mesh3d"


def test_viewer_draws_the_proxy_from_the_cache_entry(tmp_path):
    entry = tmp_path / "cache" / "exploration" / "abc123"
    entry.mkdir(parents=True)
    proxy = trimesh.creation.icosphere(subdivisions=3, radius=4.0)  # 1280 faces
    proxy.export(entry / "proxy.ply")
    run_dir = write_run(tmp_path, "tomb", "ours", 0, plan=square_plan(), proxy_entry=str(entry))
    out = viewer.write_viewer(run_dir, mesh_source="proxy", max_faces=300)
    traces = {t.get("name"): t for t in plot_data(out.read_text())}
    assert out == run_dir / "plan.html"
    assert traces["proxy"]["type"] == "mesh3d"
    assert "detail frusta" not in traces  # the run records no camera: no frusta, no made-up one
    i = traces["proxy"]["i"]
    n_faces = (
        len(i) if isinstance(i, list) else len(base64.b64decode(i["bdata"])) // np.dtype(i["dtype"]).itemsize
    )
    assert 100 < n_faces <= 300


def test_viewer_rejects_a_directory_without_a_plan(tmp_path, capsys):
    run_dir = write_run(tmp_path, "tomb", "ours", 0)
    assert viewer.main([str(run_dir)]) == 2
    assert "has no plan/viewpoints.csv" in capsys.readouterr().err
    assert not (run_dir / "plan.html").exists()


def test_browser_mesh_merges_and_limits_vertices(monkeypatch):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=3.0)  # 2562 vertices, 5120 faces
    # Every face with its own three vertices (as exported with per-face UVs): 15360 vertices.
    unmerged = trimesh.Trimesh(
        sphere.triangles.reshape(-1, 3), np.arange(15360).reshape(-1, 3), process=False
    )
    merged = viewer.browser_mesh(unmerged, max_faces=10_000)
    assert (len(merged.vertices), len(merged.faces)) == (2562, 5120)
    monkeypatch.setattr(viewer, "MAX_BROWSER_VERTICES", 500)
    small = viewer.browser_mesh(unmerged, max_faces=10_000)
    assert len(small.vertices) < 500 and len(small.faces) > 300
    np.testing.assert_allclose(small.bounds, sphere.bounds, atol=0.3)
