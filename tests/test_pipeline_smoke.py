"""The whole pipeline, end to end, with the smoke preset: one scene, two planners, one shared proxy.

This is the CI run of issue 7: real rendering, real pycolmap SfM + dense, real planners, real
scoring, at small sizes (a few minutes on 2 cores).
"""

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def smoke_sweep(tmp_path_factory):
    base = tmp_path_factory.mktemp("smoke")
    sweep_dir, cache_dir = base / "multirun", base / "cache"
    # The README's example planner, from a package and a config directory outside the repository.
    outside = base / "my_planners"
    (outside / "conf" / "planner").mkdir(parents=True)
    shutil.copy(ROOT / "examples" / "orbit_planner.py", outside / "orbit_planner.py")
    shutil.copy(
        ROOT / "examples" / "conf" / "planner" / "orbit.yaml", outside / "conf" / "planner" / "orbit.yaml"
    )
    cmd = [
        sys.executable,
        "run.py",
        "-m",
        "experiment=smoke",
        "scene=tomb",
        "planner=lawnmower,ours,orbit",
        f"hydra.searchpath=[file://{outside / 'conf'}]",
        f"hydra.sweep.dir={sweep_dir}",
        f"cache_dir={cache_dir}",
    ]
    env = {**os.environ, "PYTHONPATH": str(outside)}
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800, env=env)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return sweep_dir, cache_dir


def test_every_cell_scores_finite_numbers(smoke_sweep):
    sweep_dir, _ = smoke_sweep
    records = [json.loads(p.read_text()) for p in sorted(sweep_dir.rglob("metrics.json"))]
    assert sorted(r["planner"] for r in records) == ["lawnmower", "orbit", "ours"]
    for r in records:
        assert r["status"] == "ok", r.get("error")
        assert r["scene"] == "tomb" and r["experiment"] == "smoke"
        for key in ("acc90_m", "acc95_m", "comp_050", "comp_075", "align_time_s", "flight_length_m"):
            assert math.isfinite(r[key]), key
        assert 0.0 < r["acc90_m"] <= r["acc95_m"]
        assert 0.0 <= r["comp_050"] <= r["comp_075"] <= 100.0
        assert r["n_images"] == r["n_viewpoints"] > 0
        # The matcher's ceiling beside the cell: the oracle at the same registered cameras, fused
        # alike, sees at least what the real matcher found; fusion ran in one chunk on this flight.
        assert math.isfinite(r["oracle_acc90_m"]) and r["oracle_comp_050"] >= r["comp_050"]
        assert r["oracle_n_depth_maps"] >= r["n_depth_maps"]  # every view with a partner gets one
        assert r["fusion_n_chunks"] == 1
        stages = ("plan_time_s", "render_time_s", "align_time_s", "dense_time_s", "eval_total_time_s")
        assert r["cell_wall_time_s"] >= sum(r[k] for k in stages)
        assert r["registered_fraction"] == pytest.approx(r["n_registered"] / r["n_images"])
        assert r["registered_fraction"] >= 0.2  # conf/reconstruct/default.yaml: min_registered_fraction
        run_dir = Path(r["eval_dir"]).parent
        if r["planner"] == "lawnmower":
            # The nadir-ish grid registers whole, so its cloud must sit on the ground truth: a frame
            # or scale slip anywhere in the chain would push the 95 % error far beyond 0.5 m. (At
            # smoke scale ours' close-range plan can register partly, with some images misplaced,
            # so its errors are only required to be finite.)
            assert r["registered_fraction"] >= 0.9
            assert r["acc95_m"] < 0.5
        n_rows = len((run_dir / "plan" / "viewpoints.csv").read_text().strip().splitlines()) - 1
        assert n_rows == r["n_images"]
        # The plan's own forecast, recorded before it is flown, in plan.json and metrics.json alike.
        forecast = json.loads((run_dir / "plan" / "plan.json").read_text())["predicted_coverage"]
        for surface in ("ground", "roofs", "walls"):
            key = f"predicted_well_observed_{surface}_pct"
            assert 0.0 <= r[key] <= 100.0 and forecast[key] == r[key], key
        # The flight-time model of the plan as flown (drone.model), in plan.json and
        # metrics.json alike; the plan exports to a mission with the same flights.
        plan_record = json.loads((run_dir / "plan" / "plan.json").read_text())
        assert r["flight_time_s"] == plan_record["flight_time_s"] > r["n_images"] * 1.5  # >= a photo each
        assert r["n_batteries"] == plan_record["n_batteries"] == len(plan_record["flight_times_s"]) >= 1
        from mission.__main__ import main as mission_main

        assert mission_main([str(run_dir), "--format", "wpml", "--out", str(run_dir / "m.kmz")]) == 0
        assert len(list(run_dir.glob("m*.kmz"))) == r["n_batteries"]
    # One scene, one fingerprint (32 hex digits of what the cameras see) in every cell's record.
    assert len({r["scene_fingerprint"] for r in records}) == 1
    assert len(records[0]["scene_fingerprint"]) == 32
    by_planner = {r["planner"]: r for r in records}
    # ours plans close, frontal wall views; the lawnmower's grid does not.
    walls = "predicted_well_observed_walls_pct"
    assert by_planner["ours"][walls] > by_planner["lawnmower"][walls] + 10.0


def test_the_committed_proxy_is_installed_once_and_planned_on(smoke_sweep):
    sweep_dir, cache_dir = smoke_sweep
    records = [json.loads(p.read_text()) for p in sorted(sweep_dir.rglob("metrics.json"))]
    assert sorted(r["proxy_cache_hit"] for r in records) == [False, True, True]
    # only cache_hit tells a hit; the build's own work-folder reuse flags would read false on both
    assert not any({"proxy_cached", "proxy_proxy_cached"} & r.keys() for r in records)
    assert len({r["proxy_entry"] for r in records}) == 1
    # proxies/smoke/tomb/seed0, not an exploration of this machine's (pipeline.proxy_bundle)
    assert {r["proxy_bundle"] for r in records} == {"proxies/smoke/tomb/seed0"}
    assert len(list((cache_dir / "exploration_bundle").glob("*/COMPLETE.json"))) == 1
    assert not (cache_dir / "exploration").exists()
    manifest = json.loads((ROOT / "proxies" / "smoke" / "tomb" / "seed0" / "manifest.json").read_text())
    assert {r["proxy_fingerprint"] for r in records} == {manifest["mesh_fingerprint"]}


def test_the_smoke_cells_are_golden(smoke_sweep):
    """Protocol 1's code end to end (tests/golden_records.py): a change that moves these is a bug or
    a protocol bump (results/protocol.md)."""
    from tests.golden_records import CELL_FIELDS, CELLS_FILE, cell_differences

    sweep_dir, _ = smoke_sweep
    records = {r["planner"]: r for r in (json.loads(p.read_text()) for p in sweep_dir.rglob("metrics.json"))}
    golden = json.loads(CELLS_FILE.read_text())
    measured = {p: {k: records[p].get(k) for k in CELL_FIELDS} for p in golden}
    for planner, values in golden.items():
        differences = cell_differences(records[planner], values)
        assert not differences, (
            f"the smoke {planner} cell moved (a bug, or a protocol bump: results/protocol.md; the golden "
            "values come from an AMD EPYC, another processor measures its spread first): "
            f"{differences}; measured {json.dumps(measured)}"
        )
    assert records["ours"]["protocol"] is None  # the smoke preset is not the protocol's
    assert records["ours"]["planner_version"] == 1


def test_tables_from_the_sweep(smoke_sweep, tmp_path):
    sweep_dir, _ = smoke_sweep
    out = subprocess.run(
        [sys.executable, "-m", "experiments.tables", str(sweep_dir), "--out", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    for name in ("table1", "table2"):
        for ext in ("md", "tex", "csv"):
            assert (tmp_path / f"{name}.{ext}").is_file()
    records = {r["planner"]: r for r in (json.loads(p.read_text()) for p in sweep_dir.rglob("metrics.json"))}
    table1 = pd.read_csv(tmp_path / "table1.csv")
    assert sorted(set(table1["planner"])) == ["lawnmower", "orbit", "ours"]
    assert "| Orbit |" in (tmp_path / "tables.md").read_text()  # a planner from outside, in the tables
    for row in table1.itertuples():
        assert row.mean == pytest.approx(records[row.planner][row.metric], rel=1e-9)
    table2 = pd.read_csv(tmp_path / "table2.csv").set_index(["planner", "metric"])
    for planner, r in records.items():
        assert table2.loc[(planner, "n_images"), "mean"] == r["n_images"]


def _lawnmower_run(sweep_dir: Path) -> tuple[Path, dict]:
    for path in sweep_dir.rglob("metrics.json"):
        record = json.loads(path.read_text())
        if record["planner"] == "lawnmower":
            return path.parent, record
    raise AssertionError("no lawnmower cell in the smoke sweep")


def _stage(stage: str, run_dir: Path, out: Path, capsys) -> dict:
    from pipeline.stages import main as stage_main

    capsys.readouterr()
    assert stage_main([stage, str(run_dir), "--out", str(out)]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def test_the_render_stage_command_reproduces_the_cells_images(smoke_sweep, tmp_path, capsys):
    run_dir, record = _lawnmower_run(smoke_sweep[0])
    again = _stage("render", run_dir, tmp_path, capsys)
    assert again["n_images"] == record["n_images"]
    kept = sorted(p.name for p in (run_dir / "images").glob("*.png"))
    assert sorted(p.name for p in (tmp_path / "images").glob("*.png")) == kept
    for name in kept:
        assert (tmp_path / "images" / name).read_bytes() == (run_dir / "images" / name).read_bytes(), name
    # cameras.json: the same cameras (its render timings are this run's)
    cameras = [json.loads((d / "images" / "cameras.json").read_text()) for d in (tmp_path, run_dir)]
    assert cameras[0]["images"] == cameras[1]["images"]
    assert cameras[0]["intrinsics"] == cameras[1]["intrinsics"]


def test_the_dense_and_evaluate_stage_commands_reproduce_the_cells_cloud_and_scores(
    smoke_sweep, tmp_path, capsys
):
    """The dense stage on the cell's own aligned model and images: the same cloud, byte for byte
    (the preset is deterministic); scored again: the same numbers."""
    run_dir, record = _lawnmower_run(smoke_sweep[0])
    dense = _stage("dense", run_dir, tmp_path, capsys)
    assert dense["n_dense_points"] == record["n_dense_points"]
    assert (tmp_path / "recon" / "dense.ply").read_bytes() == (run_dir / "recon" / "dense.ply").read_bytes()
    scores = _stage("evaluate", run_dir, tmp_path, capsys)
    for key in ("acc90_m", "acc95_m", "comp_050", "comp_075", "n_points"):
        assert scores[key] == record[key], key


@pytest.mark.slow  # SfM of the 70 images again: minutes on 2 cores
def test_the_sfm_stage_command_reproduces_the_cells_aligned_model(smoke_sweep, tmp_path, capsys):
    import numpy as np
    import pycolmap

    run_dir, record = _lawnmower_run(smoke_sweep[0])
    sfm = _stage("sfm", run_dir, tmp_path, capsys)
    for key in ("n_registered", "n_sparse_points", "position_error_median_m", "rotation_error_median_deg"):
        assert sfm[key] == record[key], key
    ours, theirs = (pycolmap.Reconstruction(d / "recon" / "sparse") for d in (tmp_path, run_dir))
    centres = {ours.image(i).name: ours.image(i).projection_center() for i in ours.reg_image_ids()}
    for image_id in theirs.reg_image_ids():
        image = theirs.image(image_id)
        np.testing.assert_array_equal(centres[image.name], image.projection_center())
