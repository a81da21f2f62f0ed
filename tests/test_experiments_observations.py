"""How closely flights observe the ground truth: a wall, three close frontal views and a far one."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from evaluate.settings import EvaluationSettings
from experiments import observations
from pipeline.forecast import ObservationCriteria, observation_shares
from scene.camera import Intrinsics
from scene.cameras_file import write_cameras
from tests.experiments_fixtures import write_run

INTRINSICS = Intrinsics(1024, 768, 60.0)
TARGET_DISTANCE_M = 20.0
# Three views 20 m in front of the wall (every sample within 21.8 m and 23 deg of its normal, inside
# each image), one 60 m away.
CLOSE = [[20.0, -2.0, 6.0, 180.0, 0.0], [20.0, 0.0, 6.0, 180.0, 0.0], [20.0, 2.0, 6.0, 180.0, 0.0]]
FAR = [[60.0, 0.0, 6.0, 180.0, 0.0]]


def wall() -> trimesh.Trimesh:
    """A 10 x 10 m wall in the plane x = 0 (y in [-5, 5], z in [1, 11]) facing +x."""
    vertices = np.array([[0, -5, 1], [0, 5, 1], [0, 5, 11], [0, -5, 11]], float)
    mesh = trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)
    assert np.allclose(mesh.face_normals, [1, 0, 0])
    return mesh


def shares(views, **criteria):
    table = observation_shares(
        wall(),
        np.array(views),
        INTRINSICS,
        TARGET_DISTANCE_M,
        ObservationCriteria(n_samples=400, **criteria),
        EvaluationSettings(),
    )
    return table.set_index("surface")


def test_close_frontal_views_observe_the_wall_and_far_ones_only_see_it():
    table = shares(CLOSE + FAR)
    assert table.loc["walls", "n_samples"] == 400 and table["n_samples"].sum() == 400
    assert table.loc["walls", "well_observed_pct"] == 100.0 and table.loc["walls", "seen_pct"] == 100.0
    assert table.loc["walls", "median_views"] == 4.0
    assert np.isnan(table.loc["ground", "well_observed_pct"])  # no ground in this scene
    # A fourth view is required: the far one sees every sample but is past 1.3 d_t = 26 m.
    four = shares(CLOSE + FAR, min_views=4)
    assert four.loc["walls", "well_observed_pct"] == 0.0 and four.loc["walls", "seen_pct"] == 100.0
    # 70 m reach (3.5 d_t) lets the far view count.
    assert (
        shares(CLOSE + FAR, min_views=4, max_distance_factor=3.5).loc["walls", "well_observed_pct"] == 100.0
    )
    # Two close views and the far one: seen by three, observed well by two.
    two = shares(CLOSE[:2] + FAR)
    assert two.loc["walls", "well_observed_pct"] == 0.0 and two.loc["walls", "seen_pct"] == 100.0


def test_grazing_views_do_not_observe_well():
    # 20 m off the wall's plane and 34.6 m along it, looking at its centre: 56-63 deg off the normal.
    grazing = [[20.0, -34.6, 6.0, 120.0, 0.0]] * 3
    table = shares(grazing, max_distance_factor=3.0, max_incidence_deg=55.0)
    assert table.loc["walls", "well_observed_pct"] == 0.0 and table.loc["walls", "seen_pct"] == 100.0
    assert (
        shares(grazing, max_distance_factor=3.0, max_incidence_deg=70.0).loc["walls", "well_observed_pct"]
        > 50
    )


def write_wall_run(root, planner, views, names=None):
    run_dir = write_run(root, "wallscene", planner, 0, acc90_m=0.1)
    (run_dir / "eval").mkdir()
    wall().export(run_dir / "eval" / "gt_region.ply")
    names = names or [f"{i:06d}.png" for i in range(len(views))]
    (run_dir / "images").mkdir()
    write_cameras(run_dir / "images", names, views, INTRINSICS, ["view"] * len(names))
    gsd = TARGET_DISTANCE_M / INTRINSICS.focal_px
    (run_dir / ".hydra").mkdir()
    camera = "camera:\n  width: 1024\n  height: 768\n  hfov_deg: 60.0\n"
    (run_dir / ".hydra" / "config.yaml").write_text(f"{camera}survey:\n  target_gsd_m: {gsd!r}\nseed: 0\n")
    return run_dir


def test_only_registered_views_count_and_the_cli_writes_the_table(tmp_path, monkeypatch, capsys):
    root = tmp_path / "study"
    write_wall_run(root, "ours", CLOSE + FAR)
    write_wall_run(root, "lawnmower", CLOSE + FAR)
    # SfM registered all of ours' views but one close view of the lawnmower's.
    models = {"ours": None, "lawnmower": {"000000.png", "000002.png", "000003.png"}}
    monkeypatch.setattr(
        observations, "registered_image_names", lambda sparse: models[sparse.parent.parent.parent.name]
    )
    out = tmp_path / "out"
    assert observations.main([str(root), "--out", str(out), "--samples", "300"]) == 0
    frame = observations.observations_frame([root], ObservationCriteria(n_samples=300))
    walls = frame[frame.surface == "walls"].set_index("planner")
    assert walls.loc["ours", "well_observed_pct"] == 100.0 and walls.loc["ours", "n_views"] == 4
    assert walls.loc["lawnmower", "well_observed_pct"] == 0.0 and walls.loc["lawnmower", "n_views"] == 3
    assert walls.loc["ours", "max_distance_m"] == pytest.approx(26.0)
    table = (out / "observations.md").read_text()
    assert "| Wallscene | Lawnmower | 3 / 4 | n/a | n/a | 0 / 100 | n/a |" in table
    assert "| Wallscene | Ours | all 4 | n/a | n/a | 100 / 100 | n/a |" in table
    assert len((out / "observations.csv").read_text().splitlines()) == 1 + 2 * 4


def test_a_run_without_its_scored_ground_truth_is_a_clear_error(tmp_path, capsys):
    run_dir = write_wall_run(tmp_path / "study", "ours", CLOSE)
    (run_dir / "eval" / "gt_region.ply").unlink()
    assert observations.main([str(tmp_path / "study"), "--out", str(tmp_path / "out")]) == 2
    assert "gt_region.ply: missing (the run was not scored)" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="max_incidence_deg"):
        ObservationCriteria(max_incidence_deg=85.0)
