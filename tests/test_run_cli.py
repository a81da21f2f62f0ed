"""The Hydra entry point: composed config, and refusal of unknown scenes and planners."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def run_py(*args, cwd=ROOT, timeout=120):
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )


def test_cfg_job_prints_composed_config():
    out = run_py("--cfg", "job", "scene=church", "planner=smith", "seed=3")
    assert out.returncode == 0, out.stderr
    cfg = yaml.safe_load(out.stdout)
    assert cfg["scene"]["name"] == "church"
    assert cfg["planner"]["name"] == "smith"
    assert cfg["seed"] == 3
    assert {"scene", "planner", "render", "reconstruct", "evaluate", "experiment", "exploration"} <= set(cfg)
    assert cfg["camera"] == {"width": 1024, "height": 768, "hfov_deg": 60.0}


def test_paper_preset_overrides_camera():
    out = run_py("--cfg", "job", "experiment=paper")
    assert out.returncode == 0, out.stderr
    cfg = yaml.safe_load(out.stdout)
    assert (cfg["camera"]["width"], cfg["camera"]["height"]) == (2048, 1536)
    assert cfg["experiment"]["name"] == "paper"


def test_degraded_proxy_option():
    out = run_py("--cfg", "job", "proxy=ground_truth_degraded")
    assert out.returncode == 0, out.stderr
    assert yaml.safe_load(out.stdout)["reconstruct"]["proxy"]["source"] == "ground_truth_degraded"


@pytest.mark.parametrize(
    ("override", "known"),
    [
        ("scene=atlantis", ["tomb", "church", "cathedral", "mesh"]),
        ("planner=magic", ["ours", "smith", "yan", "lawnmower"]),
    ],
)
def test_unknown_choice_is_refused_with_the_known_ones(override, known):
    out = run_py(override)
    assert out.returncode != 0
    for name in known:
        assert name in out.stderr, out.stderr
