"""The run's one flat ``metrics.json`` (the run-directory contract: docs/architecture.md)."""

from __future__ import annotations

import functools
import math
import os
import platform
import subprocess
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path

from scene.io import write_json_atomic

METRICS_FILE = "metrics.json"
PROJECT_ROOT = Path(__file__).resolve().parents[1]
# Libraries whose versions go into every record (the numbers depend on them).
RECORDED_LIBRARIES = (
    "numpy",
    "scipy",
    "trimesh",
    "open3d",
    "pycolmap",
    "mujoco",
    "cma",
    "elkai",
    "opencv-python-headless",
)


def library_versions() -> dict:
    """``{"python_version": ..., "numpy_version": ..., ...}``; None for a library that is not installed."""
    versions = {"python_version": platform.python_version()}
    for name in RECORDED_LIBRARIES:
        try:
            version = metadata.version(name)
        except metadata.PackageNotFoundError:
            version = None
        versions[f"{name.split('-')[0]}_version"] = version
    return versions


@functools.cache
def machine_info() -> dict:
    """``{"machine_cpu": <model name>, "machine_cpus": <logical CPUs this process may use>}``: what
    the timings of a record were measured on."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"machine_cpu": model, "machine_cpus": cpus}


def git(*args: str, repo: Path | None = None) -> str | None:
    """The stripped output of ``git -C repo args`` (default: the project); None when it fails or git
    is missing."""
    repo = PROJECT_ROOT if repo is None else repo
    try:
        done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.cache
def code_revision() -> dict:
    """``{"code_commit": <40-hex>, "code_dirty": bool}`` of the project's git checkout.

    Read once per process: a process runs the code it imported when it started, so run.py reads it
    at the start of a cell and a later commit in the same tree does not relabel the cell.
    ``code_dirty`` is true when tracked files differ from the commit. Both are None outside a git
    checkout or without git.
    """

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"code_commit": commit, "code_dirty": None if status is None else bool(status)}


def run_identity(cfg: Mapping | None) -> dict:
    """``scene``, ``planner``, ``seed``, ``experiment`` from a composed run config (None where absent)."""
    cfg = cfg or {}

    def name(group: str):
        value = cfg.get(group)
        return value.get("name") if isinstance(value, Mapping) else value

    seed = cfg.get("seed")
    return {
        "scene": name("scene"),
        "planner": name("planner"),
        "seed": int(seed) if seed is not None else None,
        "experiment": name("experiment"),
    }


def write_metrics(run_dir: str | Path, record: Mapping, cfg: Mapping | None = None) -> Path:
    """Write ``run_dir/metrics.json`` atomically: the flat ``record``, plus the config's
    scene/planner/seed where the record lacks them, plus the library versions, the machine and the
    code revision.

    Args:
        run_dir: the run directory.
        record: flat mapping of str -> None/bool/int/float/str (numpy scalars accepted); NaN and
            infinity are written as null (JSON has neither).
        cfg: the composed run config as a plain mapping (``OmegaConf.to_container(cfg)``), or None.

    Returns:
        The path of ``metrics.json``.

    Raises:
        TypeError: a value is not a scalar (the record must stay flat), naming its key.
    """
    out: dict = {}
    for key, value in run_identity(cfg).items():
        if value is not None:
            out[key] = value
    for key, value in record.items():
        if not isinstance(key, str):
            raise TypeError(f"metrics record keys must be strings, got {key!r}")
        out[key] = _scalar(key, value)
    for key, value in {**library_versions(), **machine_info(), **code_revision()}.items():
        out.setdefault(key, value)
    return write_json_atomic(Path(run_dir) / METRICS_FILE, out)


def _scalar(key: str, value):
    if value is None or isinstance(value, bool | str):
        return value
    if hasattr(value, "item") and getattr(value, "ndim", 0) == 0:  # numpy scalar / 0-d array
        value = value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    raise TypeError(f"metrics.json must stay flat: {key!r} is a {type(value).__name__} ({value!r:.80})")
