"""The console commands: each answers --help and does one real job with numbers checked."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from benchmarks.cli import COMMANDS as BENCH_COMMANDS
from experiments.cli import COMMANDS as STUDY_COMMANDS
from experiments.diagnose_cli import COMMANDS as DIAGNOSE_COMMANDS
from pipeline.cli import dispatch
from scene.plan import Plan, read_viewpoints, write_plan

ROOT = Path(__file__).resolve().parents[1]
# The console commands as pyproject.toml declares them, run from this checkout's code (an installed
# script may point at another checkout, or not exist yet).
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
COMMANDS = tuple(SCRIPTS)
RESULTS_FIXTURE = ROOT / "tests" / "data" / "results_study"


def command(name: str, *args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    module, function = SCRIPTS[name].split(":")
    call = f"import sys; sys.argv[0] = {name!r}; from {module} import {function}; sys.exit({function}())"
    return subprocess.run(
        [sys.executable, "-c", call, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.parametrize("name", COMMANDS)
def test_every_console_command_answers_help(name):
    out = command(name, "--help")
    assert out.returncode == 0, out.stderr
    assert "usage:" in out.stdout


@pytest.mark.parametrize(
    ("prog", "commands"),
    [
        ("uavplan-study", STUDY_COMMANDS),
        ("uavplan-diagnose", DIAGNOSE_COMMANDS),
        ("uavplan-bench", BENCH_COMMANDS),
    ],
)
def test_every_sub_command_answers_help(prog, commands, capsys):
    for name in commands:
        with pytest.raises(SystemExit) as stop:
            dispatch(prog, commands, [name, "--help"], "")
        assert stop.value.code == 0, name
        assert f"usage: {prog} {name}" in capsys.readouterr().out, name


def test_an_unknown_sub_command_is_refused_with_the_list():
    out = command("uavplan-study", "tabels")
    assert out.returncode == 2
    assert "unknown command 'tabels'" in out.stderr and "tables" in out.stderr


def test_uavplan_run_composes_the_cell_config():
    out = command("uavplan", "run", "--cfg", "job", "scene=church", "planner=smith", "seed=3")
    assert out.returncode == 0, out.stderr
    cfg = yaml.safe_load(out.stdout)
    assert (cfg["scene"]["name"], cfg["planner"]["name"], cfg["seed"]) == ("church", "smith", 3)


def test_uavplan_study_results_regenerates_the_fixture_tables(tmp_path):
    out = command(
        "uavplan-study",
        "results",
        "fixture",
        "--cells",
        str(RESULTS_FIXTURE / "cells"),
        "--out",
        str(tmp_path),
    )
    assert out.returncode == 0, out.stderr
    expected = RESULTS_FIXTURE / "expected" / "fixture" / "tables" / "table1.md"
    assert (tmp_path / "fixture" / "tables" / "table1.md").read_text() == expected.read_text()


def test_uavplan_bench_evaluate_scores_its_constructed_cloud():
    out = command("uavplan-bench", "evaluate", "--points", "20000", "--grid", "60")
    assert out.returncode == 0, out.stderr
    # The cloud is the terrain sampled with 2 cm noise and 3 % outliers: its 90 % error is a few cm.
    line = next(line for line in out.stdout.splitlines() if "acc90" in line)
    acc90 = float(line.split("acc90")[1].split()[0].strip("=:m"))
    assert 0.01 < acc90 < 0.06, line


def test_uavplan_mission_exports_waypoints_at_the_plan_positions(tmp_path):
    from pyproj import Transformer

    views = np.array([[0, 0, 20, 0, -45], [30, 0, 20, 90, -45], [30, 30, 25, 180, -60]], float)
    write_plan(Plan(views, ["view"] * 3, "test", {}), tmp_path / "plan")
    out = command(
        "uavplan-mission",
        str(tmp_path),
        "--format",
        "litchi",
        "--out",
        str(tmp_path / "m.csv"),
        "--origin",
        "47.0,8.0,400,90",
    )
    assert out.returncode == 0, out.stderr
    rows = (tmp_path / "m.csv").read_text().strip().splitlines()[1:]
    lat = np.array([float(r.split(",")[0]) for r in rows])
    lon = np.array([float(r.split(",")[1]) for r in rows])
    to_enu = Transformer.from_crs("EPSG:4326", "+proj=tmerc +lat_0=47 +lon_0=8 +ellps=WGS84", always_xy=True)
    east, north = to_enu.transform(lon, lat)
    np.testing.assert_allclose(east, views[:, 0], atol=0.05)
    np.testing.assert_allclose(north, views[:, 1], atol=0.05)


def test_uavplan_evaluate_scores_a_cloud_on_its_own_mesh(tmp_path):
    box = trimesh.creation.box(extents=(4.0, 4.0, 2.0))
    box.apply_translation((0, 0, 1.0))
    box.export(tmp_path / "gt.ply")
    points = box.sample(20000, seed=0) + np.array([0.0, 0.0, 0.01])  # every point 1 cm off (up)
    trimesh.PointCloud(points).export(tmp_path / "cloud.ply")
    out = command(
        "uavplan-evaluate",
        str(tmp_path / "cloud.ply"),
        "--gt-mesh",
        str(tmp_path / "gt.ply"),
        "--region=-3,-3,-1,3,3,3",
        "--out",
        str(tmp_path / "scored"),
    )
    assert out.returncode == 0, out.stderr
    record = json.loads((tmp_path / "scored" / "metrics.json").read_text())
    assert record["acc90_m"] == pytest.approx(0.01, abs=2e-3)


def test_uavplan_render_writes_the_viewpoint_images(tmp_path):
    views = np.array([[0, -40, 20, 90, -30], [40, 0, 20, 180, -30]], float)
    write_plan(Plan(views, ["view"] * 2, "test", {}), tmp_path / "plan")
    out = command(
        "uavplan-render",
        "tomb",
        str(tmp_path / "plan" / "viewpoints.csv"),
        str(tmp_path / "img"),
        "--width",
        "160",
        "--height",
        "120",
    )
    assert out.returncode == 0, out.stderr
    from scene.cameras_file import read_cameras

    cameras = read_cameras(tmp_path / "img")
    assert cameras.names == ("000000.png", "000001.png")
    np.testing.assert_allclose(cameras.viewpoints, read_viewpoints(tmp_path / "plan" / "viewpoints.csv")[0])
