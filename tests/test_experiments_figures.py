"""Figures from run directories: the plotted data equal the runs' viewpoints and metrics."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from matplotlib.collections import PathCollection
from matplotlib.quiver import Quiver
from PIL import Image

from experiments import figures
from experiments.runs import load_runs, runs_frame
from scene.camera import forward_vectors
from tests.experiments_fixtures import square_plan, write_run


def box_mesh() -> trimesh.Trimesh:
    box = trimesh.creation.box((8.0, 8.0, 6.0))
    box.apply_translation((0.0, 0.0, 3.0))
    return box


def test_flight_path_plots_the_viewpoints_by_kind():
    plan = square_plan()
    fig = figures.plot_flight_path(plan.viewpoints, plan.kinds, box_mesh(), arrow_length_m=2.0)
    ax3d, ax_top = fig.axes[0], fig.axes[1]
    kinds = np.array(plan.kinds)
    top_scatters = [c for c in ax_top.collections if isinstance(c, PathCollection)]
    assert [c.get_label() for c in top_scatters] == ["detail (3)", "coverage (3)", "grid (2)"]
    for scatter, kind in zip(top_scatters, ["detail", "coverage", "grid"], strict=True):
        np.testing.assert_allclose(scatter.get_offsets(), plan.viewpoints[kinds == kind, :2])
    scatters3d = [
        c for c in ax3d.collections if hasattr(c, "_offsets3d") and c.get_label().startswith("grid")
    ]
    np.testing.assert_allclose(
        np.column_stack(scatters3d[0]._offsets3d), plan.viewpoints[kinds == "grid", :3]
    )
    # Trajectory in flight order.
    trajectory = next(line for line in ax_top.lines if line.get_label() == "trajectory")
    np.testing.assert_allclose(np.column_stack(trajectory.get_data()), plan.viewpoints[:, :2])
    # Top-view arrows: horizontal part of the viewing direction, 2 m long in 3-D.
    quivers = [c for c in ax_top.collections if isinstance(c, Quiver)]
    detail = plan.viewpoints[kinds == "detail"]
    expected = 2.0 * forward_vectors(detail[:, 3], detail[:, 4])[:, :2]
    np.testing.assert_allclose(np.column_stack([quivers[0].U, quivers[0].V]), expected, atol=1e-12)
    # The box's 12 triangles are drawn under the flight.
    fig.canvas.draw()  # 3-D collections project their polygons when drawn
    surface = next(c for c in ax3d.collections if c.get_label() == "scene")
    assert len(surface.get_paths()) == 12


def test_flight_paths_by_scene_one_panel_each():
    plan = square_plan()
    shifted = plan.viewpoints + [100.0, 0.0, 0.0, 0.0, 0.0]
    fig = figures.plot_flight_paths_by_scene(
        [("Tomb", plan.viewpoints, plan.kinds, box_mesh()), ("Church", shifted, plan.kinds, None)]
    )
    assert [ax.get_title() for ax in fig.axes] == ["Tomb", "Church"]
    for ax, viewpoints in zip(fig.axes, [plan.viewpoints, shifted], strict=True):
        points = np.vstack(
            [np.column_stack(c._offsets3d) for c in ax.collections if hasattr(c, "_offsets3d")]
        )
        np.testing.assert_allclose(np.sort(points, axis=0), np.sort(viewpoints[:, :3], axis=0))


def test_metrics_vs_images_scatter_equals_the_runs(tmp_path):
    values = {  # (scene, planner, seed) -> (n_images, acc90_m, comp_050)
        ("tomb", "ours", 0): (291, 0.196, 31.56),
        ("tomb", "ours", 1): (305, 0.201, 30.10),
        ("tomb", "smith", 0): (322, 0.266, 18.92),
        ("church", "yan", 0): (3441, 0.106, 59.39),
    }
    for (scene, planner, seed), (n, acc, comp) in values.items():
        write_run(tmp_path, scene, planner, seed, n_images=n, acc90_m=acc, comp_050=comp)
    write_run(tmp_path, "church", "ours", 0, status="failed", error="boom", n_images=400)
    fig = figures.plot_metrics_vs_images(runs_frame(load_runs([tmp_path])))
    axes = np.array(fig.axes).reshape(2, 2)
    assert [ax.get_title() for ax in axes[0]] == ["Tomb", "Church"]
    by_label = {c.get_label(): c.get_offsets() for c in axes[0][0].collections}
    assert set(by_label) == {"Smith et al.", "Ours"}
    np.testing.assert_allclose(by_label["Ours"], [[291, 0.196], [305, 0.201]])
    np.testing.assert_allclose(by_label["Smith et al."], [[322, 0.266]])
    church_comp = {c.get_label(): c.get_offsets() for c in axes[1][1].collections}
    assert set(church_comp) == {"Yan et al."}  # the failed run of ours is not plotted
    np.testing.assert_allclose(church_comp["Yan et al."], [[3441, 59.39]])


def test_metrics_vs_flight_time_shows_minutes(tmp_path):
    write_run(tmp_path, "tomb", "ours", 0, n_images=291, flight_time_s=1500.0, acc90_m=0.19, comp_050=31.5)
    write_run(tmp_path, "tomb", "yan", 0, n_images=900, flight_time_s=5400.0, acc90_m=0.31, comp_050=60.2)
    fig = figures.plot_metrics_vs_images(runs_frame(load_runs([tmp_path])), cost="flight_time_s")
    top, bottom = fig.axes[:2]
    assert top.get_xlabel() == "flight time (min)"
    offsets = {c.get_label(): c.get_offsets() for c in bottom.collections}
    np.testing.assert_allclose(offsets["Ours"], [[25.0, 31.5]])
    np.testing.assert_allclose(offsets["Yan et al."], [[90.0, 60.2]])


def test_error_panel_shows_each_methods_images(tmp_path):
    images = {}
    for i, method in enumerate(["Smith et al.", "Ours"]):
        images[method] = {}
        for view in range(2):
            pixels = np.zeros((20, 30, 3), np.uint8)
            pixels[..., 0], pixels[..., 2] = 100 * i, 60 * view
            path = tmp_path / f"{i}_{view}.png"
            Image.fromarray(pixels).save(path)
            images[method][f"error_view{view}.png"] = path
    fig = figures.plot_error_panel(images)
    axes = np.array(fig.axes).reshape(2, 2)
    assert [ax.get_title() for ax in axes[0]] == ["Smith et al.", "Ours"]
    for row in range(2):
        for col in range(2):
            shown = np.asarray(axes[row][col].images[0].get_array())
            np.testing.assert_allclose(shown[..., 0], 100 * col / 255.0, atol=1e-6)
            np.testing.assert_allclose(shown[..., 2], 60 * row / 255.0, atol=1e-6)


def test_error_panel_draws_one_key_for_all_pictures(tmp_path):
    path = tmp_path / "view.png"
    Image.fromarray(np.full((20, 30, 3), 90, np.uint8)).save(path)
    images = {"Ours": {"error_nadir.png": path}}
    fig = figures.plot_error_panel(images, error_scale=(0.2, "turbo"))
    bars = [ax for ax in fig.axes if ax.get_label() == figures.COLOUR_BAR_LABEL]
    assert len(bars) == 1 and not fig.legends
    np.testing.assert_allclose(bars[0].get_ylim(), [0.0, 0.2])
    fig = figures.plot_error_panel(images, covered_within_m=0.05)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["within 50 mm", "missed"]
    assert not [ax for ax in fig.axes if ax.get_label() == figures.COLOUR_BAR_LABEL]


def test_decimate_mesh_keeps_the_shape():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=5.0)  # 5120 faces
    small = figures.decimate_mesh(sphere, 500)
    assert 100 < len(small.faces) <= 500
    np.testing.assert_allclose(small.bounds, sphere.bounds, atol=0.5)
    assert figures.decimate_mesh(sphere, 10_000) is sphere
    with pytest.raises(ValueError, match="max_faces"):
        figures.decimate_mesh(sphere, 2)


def test_cli_writes_png_and_pdf(tmp_path):
    root = tmp_path / "multirun"
    root.mkdir()
    box_mesh().export(root / "gt.ply")
    for i, planner in enumerate(["smith", "ours"]):
        run_dir = write_run(
            root,
            "tomb",
            planner,
            0,
            plan=square_plan(planner),
            n_images=300 + i,
            acc90_m=0.2,
            comp_050=30.0,
            gt_mesh_path=str(root / "gt.ply"),
        )
        (run_dir / "eval").mkdir()
        # The evaluation's file names (evaluate/visualise.py): error_<view>.png, coverage_<view>.png.
        for name in ("error_nadir.png", "error_oblique_ne.png", "coverage_nadir.png"):
            Image.fromarray(np.full((20, 30, 3), 40 * i, np.uint8)).save(run_dir / "eval" / name)
    out = tmp_path / "figures"
    assert figures.main([str(root), "--out", str(out), "--dpi", "50"]) == 0
    expected = {
        f"{stem}.{ext}"
        for stem in (
            "flight_tomb_smith",
            "flight_tomb_ours",
            "errors_tomb",
            "coverage_tomb",
            "metrics_vs_images",
        )
        for ext in ("png", "pdf")
    }
    assert {p.name for p in out.iterdir()} == expected
    for name in expected:
        data = (out / name).read_bytes()
        assert data[:4] == (b"\x89PNG" if name.endswith(".png") else b"%PDF")
    with Image.open(out / "flight_tomb_ours.png") as image:
        assert image.size[0] > image.size[1] > 100
    # errors: 2 views (rows) x 2 methods (columns); coverage: 1 view, so it is about half as tall.
    with Image.open(out / "errors_tomb.png") as errors, Image.open(out / "coverage_tomb.png") as coverage:
        assert errors.size[1] > 1.5 * coverage.size[1]
    assert figures.main([str(tmp_path / "nothing"), "--out", str(out)]) == 2
