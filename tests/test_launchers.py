"""The launcher presets (conf/hydra/launcher): each composes; a 2 x 2 sweep completes on each local engine.

The sweeps run a small Hydra app that uses the repository's preset files unchanged and writes one
metrics.json per cell, so the presets are tested without the minutes a real cell takes.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PRESETS = REPO / "conf" / "hydra" / "launcher"

APP = """
import json, os
from pathlib import Path
import hydra
from hydra.core.hydra_config import HydraConfig

@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg):
    out = Path(HydraConfig.get().runtime.output_dir)
    record = {"scene": cfg.scene, "planner": cfg.planner, "seed": cfg.seed, "pid": os.getpid(),
              "launcher": HydraConfig.get().launcher._target_}
    (out / "metrics.json").write_text(json.dumps(record))
    if cfg.fail == f"{cfg.scene}/{cfg.planner}":  # like run.py: record the cell, then raise
        raise RuntimeError("this cell fails")

if __name__ == "__main__":
    main()
"""

CONFIG = """
scene: tomb
planner: ours
seed: 0
fail: none
hydra:
  sweep:
    dir: sweep
    subdir: ${scene}/${planner}/seed${seed}
  job:
    chdir: false
"""


@pytest.fixture
def app(tmp_path):
    (tmp_path / "conf" / "hydra").mkdir(parents=True)
    shutil.copytree(PRESETS, tmp_path / "conf" / "hydra" / "launcher")
    (tmp_path / "conf" / "config.yaml").write_text(CONFIG)
    (tmp_path / "app.py").write_text(APP)
    return tmp_path


def hydra_run(app: Path, *args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}
    return subprocess.run(
        [sys.executable, "app.py", *args], cwd=app, env=env, capture_output=True, text=True, timeout=timeout
    )


def launcher_config(app: Path, preset: str) -> dict:
    result = hydra_run(app, f"hydra/launcher={preset}", "--cfg", "hydra", "-p", "hydra.launcher")
    assert result.returncode == 0, result.stderr
    return yaml.safe_load(result.stdout)


def test_the_four_presets():
    names = sorted(p.stem for p in PRESETS.glob("*.yaml"))
    assert names == ["local", "ray_cluster", "ray_local", "slurm"]


def test_local_preset_is_joblib_with_two_jobs(app):
    config = launcher_config(app, "local")
    assert config["_target_"] == "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    assert config["n_jobs"] == 2 and config["prefer"] == "processes"


@pytest.mark.parametrize(
    ("preset", "plugin", "target"),
    [
        (
            "ray_local",
            "hydra_plugins.hydra_ray_launcher",
            "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
        ),
        (
            "ray_cluster",
            "hydra_plugins.hydra_ray_launcher",
            "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
        ),
        (
            "slurm",
            "hydra_plugins.hydra_submitit_launcher",
            "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
        ),
    ],
)
def test_cluster_presets_compose(app, preset, plugin, target):
    pytest.importorskip(plugin, reason=f"{plugin} not installed (optional extra)")
    config = launcher_config(app, preset)
    assert config["_target_"] == target
    if preset == "ray_local":
        assert config["ray"]["init"]["address"] is None and config["ray"]["remote"]["num_cpus"] == 1
    elif preset == "ray_cluster":
        assert config["ray"]["init"]["address"] == "auto"
    else:
        assert (config["timeout_min"], config["cpus_per_task"], config["mem_gb"]) == (480, 8, 32)


def check_sweep(app: Path, target: str) -> None:
    records = [json.loads(p.read_text()) for p in sorted((app / "sweep").rglob("metrics.json"))]
    cells = sorted((r["scene"], r["planner"]) for r in records)
    assert cells == [("church", "ours"), ("church", "smith"), ("tomb", "ours"), ("tomb", "smith")]
    for record in records:
        run_dir = app / "sweep" / record["scene"] / record["planner"] / f"seed{record['seed']}"
        assert (run_dir / "metrics.json").is_file()
        assert record["launcher"] == target
    # The cells ran in worker processes, not in the process that launched the sweep.
    assert os.getpid() not in {r["pid"] for r in records}


@pytest.mark.parametrize("fail", ["none", "tomb/smith"])
def test_joblib_sweep_2x2(app, fail):
    result = hydra_run(
        app, "-m", "hydra/launcher=local", "scene=tomb,church", "planner=ours,smith", f"fail={fail}"
    )
    # A failed cell fails the sweep's exit status but does not stop the other cells.
    assert (result.returncode == 0) == (fail == "none"), result.stderr
    check_sweep(app, "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher")


# The failing variant starts a second Ray instance (~20 s): slow.
@pytest.mark.parametrize("fail", ["none", pytest.param("tomb/smith", marks=pytest.mark.slow)])
def test_ray_local_sweep_2x2(app, fail):
    pytest.importorskip("hydra_plugins.hydra_ray_launcher", reason="the `ray` extra is not installed")
    result = hydra_run(
        app, "-m", "hydra/launcher=ray_local", "scene=tomb,church", "planner=ours,smith", f"fail={fail}"
    )
    assert (result.returncode == 0) == (fail == "none"), result.stderr
    check_sweep(app, "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher")
