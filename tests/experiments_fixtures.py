"""Run directories written the way run.py writes them, with known numbers, for the experiments tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scene.plan import Plan, write_plan


def write_run(
    root: Path,
    scene: str,
    planner: str,
    seed: int,
    *,
    status: str = "ok",
    error: str = "",
    plan: Plan | None = None,
    camera: dict | None = None,
    **metrics,
) -> Path:
    """A run directory ``root/<scene>/<planner>/seed<N>`` (``.../<planner>/<budget>/seed<N>`` when the
    metrics name a budget) with metrics.json (+ plan and config if given)."""
    run_dir = root / scene / planner / metrics.get("budget", "") / f"seed{seed}"
    run_dir.mkdir(parents=True)
    record = {
        "scene": scene,
        "planner": planner,
        "seed": seed,
        "status": status,
        "numpy_version": np.__version__,
        "reconstruction_path": "recon/dense.ply",
    }
    if status == "failed":
        record["error"] = error
    record.update(metrics)
    (run_dir / "metrics.json").write_text(json.dumps(record))
    if plan is not None:
        write_plan(plan, run_dir / "plan")
    if camera is not None:
        (run_dir / ".hydra").mkdir()
        lines = ["camera:"] + [f"  {k}: {v}" for k, v in camera.items()] + [f"seed: {seed}"]
        (run_dir / ".hydra" / "config.yaml").write_text("\n".join(lines) + "\n")
    return run_dir


def square_plan(planner: str = "ours") -> Plan:
    """Eight viewpoints on a 20 m square around the origin at 15 m, looking at the centre."""
    xy = np.array([[10, 0], [10, 10], [0, 10], [-10, 10], [-10, 0], [-10, -10], [0, -10], [10, -10]], float)
    yaw = np.degrees(np.arctan2(-xy[:, 1], -xy[:, 0]))
    viewpoints = np.column_stack([xy, np.full(8, 15.0), yaw, np.full(8, -45.0)])
    kinds = ["detail", "detail", "coverage", "coverage", "coverage", "grid", "grid", "detail"]
    return Plan(viewpoints, kinds, planner)
