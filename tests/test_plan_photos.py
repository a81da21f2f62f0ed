"""``uavplan plan-photos`` on 20 photos of a ground plane: the proxy lies at z = 0, missions out."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_dir

from experiments.photo_roundtrip import photos_from_flight
from mission.geo import SurveyOrigin

ROOT = Path(__file__).resolve().parents[1]
ORIGIN = SurveyOrigin(47.397742, 8.545594, 488.0, "amsl", 90.0)


@pytest.fixture(scope="module")
def ground_photos(tmp_path_factory) -> Path:
    """20 nadir photos (4 x 5, 24 m up, 480 x 360) of the tomb's textured ground east of it."""
    from render import RenderSettings, render_flight
    from scene.camera import Intrinsics
    from scene.registry import load_scene

    base = tmp_path_factory.mktemp("photos")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("config", overrides=["experiment=smoke", "scene=tomb"])
    scene = load_scene(cfg.scene, cache_dir=base / "cache")
    xs, ys = np.meshgrid(np.linspace(32.0, 50.0, 4), np.linspace(-12.0, 12.0, 5))
    vps = np.column_stack([xs.ravel(), ys.ravel(), np.full(20, 24.0), np.zeros(20), np.full(20, -90.0)])
    render_flight(
        scene, vps, Intrinsics(480, 360, 60.0), base / "render", RenderSettings.from_config(cfg.render)
    )
    return photos_from_flight(base / "render", base / "jpeg", ORIGIN, gnss_sigma_m=0.02)


def test_twenty_photos_of_a_plane_give_a_proxy_at_z0_and_missions(ground_photos, tmp_path):
    run_dir = tmp_path / "run"
    out = subprocess.run(
        [
            str(Path(sys.executable).parent / "uavplan"),
            "plan-photos",
            str(ground_photos),
            "experiment=smoke",
            "planner=ours",
            "photos.min_photos=10",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["photos"]["n_used"] == 20 and report["photos"]["n_left_out"] == 0
    assert report["registration"]["n_registered"] == 20 and report["registration"]["not_registered"] == []
    # The frame at take-off: the first photo's position at the photos' take-off height (488 m).
    assert report["origin"]["height_m"] == pytest.approx(488.0, abs=0.05)
    assert report["registration"]["gnss_residual_median_m"] < 0.05  # 2 cm GNSS noise
    proxy = trimesh.load(run_dir / "proxy.ply", force="mesh")
    assert abs(float(np.median(proxy.vertices[:, 2]))) < 0.05  # the ground plane ends at z = 0
    for name in ("mission.plan", "mission.csv", "mission.kmz"):
        assert list((run_dir / "missions").glob(name.replace(".", "*."))), name


SHARED_FLIGHT = ROOT.parent / "shared" / "data" / "photos" / "brighton_beach"


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_FLIGHT.is_dir(), reason="the shared Phantom 3 flight is not here")
def test_the_shared_phantom_3_flight_plans_as_documented_with_nothing_else_typed(tmp_path):
    """``uavplan plan-photos ../shared/data/photos/brighton_beach planner=ours``: a consumer DJI
    Phantom 3, 18 nadir photos, no RTK: registered, within 120 m of take-off, three missions, a PNG."""
    run_dir = tmp_path / "run"
    out = subprocess.run(
        [
            str(Path(sys.executable).parent / "uavplan"),
            "plan-photos",
            str(SHARED_FLIGHT),
            "planner=ours",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["settings_used"]["gnss"]["name"] == "consumer"
    assert report["settings_used"]["gnss"]["sigma_m"] == 2.0
    assert report["registration"]["n_registered"] >= 17
    assert report["registration"]["gnss_residual_median_m"] < 6.0  # the gate: 3 x 2 m
    assert report["origin"]["height_m"] == pytest.approx(
        158.5, abs=0.1
    )  # AbsoluteAltitude - RelativeAltitude
    heights = np.loadtxt(run_dir / "plan" / "viewpoints.csv", delimiter=",", skiprows=1, usecols=3)
    assert heights.max() <= 120.0 + 1e-6 and heights.min() >= 2.0 - 1e-6
    assert report["waypoints"]["height_max_m"] <= 120.0
    for name in ("mission.plan", "mission.csv", "mission.kmz"):
        assert list((run_dir / "missions").glob(name.replace(".", "*."))), name
    assert (run_dir / "flight.png").stat().st_size > 10_000
