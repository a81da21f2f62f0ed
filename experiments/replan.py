"""Re-plan a recorded cell at one or more code revisions and compare the plans with the record.

    uavplan-diagnose replan results/cells/study/church/smith/default/seed0 \\
        --revision 00514f4 fb9b5f7

Answers "does this code change alter that recorded cell?" without flying it again. The record's
``metrics.json`` names the cell (scene config, planner, seed, budget, experiment preset). For each
revision a child Python runs in a worktree of that revision (the working tree itself when no
revision is given), so the config, proxy and planner code are that revision's: it composes the
cell's config, takes the exploration proxy from the shared cache (built when missing: one proxy for
every revision, since the cache key is the exploration's content), plans, checks the plan with
``mission.validate`` and writes ``plan.json`` and ``viewpoints.csv`` under ``--out``.

Compared: every field the record's ``plan.json`` and the re-plan both hold except what a plan
measures about its own run (``MEASUREMENTS``), floats to a relative 1e-9. The default reconstruction
is not bit-deterministic (``proxy_deterministic`` in the record), so a proxy rebuilt on another
machine differs from the record's and so may the plan: the tool says whether the proxy is the
record's (its sparse/dense point and face counts), and then only the revisions' agreement with each
other answers the question.

Exit status: 0 when all revisions plan the same (and, on the record's own proxy, the same as the
record), 1 when they differ, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments.record import revision_worktree
from scene.plan import read_viewpoints

ROOT = Path(__file__).resolve().parents[1]

# What a plan measures about its own run rather than decides: wall-clock timings, and ray counts
# (a test added beside the optimisation casts rays without changing a single view).
MEASUREMENTS = ("timings_s", "rays_cast")
# Output statistics of the exploration's reconstruction that the record keeps: equal counts mean
# the proxy here is the record's (a rebuilt, non-deterministic one differs in them).
PROXY_IDENTITY = ("proxy_n_sparse_points", "proxy_n_dense_points", "proxy_proxy_faces")
REL_TOL = 1e-9

# Runs in the revision's tree (cwd), so every import is that revision's. A ``-c`` string rather than
# a file of this module: an older revision's tree does not hold this module. It needs a revision with
# the pipeline package and the drone model (``pipeline.proxy``, ``pipeline.settings``,
# ``drone.model``); nothing imports ``run.py``, the Hydra entry point alone.
CHILD = r"""
import json, sys, time
from pathlib import Path
import hydra
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from mission.validate import validate_plan
from scene.camera import Intrinsics
from scene.plan import write_plan
from scene.registry import load_scene

from drone.model import DroneSettings, flight_summary
from pipeline.proxy import ProxyInputs, proxy_stage
from pipeline.settings import planner_setup


def obtain_proxy(scene, intrinsics, cfg, record):
    proxy, fields = proxy_stage(scene, intrinsics, ProxyInputs.of(cfg))
    record.update(fields)
    return proxy


overrides, out = json.loads(sys.argv[1]), Path(sys.argv[2])
with initialize_config_dir(config_dir=str(Path("conf").resolve()), version_base=None):
    cfg = compose(config_name="config", overrides=overrides)
params, _ = planner_setup(cfg)
scene = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
intrinsics = Intrinsics(**cfg.camera)
proxy_record = {}
proxy = obtain_proxy(scene, intrinsics, cfg, proxy_record)
start = time.process_time()
plan = hydra.utils.get_method(cfg.planner._target_)(proxy, intrinsics, params, cfg.seed)
plan_cpu_s = time.process_time() - start
drone = DroneSettings.from_config(OmegaConf.to_container(cfg.drone, resolve=True))
validate_plan(plan, proxy, drone)
plan.info.update(flight_summary(plan.viewpoints, drone))
write_plan(plan, out)
(out / "replan.json").write_text(json.dumps({"proxy": proxy_record, "plan_cpu_s": plan_cpu_s}))
"""


@dataclass(frozen=True)
class Difference:
    """One field two plans disagree on (``None`` where a side lacks it)."""

    key: str
    reference: object
    other: object


def same_value(a, b, rel_tol: float = REL_TOL) -> bool:
    """Equal JSON values; floats within ``rel_tol`` (relative), containers element by element."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(a, b, rel_tol=rel_tol, abs_tol=0.0)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_value(x, y, rel_tol) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_value(a[k], b[k], rel_tol) for k in a)
    return a == b


def compare_plans(reference: dict, other: dict, rel_tol: float = REL_TOL) -> list[Difference]:
    """The fields of two ``plan.json`` records that differ: every key both hold, minus
    ``MEASUREMENTS``, in ``reference``'s order. A key one side lacks is not a difference (run.py adds
    the predicted coverage after planning; the re-plan does not compute it)."""
    shared = [k for k in reference if k in other and k not in MEASUREMENTS]
    return [
        Difference(k, reference[k], other[k])
        for k in shared
        if not same_value(reference[k], other[k], rel_tol)
    ]


def proxy_is_records(metrics: dict, proxy_record: dict) -> bool:
    """Whether the re-plan's proxy has the record's reconstruction statistics (``PROXY_IDENTITY``);
    ``proxy_record`` holds them under the record's names (``pipeline.proxy.proxy_stage`` prefixes them)."""
    return all(
        metrics.get(key) is not None and metrics.get(key) == proxy_record.get(key) for key in PROXY_IDENTITY
    )


def cell_overrides(metrics: dict) -> list[str]:
    """``run.py`` overrides that compose a recorded cell's config.

    Raises:
        ValueError: the record lacks a field, or is of a user's mesh (its path is not recorded)."""
    missing = [k for k in ("scene_config", "planner", "seed", "budget", "experiment") if k not in metrics]
    if missing:
        raise ValueError(f"the record lacks {', '.join(missing)}: not a cell record of run.py")
    if metrics["scene_config"] == "mesh":
        raise ValueError("a cell of a user's mesh: its path is not in the record; pass --set scene.path=...")
    return [
        f"scene={metrics['scene_config']}",
        f"planner={metrics['planner']}",
        f"seed={metrics['seed']}",
        f"budget={metrics['budget']}",
        f"experiment={metrics['experiment']}",
    ]


def plan_at(revision: str | None, overrides: list[str], out: Path) -> tuple[dict, dict]:
    """Plan in a child Python at ``revision`` (the working tree when ``None``) into ``out``.

    Returns (its plan.json, its replan.json: the proxy record and the planning CPU seconds).

    Raises:
        ValueError: ``revision`` names no commit. RuntimeError: the child failed."""
    env = dict(os.environ, UAVPLAN_CACHE=os.environ.get("UAVPLAN_CACHE", str(ROOT / "cache")))
    with revision_worktree(revision, prefix="uavplan_replan_") if revision else nullcontext(ROOT) as tree:
        env["PYTHONPATH"] = str(tree)
        child = [sys.executable, "-c", CHILD, json.dumps(overrides), str(out.resolve())]
        if subprocess.run(child, cwd=tree, env=env).returncode != 0:
            raise RuntimeError(f"re-planning at {revision or 'the working tree'} failed (see above)")
    return json.loads((out / "plan.json").read_text()), json.loads((out / "replan.json").read_text())


def views_line(reference: np.ndarray, other: np.ndarray) -> str:
    """How two plans' (V, 5) viewpoint rows (x, y, z m; yaw, pitch deg) compare, row by row."""
    if reference.shape != other.shape:
        return f"views: {len(reference)} vs {len(other)}"
    if np.array_equal(reference, other):
        return "views: identical"
    moved = np.linalg.norm(reference[:, :3] - other[:, :3], axis=1)
    turned = np.abs(reference[:, 3:] - other[:, 3:]).max(axis=1)
    return (
        f"views: {np.count_nonzero(moved + turned)} of {len(reference)} differ "
        f"(up to {moved.max():.3f} m, {turned.max():.2f} deg)"
    )


def describe(plan: dict) -> str:
    """``189 views, 1161 m, objective 12.41 -> 0.0137`` (the objective where the planner reports one)."""
    text = f"{plan['n_viewpoints']} views, {plan['flight_length_m']:.0f} m"
    if "objective_initial" in plan and "objective_final" in plan:
        text += f", objective {plan['objective_initial']:.4g} -> {plan['objective_final']:.4g}"
    return text


def differences_line(differences: list[Difference]) -> str:
    """``equal`` or ``differs in a (x vs y), b (...)`` with long values shortened."""
    if not differences:
        return "equal"

    def short(value) -> str:
        text = json.dumps(value)
        return text if len(text) <= 40 else text[:37] + "..."

    fields = [f"{d.key} ({short(d.reference)} vs {short(d.other)})" for d in differences]
    return "differs in " + ", ".join(fields)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("record", type=Path, help="a cell record folder (metrics.json, plan.json)")
    parser.add_argument(
        "--revision", nargs="+", default=[None], help="commits to plan at (default: the working tree)"
    )
    parser.add_argument("--set", action="append", default=[], help="an extra run.py override")
    parser.add_argument("--out", type=Path, default=Path("outputs") / "replan", help="where the plans go")
    args = parser.parse_args(argv)
    try:
        metrics = json.loads((args.record / "metrics.json").read_text())
        recorded = json.loads((args.record / "plan.json").read_text())
        overrides = cell_overrides(metrics) + args.set
    except (OSError, ValueError) as exc:
        print(f"error: {args.record}: {exc}", file=sys.stderr)
        return 2
    scene = metrics.get("scene", metrics["scene_config"])
    name = f"{scene}/{metrics['planner']}/{metrics['budget']}/seed{metrics['seed']}"
    code = str(metrics.get("code_commit", "?"))[:10]
    print(f"{name}: the record (code {code}): {describe(recorded)}", flush=True)
    plans: dict[str, tuple[dict, np.ndarray]] = {}
    agree = True
    for revision in args.revision:
        label = revision or "working tree"
        out = args.out / name.replace("/", "_") / (revision or "worktree")
        try:
            plan, extra = plan_at(revision, overrides, out)
        except (ValueError, RuntimeError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        own_proxy = proxy_is_records(metrics, extra["proxy"])
        to_record = compare_plans(recorded, plan)
        proxy = extra["proxy"]
        whose = "the record's" if own_proxy else "not the record's"
        points = f"{proxy.get('proxy_n_sparse_points')} sparse / {proxy.get('proxy_n_dense_points')} dense"
        cpu = f"{extra['plan_cpu_s']:.0f} s CPU"
        print(f"  {label}: {describe(plan)}, {cpu}; proxy {points} points ({whose})", flush=True)
        print(f"    against the record: {differences_line(to_record)}", flush=True)
        agree &= not (own_proxy and to_record)
        views = read_viewpoints(out / "viewpoints.csv")[0]
        for earlier, (earlier_plan, earlier_views) in plans.items():
            between = compare_plans(earlier_plan, plan)
            print(
                f"    against {earlier}: {differences_line(between)}; {views_line(earlier_views, views)}",
                flush=True,
            )
            agree &= not between and np.array_equal(earlier_views, views)
        plans[label] = plan, views
        print(f"    plan: {out}", flush=True)
    return 0 if agree else 1


if __name__ == "__main__":
    sys.exit(main())
