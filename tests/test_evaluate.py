"""Evaluation: metrics on constructed clouds with known answers, region handling, files, records."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import trimesh
from omegaconf import OmegaConf

from evaluate import record as run_record
from evaluate.__main__ import _load_group_config
from evaluate.__main__ import main as cli_main
from evaluate.geometry import clip_mesh_to_box, point_triangle_distance, sample_surface
from evaluate.loading import ReconstructionFileError, load_reconstruction
from evaluate.metrics import (
    SURFACE_CLASSES,
    EmptyReconstructionWarning,
    GroundTruth,
    score_file,
    score_points,
    surface_classes,
)
from evaluate.record import write_metrics
from evaluate.run import evaluate_reconstruction, format_region, parse_region
from evaluate.settings import EvaluationSettings, threshold_key
from evaluate.visualise import VIEW_NAMES, error_colors, save_view_png, splat, view_pixels
from scene.base import Box
from scene.camera import Intrinsics

ROOT = Path(__file__).resolve().parents[1]
BIG_BOX = Box((-10.0, -10.0, -10.0), (10.0, 10.0, 10.0))
FULL = {"accuracy_percentiles": [50, 80, 90, 95]}


def plane(x0, x1, y0, y1, z=0.0) -> trimesh.Trimesh:
    """Axis-aligned rectangle at height z, two triangles, normal +z."""
    vertices = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return trimesh.Trimesh(vertices=vertices, faces=[[0, 1, 2], [0, 2, 3]], process=False)


def grid(x0, x1, y0, y1, spacing, z=0.0) -> np.ndarray:
    xs = np.linspace(x0, x1, int(round((x1 - x0) / spacing)) + 1)
    ys = np.linspace(y0, y1, int(round((y1 - y0) / spacing)) + 1)
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3, radius=1.0)


# --- accuracy ---------------------------------------------------------------------------------


@pytest.mark.parametrize("d", [0.01, 0.04, 0.3])
def test_points_displaced_along_normal_have_accuracy_d(sphere, d):
    # On a convex mesh, a point pushed out along its face normal by d is at distance exactly d.
    samples, face = sample_surface(sphere, 5000.0, seed=1)
    points = samples + d * sphere.face_normals[face]
    record = score_points(points, sphere, BIG_BOX, FULL)
    for q in (50, 80, 90, 95):
        assert record[f"acc{q}_m"] == pytest.approx(d, rel=1e-6)
    assert record["acc_mean_m"] == pytest.approx(d, rel=1e-6)
    assert record["prec_050"] == (100.0 if d <= 0.05 else 0.0)


def test_accuracy_percentile_is_the_distance_below_which_q_percent_lie():
    # 100 points at heights 0.001 .. 0.100 over a plane: 90 % lie within 0.090.
    ground = plane(-1, 1, -1, 1)
    heights = np.arange(1, 101) / 1000.0
    points = np.column_stack([np.zeros(100), np.zeros(100), heights])
    record = score_points(points, ground, Box((-1, -1, -1), (1, 1, 1)), FULL)
    assert record["acc90_m"] == pytest.approx(0.090, abs=1e-12)
    assert record["acc95_m"] == pytest.approx(0.095, abs=1e-12)
    assert record["acc50_m"] == pytest.approx(0.050, abs=1e-12)
    assert record["prec_050"] == pytest.approx(50.0)


def test_point_triangle_distance_matches_trimesh_closest_point():
    rng = np.random.default_rng(4)
    triangles = rng.normal(size=(2000, 3, 3))
    points = rng.normal(scale=2.0, size=(2000, 3))
    expected = np.linalg.norm(points - trimesh.triangles.closest_point(triangles, points), axis=1)
    got = point_triangle_distance(points, triangles[:, 0], triangles[:, 1], triangles[:, 2])
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


# --- completeness ------------------------------------------------------------------------------


def test_cloud_sampling_half_of_the_surface_is_50_percent_complete():
    ground = plane(0, 20, 0, 10)
    half = grid(0, 10, 0, 10, 0.02)  # 2 cm grid: every point of the left half within 1.5 cm
    region = Box((-1, -1, -1), (21, 11, 1))
    record = score_points(half, ground, region)
    # Only the samples within t of the cut edge (t * 10 m of 200 m^2) add to the half.
    assert record["comp_050"] == pytest.approx(50.0, abs=1.0)
    assert record["comp_075"] == pytest.approx(50.0, abs=1.0)
    assert record["n_gt_samples"] == 200_000
    assert record["acc95_m"] == pytest.approx(0.0, abs=1e-9)


def test_cloud_equal_to_the_gt_samples_is_complete_and_exact(sphere):
    region = Box((-2, -2, -0.3), (2, 2, 2))  # cuts the sphere: only the upper part is scored
    settings = EvaluationSettings(accuracy_percentiles=(50, 90, 95), completeness_thresholds_m=(0.005, 0.05))
    samples, _ = sample_surface(clip_mesh_to_box(sphere, region), settings.gt_sample_density_per_m2, 0)
    record = score_points(samples, sphere, region, settings)
    assert record["comp_005"] == 100.0 and record["comp_050"] == 100.0
    assert record["acc95_m"] <= 1e-12 and record["acc_max_m"] <= 1e-6
    assert record["chamfer_m"] <= 1e-6
    assert record["fscore_050"] == 100.0


def test_completeness_per_surface_class_of_a_roof_only_cloud():
    # A 4 x 4 x 2 m block on 20 x 20 m of ground: ground 400 m^2, roof 16, walls 32, underside 16
    # (the block's bottom face). The underside and the 16 m^2 of ground under the block face each
    # other: no camera sees them, so they are counted apart and scored against nobody. A cloud on
    # the roof alone covers the roof and the top t of the walls.
    block = trimesh.creation.box(extents=(4.0, 4.0, 2.0))
    block.apply_translation((0.0, 0.0, 1.0))
    gt = trimesh.util.concatenate([plane(-10, 10, -10, 10), block])
    roof = grid(-2, 2, -2, 2, 0.02, z=2.0)
    record = score_points(roof, gt, Box((-11, -11, -1), (11, 11, 3)))
    assert record["gt_enclosed_pct"] == pytest.approx(100.0 * 32.0 / 464.0, abs=0.3)
    assert record["gt_enclosed_pct_undersides"] == 100.0
    assert record["gt_enclosed_pct_ground"] == pytest.approx(100.0 * 16.0 / 400.0, abs=0.3)
    assert record["gt_enclosed_pct_walls"] == 0.0 and record["gt_enclosed_pct_roofs"] == 0.0
    areas = {"ground": 384.0, "roofs": 16.0, "walls": 32.0, "undersides": 0.0}
    for name, area in areas.items():
        assert record[f"gt_share_{name}"] == pytest.approx(100.0 * area / 432.0, abs=0.3)
    assert record["comp_050_roofs"] == pytest.approx(100.0)
    assert record["comp_050_walls"] == pytest.approx(100.0 * 0.05 / 2.0, abs=0.3)
    assert record["comp_075_walls"] == pytest.approx(100.0 * 0.075 / 2.0, abs=0.3)
    assert record["comp_050_ground"] == 0.0 and record["comp_075_undersides"] is None
    # with the exclusion off, every sample is scored, as the first study did
    everything = score_points(roof, gt, Box((-11, -11, -1), (11, 11, 3)), {"exclude_enclosed": False})
    assert everything["gt_share_undersides"] == pytest.approx(100.0 * 16.0 / 464.0, abs=0.3)
    assert everything["n_gt_samples_enclosed"] == 0
    # the classes partition the samples: their weighted completeness is the overall one
    for key in ("050", "075"):
        total = (
            sum(record[f"gt_share_{c}"] * (record[f"comp_{key}_{c}"] or 0.0) for c in SURFACE_CLASSES) / 100.0
        )
        assert total == pytest.approx(record[f"comp_{key}"], abs=1e-9)


def test_accuracy_per_surface_class_of_a_cloud_off_the_roof_and_the_walls():
    # The same block: 1000 points 1 cm above the roof and 3000 points 4 cm off the +x wall (outside
    # it, at mid-height). Each class's percentiles are its own offset; the overall 90th percentile
    # is the walls' 4 cm, which the roof's points alone would never show.
    block = trimesh.creation.box(extents=(4.0, 4.0, 2.0))
    block.apply_translation((0.0, 0.0, 1.0))
    gt = trimesh.util.concatenate([plane(-10, 10, -10, 10), block])
    rng = np.random.default_rng(0)
    roof = np.column_stack([rng.uniform(-1.5, 1.5, (1000, 2)), np.full(1000, 2.01)])
    wall = np.column_stack([np.full(3000, 2.04), rng.uniform(-1.5, 1.5, 3000), rng.uniform(0.5, 1.5, 3000)])
    record = score_points(np.vstack([roof, wall]), gt, Box((-11, -11, -1), (11, 11, 3)))
    assert record["acc_share_roofs"] == pytest.approx(25.0)
    assert record["acc_share_walls"] == pytest.approx(75.0)
    assert record["acc90_roofs_m"] == pytest.approx(0.01, abs=1e-6)
    assert record["acc90_walls_m"] == pytest.approx(0.04, abs=1e-6)
    assert record["acc90_m"] == pytest.approx(0.04, abs=1e-6)
    assert record["acc_share_ground"] == 0.0 and record["acc90_ground_m"] is None


def test_surface_classes_by_slope_and_height():
    def normal(slope_deg):  # unit normal of a surface tilted slope_deg from horizontal
        a = math.radians(slope_deg)
        return [math.sin(a), 0.0, math.cos(a)]

    normals = np.array([normal(0), normal(0), normal(55), normal(65), normal(90), normal(125), normal(180)])
    heights = np.array([0.1, 0.4, 5.0, 5.0, 5.0, 5.0, 3.0])
    points = np.column_stack([np.zeros(7), np.zeros(7), heights])
    names = [SURFACE_CLASSES[k] for k in surface_classes(points, normals, 0.25, 0.5)]
    assert names == ["ground", "roofs", "roofs", "walls", "walls", "undersides", "undersides"]
    with pytest.raises(ValueError, match="facing_normal_z"):
        EvaluationSettings(facing_normal_z=1.0)


def test_clip_mesh_to_box_keeps_exactly_the_surface_inside():
    square = plane(0, 10, 0, 10)
    box = Box((2.5, 1.0, -1.0), (7.5, 4.0, 1.0))
    clipped = clip_mesh_to_box(square, box)
    assert clipped.area == pytest.approx(15.0, rel=1e-12)
    assert box.contains(clipped.vertices).all()
    # A tilted plane z = x through a box: the cut part is a sqrt(2) x 2 rectangle at 45 degrees.
    tilted = trimesh.Trimesh(
        vertices=[[-5, -5, -5], [5, -5, 5], [5, 5, 5], [-5, 5, -5]], faces=[[0, 1, 2], [0, 2, 3]]
    )
    cut = clip_mesh_to_box(tilted, Box((0, 0, -10), (1, 2, 10)))
    assert cut.area == pytest.approx(math.sqrt(2) * 2.0, rel=1e-12)
    # Cutting again changes nothing (re-scoring from the exported region mesh draws the same samples).
    again = clip_mesh_to_box(cut, Box((0, 0, -10), (1, 2, 10)))
    np.testing.assert_array_equal(again.vertices[again.faces], cut.vertices[cut.faces])


def test_clip_sphere_area_matches_the_spherical_zone(sphere):
    # A fine sphere cut at z >= 0.5 keeps the zone of height 0.5: area 2 pi r h = pi (to faceting).
    fine = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    cut = clip_mesh_to_box(fine, Box((-2, -2, 0.5), (2, 2, 2)))
    zone = fine.area / (4 * math.pi) * (2 * math.pi * 0.5)  # scale out the faceting of the sphere
    assert cut.area == pytest.approx(zone, rel=2e-3)


def test_surface_samples_are_uniform_by_area_and_deterministic():
    # Two squares of 1 and 3 m^2: a quarter of the samples on the small one.
    mesh = trimesh.util.concatenate([plane(0, 1, 0, 1), plane(2, 5, 0, 1)])
    a, face_a = sample_surface(mesh, 40_000.0, seed=7)
    b, _ = sample_surface(mesh, 40_000.0, seed=7)
    np.testing.assert_array_equal(a, b)
    assert len(a) == 160_000
    share = np.mean(a[:, 0] <= 1.0)
    assert share == pytest.approx(0.25, abs=4 * math.sqrt(0.25 * 0.75 / len(a)))
    # Inside a square, a sub-square of a quarter of its area gets a quarter of its samples.
    small = a[a[:, 0] <= 1.0]
    inner = np.mean((small[:, 0] < 0.5) & (small[:, 1] < 0.5))
    assert inner == pytest.approx(0.25, abs=4 * math.sqrt(0.25 * 0.75 / len(small)))


# --- Chamfer and F-score -----------------------------------------------------------------------


def test_chamfer_and_fscore_against_hand_values():
    # Ground truth: the plane [0, 2] x [0, 1]. Reconstruction: a 5 mm grid over the left half,
    # h = 3 cm above it. Hand values (derivation in the comments):
    h, s = 0.03, 0.005
    ground = plane(0, 2, 0, 1)
    points = grid(0, 1, 0, 1, s, z=h)
    settings = EvaluationSettings(
        completeness_thresholds_m=(0.02, 0.05, 0.075), gt_sample_density_per_m2=200_000.0, distance_cap_m=2.0
    )
    record = score_points(points, ground, Box((-0.1, -0.1, -0.5), (2.1, 1.1, 0.5)), settings)
    # Reconstruction -> ground truth: every point is exactly h away.
    assert record["chamfer_acc_m"] == pytest.approx(h, rel=1e-9)
    # Ground truth -> reconstruction: left half sqrt(h^2 + lateral^2), E[lateral^2] = s^2 / 6;
    # right half at x = 1 + u: sqrt(h^2 + u^2), mean over u in [0, 1] = (sqrt(h^2+1) + h^2 asinh(1/h)) / 2.
    left = math.sqrt(h * h + s * s / 6)
    right = 0.5 * (math.sqrt(h * h + 1) + h * h * math.asinh(1 / h))
    comp_mean = 0.5 * (left + right)
    assert record["chamfer_comp_m"] == pytest.approx(comp_mean, rel=5e-3)
    assert record["chamfer_m"] == pytest.approx(0.5 * (h + comp_mean), rel=5e-3)
    # Completeness at t: the left half plus the strip u <= sqrt(t^2 - h^2) of the right half.
    for t in (0.05, 0.075):
        recall = 100.0 * (1.0 + math.sqrt(t * t - h * h)) / 2.0
        key = threshold_key(t)
        assert record[f"comp_{key}"] == pytest.approx(recall, abs=0.3)
        assert record[f"prec_{key}"] == 100.0
        assert record[f"fscore_{key}"] == pytest.approx(2 * 100.0 * recall / (100.0 + recall), abs=0.3)
    # Below h nothing is within reach either way: precision, recall and F-score are 0.
    assert record["comp_020"] == 0.0 and record["prec_020"] == 0.0 and record["fscore_020"] == 0.0


# --- region, empty and bad input ---------------------------------------------------------------


def test_points_outside_the_region_are_excluded_and_counted(sphere):
    region = Box((-2, -2, -2), (2, 2, 2))
    samples, face = sample_surface(sphere, 2000.0, seed=3)
    inside = samples + 0.02 * sphere.face_normals[face]
    far = np.random.default_rng(0).uniform(3, 5, size=(500, 3))  # 2+ m off: would wreck accuracy
    nan_rows = np.full((7, 3), np.nan)
    base = score_points(inside, sphere, region, FULL)
    mixed = score_points(np.concatenate([inside, far, nan_rows]), sphere, region, FULL)
    assert mixed["n_points"] == len(inside) + 507
    assert mixed["n_points_in_region"] == len(inside)
    assert mixed["n_points_outside_region"] == 500
    assert mixed["n_points_nonfinite"] == 7
    assert mixed["fraction_outside_region"] == pytest.approx(500 / (len(inside) + 500))
    for key in ("acc50_m", "acc95_m", "comp_050", "comp_075", "chamfer_m", "fscore_050"):
        assert mixed[key] == base[key]


def test_record_does_not_depend_on_point_order(sphere):
    samples, face = sample_surface(sphere, 2000.0, seed=8)
    points = samples + np.random.default_rng(2).normal(scale=0.02, size=samples.shape)
    shuffled = points[np.random.default_rng(3).permutation(len(points))]
    a, b = score_points(points, sphere, BIG_BOX, FULL), score_points(shuffled, sphere, BIG_BOX, FULL)
    for key in ("acc50_m", "acc95_m", "acc_mean_m", "comp_050", "fscore_075", "chamfer_m"):
        assert a[key] == pytest.approx(b[key], rel=1e-12, abs=1e-15)


def test_empty_cloud_gives_nulls_and_a_warning(sphere, tmp_path):
    with pytest.warns(EmptyReconstructionWarning, match="no reconstructed point"):
        record = score_points(np.zeros((0, 3)), sphere, BIG_BOX)
    assert record["n_points"] == 0 and record["n_points_in_region"] == 0
    assert record["fraction_outside_region"] is None
    for key in ("acc90_m", "acc95_m", "acc_mean_m", "prec_050", "chamfer_m"):
        assert record[key] is None
    assert record["comp_050"] == 0.0 and record["fscore_050"] == 0.0
    # The same from an empty (but valid) PLY file, and JSON writes the nulls as null.
    empty = tmp_path / "empty.ply"
    empty.write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    with pytest.warns(EmptyReconstructionWarning):
        from_file = score_file(empty, GroundTruth("sphere", sphere, BIG_BOX))
    assert from_file["acc90_m"] is None and from_file["n_points"] == 0
    written = json.loads(write_metrics(tmp_path, from_file).read_text())
    assert written["acc90_m"] is None and written["comp_050"] == 0.0


def test_bad_files_raise_errors_naming_them(tmp_path, sphere):
    truth = GroundTruth("sphere", sphere, BIG_BOX)
    text = tmp_path / "notes.ply"
    text.write_text("these are my notes\n")
    with pytest.raises(ReconstructionFileError, match="notes.ply"):
        score_file(text, truth)
    other = tmp_path / "table.csv"
    other.write_text("1,2,3\n")
    with pytest.raises(ReconstructionFileError, match="table.csv.*unsupported"):
        score_file(other, truth)
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        score_file(tmp_path / "missing.ply", truth)
    garbage = tmp_path / "cloud.xyz"
    garbage.write_text("not numbers\n")
    with pytest.raises(ReconstructionFileError, match="cloud.xyz"):
        score_file(garbage, truth)


def test_mesh_files_score_vertices_or_surface_samples(tmp_path):
    ground = plane(0, 1, 0, 1)
    lifted = plane(0, 1, 0, 1, z=0.04)
    path = tmp_path / "recon.obj"
    lifted.export(path)
    points, kind = load_reconstruction(path)
    assert kind == "mesh_vertices" and len(points) == 4
    truth = GroundTruth("plane", ground, Box((-1, -1, -1), (2, 2, 1)))
    by_surface = score_file(path, truth, {"mesh_input": "surface", "mesh_sample_density_per_m2": 5000.0})
    assert by_surface["reconstruction_kind"] == "mesh_surface_samples"
    assert by_surface["n_points"] == 5000
    assert by_surface["acc95_m"] == pytest.approx(0.04, rel=1e-9)
    assert by_surface["comp_050"] == 100.0
    # a sampling past the limit is refused before it is drawn (a large proxy at 10,000/m^2 once
    # took 22 GB and the OOM killer)
    with pytest.raises(ValueError, match="needs 5000 samples, more than evaluate.max_gt_samples = 4999"):
        score_file(
            path,
            truth,
            {"mesh_input": "surface", "mesh_sample_density_per_m2": 5000.0, "max_gt_samples": 4999},
        )


# --- stage, record, cost, CLI ------------------------------------------------------------------


def test_rescoring_from_the_exported_region_mesh_reproduces_the_record(tmp_path, sphere):
    region = Box((-2, -2, -0.4), (2, 2, 2))
    samples, face = sample_surface(sphere, 3000.0, seed=5)
    points = samples + np.random.default_rng(1).normal(scale=0.01, size=samples.shape)
    cloud = tmp_path / "dense.ply"
    trimesh.PointCloud(points).export(cloud)
    record = evaluate_reconstruction(
        cloud, GroundTruth("sphere", sphere, region), {"visualise": {"enabled": False}}, tmp_path / "eval"
    )
    exported = trimesh.load(record["gt_mesh_path"], process=False)
    again = score_file(cloud, GroundTruth("sphere", exported, parse_region(record["eval_region"])))
    for key in (
        "acc90_m",
        "acc95_m",
        "comp_050",
        "comp_075",
        "chamfer_m",
        "n_gt_samples",
        "n_points_in_region",
    ):
        assert again[key] == record[key]
    assert parse_region(format_region(region)) == region


def test_write_metrics_is_flat_with_identity_and_versions(tmp_path):
    cfg = {"scene": {"name": "tomb"}, "planner": {"name": "ours"}, "seed": 3}
    path = write_metrics(
        tmp_path, {"acc90_m": np.float64(0.12), "n_images": np.int64(291), "bad": float("nan")}, cfg
    )
    record = json.loads(path.read_text())
    assert (record["scene"], record["planner"], record["seed"]) == ("tomb", "ours", 3)
    assert record["acc90_m"] == 0.12 and record["n_images"] == 291 and record["bad"] is None
    assert record["numpy_version"] == np.__version__ and record["open3d_version"] == "0.20.0"
    with pytest.raises(TypeError, match="'nested'"):
        write_metrics(tmp_path, {"nested": {"a": 1}})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]  # no temporary file left
    assert json.loads(path.read_text())["acc90_m"] == 0.12  # the failed write kept the old file


def test_metrics_record_the_code_revision(tmp_path, monkeypatch):
    git = shutil.which("git")
    if git is None or not (run_record.PROJECT_ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    head = subprocess.run(
        [git, "-C", str(run_record.PROJECT_ROOT), "rev-parse", "HEAD"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    record = json.loads(write_metrics(tmp_path, {"acc90_m": 0.1}).read_text())
    assert len(head) == 40 and record["code_commit"] == head
    assert isinstance(record["code_dirty"], bool)
    # Outside a checkout both are null rather than a wrong revision; the value is read once per process.
    run_record.code_revision.cache_clear()
    monkeypatch.setattr(run_record, "PROJECT_ROOT", tmp_path)
    try:
        assert run_record.code_revision() == {"code_commit": None, "code_dirty": None}
        monkeypatch.setattr(run_record, "PROJECT_ROOT", tmp_path / "elsewhere")
        assert run_record.code_revision()["code_commit"] is None  # cached, not re-read
    finally:
        run_record.code_revision.cache_clear()


def test_cli_scores_a_file_and_rejects_bad_input(tmp_path, capsys, sphere):
    gt = tmp_path / "gt.ply"
    sphere.export(gt)
    samples, face = sample_surface(sphere, 2000.0, seed=2)
    cloud = tmp_path / "cloud.npy"  # float64 (trimesh writes PLY coordinates as float32)
    np.save(cloud, samples + 0.03 * sphere.face_normals[face])
    out = tmp_path / "out"
    code = cli_main(
        [str(cloud), "--gt-mesh", str(gt), "--region=-2,-2,-2,2,2,2", "--out", str(out), "--no-vis"]
    )
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["acc90_m"] == pytest.approx(0.03, rel=1e-6)
    assert json.loads((out / "metrics.json").read_text())["comp_075"] == printed["comp_075"]
    bad = tmp_path / "bad.ply"
    bad.write_text("not a cloud")
    assert cli_main([str(bad), "--gt-mesh", str(gt), "--no-vis"]) == 2
    assert "bad.ply" in capsys.readouterr().err
    assert cli_main([str(cloud), "--gt-mesh", str(gt), "--region", "1,2,3"]) == 2
    assert "--region" in capsys.readouterr().err


def test_yaml_defaults_match_the_settings_dataclass():
    assert (
        EvaluationSettings.from_config(OmegaConf.load(ROOT / "conf/evaluate/default.yaml"))
        == EvaluationSettings()
    )
    full = EvaluationSettings.from_config(_load_group_config("full"))
    assert full.accuracy_percentiles == (50, 80, 90, 95)
    assert [threshold_key(t) for t in full.completeness_thresholds_m][::5] == ["005", "030", "055", "080"]
    with pytest.raises(ValueError, match="accuracy_percentile"):
        EvaluationSettings.from_config({"accuracy_percentile": [90]})
    with pytest.raises(ValueError, match="distance_cap_m"):
        EvaluationSettings(distance_cap_m=0.01)


# --- pictures ----------------------------------------------------------------------------------


def test_splat_draws_the_nearest_point_at_its_pixel():
    intrinsics = Intrinsics(64, 48, 60.0)
    viewpoint = np.array([0.0, 0.0, 0.0, 0.0, 0.0])  # looking along +x
    points = np.array([[5.0, 0.0, 0.0], [3.0, 0.0, 0.0], [4.0, 0.5, 0.0]])
    colors = np.array([[255, 0, 0], [0, 0, 255], [0, 255, 0]], np.uint8)
    image = splat(points, colors, viewpoint, intrinsics, radius_px=0)
    assert tuple(image[24, 32]) == (0, 0, 255)  # the blue point at 3 m hides the red one at 5 m
    column = int(np.floor(32 - 0.5 / 4.0 * intrinsics.focal_px))  # +y is image left
    assert tuple(image[24, column]) == (0, 255, 0)
    assert (image == 255).all(axis=2).sum() == 64 * 48 - 2
    # With 3 x 3 splats the blue square covers the red one entirely; the green one stands apart.
    image = splat(points, colors, viewpoint, intrinsics, radius_px=1)
    assert (image == (0, 0, 255)).all(axis=2).sum() == 9 and (image == (255, 0, 0)).all(axis=2).sum() == 0
    assert (image == (0, 255, 0)).all(axis=2).sum() == 9


@pytest.mark.parametrize("colorbar", [None, {"vmax_m": 0.2, "colormap": "turbo"}])
def test_view_pixels_cuts_a_saved_view_to_its_picture(tmp_path, colorbar):
    import matplotlib.pyplot as plt

    # A 60 x 40 px orange block in a white 300 x 200 view: the cut must be that block, scaled as the
    # axes scale the view, with no pixel of the title, colour bar or legend.
    view = np.full((200, 300, 3), 255, np.uint8)
    view[80:120, 100:160] = (255, 128, 0)
    path = save_view_png(tmp_path / "view.png", view, title="a long title " * 3, colorbar=colorbar)
    cut = view_pixels(plt.imread(path))[..., :3]
    scale = cut.shape[1] / 60.0
    assert 0.8 < scale < 2.0
    assert cut.shape[0] == pytest.approx(40 * scale, abs=2)
    inner = cut[2:-2, 2:-2]
    np.testing.assert_allclose(inner.reshape(-1, 3).mean(axis=0), [1.0, 128 / 255, 0.0], atol=0.02)


def test_error_visualisation_colours_and_files(tmp_path, sphere):
    rgb = error_colors(np.array([0.0, 0.1, 0.2, 5.0]), vmax_m=0.2, colormap="viridis")
    import matplotlib

    ends = (255 * np.array(matplotlib.colormaps["viridis"]([0.0, 1.0]))[:, :3] + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(rgb[[0, 2, 3]], ends[[0, 1, 1]])
    region = Box((-2, -2, -2), (2, 2, 2))
    samples, face = sample_surface(sphere, 500.0, seed=2)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(samples + 0.04 * sphere.face_normals[face]).export(cloud)
    settings = {"visualise": {"width": 160, "height": 120, "vmax_m": 0.2, "colormap": "viridis"}}
    record = evaluate_reconstruction(
        cloud, GroundTruth("sphere", sphere, region), settings, tmp_path / "eval"
    )
    import open3d as o3d

    colored = o3d.io.read_point_cloud(str(tmp_path / "eval" / "error_points.ply"))
    mid = (255 * np.array(matplotlib.colormaps["viridis"](0.2))[:3] + 0.5).astype(np.uint8)  # 0.04 / 0.2
    np.testing.assert_allclose(np.asarray(colored.colors) * 255, np.tile(mid, (len(samples), 1)), atol=1.01)
    coverage = o3d.io.read_point_cloud(str(tmp_path / "eval" / "gt_coverage.ply"))
    covered = np.asarray(coverage.colors)[:, 1] > 0.5
    assert 100.0 * covered.mean() == pytest.approx(record["comp_050"], abs=1e-9)
    pngs = sorted(p.name for p in (tmp_path / "eval").glob("*.png"))
    assert pngs == sorted([f"error_{v}.png" for v in VIEW_NAMES] + [f"coverage_{v}.png" for v in VIEW_NAMES])


@pytest.mark.parametrize("name", ["tomb", "church", "cathedral"])
def test_default_settings_can_score_every_procedural_scene(name):
    # The cathedral's region (about 30k m^2) once needed more samples than the default limit (then
    # 20M) allowed, so its cells failed in the evaluate stage after the whole reconstruction.
    from scene.registry import load_scene

    scene = load_scene(
        {"name": name, "seed": 0, "texture_size": 256, "small_texture_size": 256}, cache_dir=None
    )
    settings = EvaluationSettings.from_config(_load_group_config("default"))
    area = clip_mesh_to_box(scene.ground_truth_mesh, scene.evaluation_region).area
    assert area * settings.gt_sample_density_per_m2 <= settings.max_gt_samples
