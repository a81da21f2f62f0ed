"""The golden records that guard protocol 1 (results/protocol.md), and the command that rewrites them.

Two kinds, both in the default test run (``tests/test_golden.py``):

- every study planner's plan at the smoke preset on the committed smoke tomb proxy
  (``proxies/smoke/tomb/seed0``): its views, its objective and its forecast;
- the smoke sweep's cells end to end (``tests/test_pipeline_smoke.py``): their metrics.

A change that moves one is a bug, or a protocol (or planner version) bump: rewrite them with

    .venv/bin/python -m tests.golden_records --write          # the plans (about 2 minutes)

and the smoke cells' values from a smoke sweep's ``metrics.json`` (the test prints them), with a
line in ``results/protocol.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "golden"
PLANS_FILE = GOLDEN / "smoke_tomb_plans.json"
CELLS_FILE = GOLDEN / "smoke_tomb_cells.json"
PLANNERS = ("lawnmower", "smith", "yan", "ours", "ours_plus")
# Each planner's objective in its plan.json, where it has one (the lawnmower has none).
OBJECTIVE_KEYS = {
    "smith": ("objective_final",),
    "yan": ("fraction_coverable_covered",),
    "ours": ("final", "R"),
    "ours_plus": ("final", "R"),
}
# What a smoke cell's golden record holds (metrics.json fields).
CELL_FIELDS = (
    "n_images",
    "n_registered",
    "flight_length_m",
    "flight_time_s",
    "acc90_m",
    "acc95_m",
    "comp_050",
    "comp_075",
    "n_dense_points",
    "oracle_comp_050",
    "oracle_acc90_m",
    "proxy_fingerprint",
)
# Tolerances: the spread measured on one machine (AMD EPYC, 2 cores, the golden values' machine)
# over two runs is zero for every field (deterministic mode); these allow for float summation
# order elsewhere, and a later machine widens them only by the spread it measures.
VIEW_ATOL_M = 1e-6
RELATIVE_TOL = 1e-9


def objective(info: dict, planner: str) -> float | None:
    """The planner's objective from its ``plan.json`` info (None where it records none)."""
    keys = OBJECTIVE_KEYS.get(planner)
    if not keys:
        return None
    node = info
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    return None if node is None else float(node)


def smoke_plan_record(planner: str, cache_dir: Path, overrides: tuple[str, ...] = ()) -> dict:
    """Plan ``planner`` at the smoke preset on the committed smoke tomb proxy, as a cell does
    (``pipeline.cell.plan_stage``), with ``run.py`` ``overrides``; its golden record."""
    from hydra import compose, initialize_config_dir

    from pipeline.cell import plan_stage
    from pipeline.proxy import ProxyInputs, proxy_stage
    from pipeline.settings import cell_settings
    from scene.registry import load_scene

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose(
            "config",
            overrides=[
                "experiment=smoke",
                "scene=tomb",
                f"planner={planner}",
                "seed=0",
                f"cache_dir={cache_dir}",
                *overrides,
            ],
        )
    settings = cell_settings(cfg)
    scene = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
    proxy, proxy_record = proxy_stage(scene, settings.intrinsics, ProxyInputs.of(cfg))
    with tempfile.TemporaryDirectory() as tmp:
        plan, record = plan_stage(
            proxy,
            settings.intrinsics,
            str(cfg.planner._target_),
            settings.planner_params,
            0,
            settings.drone,
            settings.evaluation,
            settings.target_gsd_m,
            Path(tmp),
            str(cfg.survey.flight_order),
        )
    forecast = {k: float(v) for k, v in record.items() if k.startswith("predicted_")}
    return {
        "proxy_bundle": proxy_record.get("proxy_bundle"),
        "proxy_fingerprint": proxy_record["proxy_fingerprint"],
        "planner_version": settings.budget.get("planner_version"),
        "n_viewpoints": len(plan.viewpoints),
        "viewpoints": np.round(np.asarray(plan.viewpoints, float), 9).tolist(),
        "kinds": list(plan.kinds),
        "objective": objective(plan.info, planner),
        "flight_time_s": float(record["flight_time_s"]),
        "forecast": forecast,
    }


def plan_differences(record: dict, golden: dict) -> list[str]:
    """What differs between a smoke plan's record and its golden record, beyond the tolerances."""
    out = []
    for key in ("proxy_fingerprint", "planner_version", "n_viewpoints", "kinds"):
        if record[key] != golden[key]:
            out.append(f"{key}: {record[key]!r} != golden {golden[key]!r}")
    if record["n_viewpoints"] == golden["n_viewpoints"]:
        gap = float(np.max(np.abs(np.subtract(record["viewpoints"], golden["viewpoints"])), initial=0.0))
        if gap > VIEW_ATOL_M:
            out.append(f"viewpoints: up to {gap:.3g} (m or deg) from golden")
    pairs = [("objective", record["objective"], golden["objective"])]
    pairs += [("flight_time_s", record["flight_time_s"], golden["flight_time_s"])]
    pairs += [(k, record["forecast"].get(k), v) for k, v in golden["forecast"].items()]
    for key, got, want in pairs:
        if (got is None) != (want is None) or (
            want is not None and not math.isclose(got, want, rel_tol=RELATIVE_TOL, abs_tol=1e-12)
        ):
            out.append(f"{key}: {got!r} != golden {want!r}")
    return out


def cell_differences(record: dict, golden: dict) -> list[str]:
    """What differs between a smoke cell's metrics and its golden record (``CELL_FIELDS``)."""
    out = []
    for key in CELL_FIELDS:
        got, want = record.get(key), golden.get(key)
        if isinstance(want, float) and isinstance(got, int | float):
            if not math.isclose(got, want, rel_tol=RELATIVE_TOL, abs_tol=1e-12):
                out.append(f"{key}: {got!r} != golden {want!r}")
        elif got != want:
            out.append(f"{key}: {got!r} != golden {want!r}")
    return out


def write_plans(planners=PLANNERS) -> dict:
    records = {}
    with tempfile.TemporaryDirectory() as cache:
        for planner in planners:
            record = records[planner] = smoke_plan_record(planner, Path(cache))
            print(f"{planner}: {record['n_viewpoints']} views, objective {record['objective']}")
    GOLDEN.mkdir(parents=True, exist_ok=True)
    PLANS_FILE.write_text(json.dumps(records, indent=1) + "\n")
    return records


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="rewrite tests/golden/smoke_tomb_plans.json")
    parser.add_argument("--planners", nargs="+", default=list(PLANNERS))
    args = parser.parse_args(argv)
    if args.write:
        write_plans(args.planners)
        return 0
    parser.error("nothing to do: --write rewrites the golden plans")
    return 2


if __name__ == "__main__":
    sys.exit(main())
