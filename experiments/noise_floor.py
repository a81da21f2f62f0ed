"""The noise floor: one cell run K times from nothing, and how far its numbers move on their own.

    uavplan-study noise-floor --repeats 5 --out study/noise -- scene=tomb planner=ours,lawnmower
    uavplan-study noise-floor --summarise study/noise --out archive/pre_p1/noise_floor

Each repeat is a Hydra sweep cell of ``run.py`` with its own empty stage cache, so the exploratory
flight, its reconstruction and the proxy are rebuilt every time, in the default (not
deterministic) mode: ``reconstruct.deterministic=false`` is forced, and the seed stays the same. What
differs between repeats is only what thread timing changes (the SfM mapper, fusion, Poisson; see
``conf/reconstruct/default.yaml``), which is the run-to-run noise a reader of one table cell cannot see.
The planners of one repeat share that repeat's proxy, as in a study.

Writes into ``--out``: ``noise_floor.md`` (per scene, planner and metric: mean, sample standard
deviation, min, max, range over the repeats), ``noise_floor.csv`` (the same, full precision) and
``noise_floor.json``, the floor that ``experiments.tables --noise-floor`` reads: per metric, the
largest range (max - min over the repeats) of any planner measured. Two planners whose single runs
differ by less than that are a tie: the same cell moves that much by itself.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.runs import (
    RunDirectoryError,
    find_run_dirs,
    method_name,
    method_sort_key,
    out_is_a_file,
    read_metrics,
    scene_name,
    scene_sort_key,
)
from scene.io import write_json_atomic, write_text_atomic

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
FLOOR_FILE = "noise_floor.json"
# The metrics whose noise the study's tables need (Table I, the surface table, Table II's counts).
NOISE_METRICS = (
    "acc90_m",
    "acc95_m",
    "comp_050",
    "comp_075",
    "comp_050_ground",
    "comp_050_roofs",
    "comp_050_walls",
    "comp_050_undersides",
    "n_images",
    "registered_fraction",
    "flight_length_m",
    "n_dense_points",
    "position_error_median_m",
    "proxy_n_faces",
)
SUMMARY_COLUMNS = ("scene", "planner", "metric", "n", "mean", "std", "min", "max", "range")


def sweep_command(repeats: int, out_dir: Path, overrides: Sequence[str]) -> list[str]:
    """The ``run.py -m`` command line that runs every cell of ``overrides`` ``repeats`` times.

    Repeat ``r`` runs in ``out_dir/rep<r>/<scene>/<planner>`` with the cache ``out_dir/cache/rep<r>``.
    """
    if repeats < 2:
        raise ValueError(f"--repeats must be at least 2 to measure a spread, got {repeats}")
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if key in ("cache_dir", "reconstruct.deterministic", "hydra.sweep.dir", "hydra.sweep.subdir"):
            raise ValueError(f"override {override!r}: the noise floor sets {key} itself")
    out_dir = Path(out_dir).resolve()
    return [
        sys.executable,
        str(ROOT / "run.py"),
        "-m",
        *overrides,
        f"+repeat=range(0,{int(repeats)})",
        "reconstruct.deterministic=false",
        f"cache_dir={out_dir}/cache/rep${{repeat}}",
        f"hydra.sweep.dir={out_dir}",
        "hydra.sweep.subdir=rep${repeat}/${scene.name}/${planner.name}",
    ]


def load_repeats(path: str | Path) -> pd.DataFrame:
    """One row per run at or below ``path`` (every repeat kept: the same seed is no duplicate here).

    Raises:
        RunDirectoryError: no run under ``path``.
    """
    rows = []
    for run_dir in find_run_dirs(path):
        record = read_metrics(run_dir)
        rows.append({"run_dir": str(run_dir), **{k: v for k, v in record.items() if not isinstance(v, dict)}})
    return pd.DataFrame(rows)


def summarise_repeats(runs: pd.DataFrame, metrics: Sequence[str] = NOISE_METRICS) -> pd.DataFrame:
    """Mean, sample standard deviation (ddof 1), min, max and range of each metric per (scene, planner).

    Only runs with ``status`` ok count; a metric no run recorded is left out.
    """
    ok = runs[runs.get("status", pd.Series("ok", index=runs.index)) == "ok"]
    rows = []
    for (scene, planner), group in ok.groupby(["scene", "planner"], sort=False):
        for metric in metrics:
            if metric not in group:
                continue
            values = pd.to_numeric(group[metric], errors="coerce").to_numpy(dtype=float)
            values = values[np.isfinite(values)]
            if not len(values):
                continue
            rows.append(
                {
                    "scene": scene,
                    "planner": planner,
                    "metric": metric,
                    "n": len(values),
                    "mean": float(values.mean()),
                    "std": float(values.std(ddof=1)) if len(values) > 1 else math.nan,
                    "min": float(values.min()),
                    "max": float(values.max()),
                    "range": float(np.ptp(values)),
                }
            )
    rows.sort(key=lambda r: (scene_sort_key(r["scene"]), method_sort_key(r["planner"])))
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def noise_floor(summary: pd.DataFrame) -> dict[str, float]:
    """Per metric, the largest range over the repeats of any (scene, planner) measured (stored unit)."""
    measured = summary[summary["n"] > 1]
    return {str(m): float(g["range"].max()) for m, g in measured.groupby("metric", sort=False)}


def floor_record(summary: pd.DataFrame, source: str) -> dict:
    """The JSON the tables read: the floor per metric, where it came from and how it was taken."""
    cells = summary[["scene", "planner", "n"]].drop_duplicates()
    return {
        "rule": "per metric, the largest range (max - min over the repeats) of any cell measured",
        "source": source,
        "cells": [
            {"scene": s, "planner": p, "repeats": int(n)}
            for s, p, n in cells.itertuples(index=False, name=None)
        ],
        "floor": noise_floor(summary),
    }


def read_floor(path: str | Path) -> dict[str, float]:
    """The per-metric floor of a ``noise_floor.json`` (metric -> floor in the stored unit).

    Raises:
        ValueError: the file is not a noise-floor record.
    """
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise ValueError(f"noise floor file not found: {path}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    floor = record.get("floor") if isinstance(record, Mapping) else None
    if not isinstance(floor, Mapping) or not all(
        isinstance(v, int | float) and v >= 0 for v in floor.values()
    ):
        raise ValueError(f"{path}: no 'floor' object of non-negative numbers (not a {FLOOR_FILE})")
    return {str(k): float(v) for k, v in floor.items()}


def to_markdown(summary: pd.DataFrame, floor: Mapping[str, float], source: str) -> str:
    """The findings file: one table per (scene, planner), then the floor the tables use."""
    lines = [
        "# Noise floor",
        "",
        f"Runs: `{source}`. Each repeat rebuilt the exploratory flight's reconstruction and proxy from an",
        "empty cache in the default mode (`reconstruct.deterministic=false`), same seed, same commit.",
        "",
    ]
    for (scene, planner), group in summary.groupby(["scene", "planner"], sort=False):
        n = int(group["n"].max())
        lines += [
            f"## {scene_name(scene)}, {method_name(planner)} ({n} repeats)",
            "",
            "| metric | mean | std | min | max | range |",
            "| :-- | --: | --: | --: | --: | --: |",
        ]
        for row in group.itertuples():
            lines.append(
                f"| {row.metric} | {_g(row.mean)} | {_g(row.std)} | {_g(row.min)} | {_g(row.max)} | "
                f"{_g(row.range)} |"
            )
        lines.append("")
    lines += [
        "## The floor the tables use",
        "",
        "Per metric the largest range of any cell above. `python -m experiments.tables ... --noise-floor "
        f"{FLOOR_FILE}` marks planners within it of the best as tied for best.",
        "",
        "| metric | floor |",
        "| :-- | --: |",
    ]
    lines += [f"| {metric} | {_g(value)} |" for metric, value in floor.items()]
    return "\n".join(lines) + "\n"


def _g(value: float) -> str:
    if not math.isfinite(value):
        return "n/a"
    return f"{value:,.4g}" if abs(value) < 1e5 else f"{value:,.0f}"


def write_noise_floor(run_path: Path, out_dir: Path) -> pd.DataFrame:
    """Summarise the repeats under ``run_path`` into ``out_dir``; return the summary."""
    runs = load_repeats(run_path)
    summary = summarise_repeats(runs)
    if summary.empty or (summary["n"] < 2).all():
        raise RunDirectoryError(f"{run_path}: no cell has two successful repeats; no spread to measure")
    source = str(run_path)
    record = floor_record(summary, source)
    buf = summary.to_csv(index=False, lineterminator="\n")
    write_text_atomic(out_dir / "noise_floor.csv", buf)
    write_text_atomic(out_dir / "noise_floor.md", to_markdown(summary, record["floor"], source))
    write_json_atomic(out_dir / FLOOR_FILE, record)
    n_failed = int((runs.get("status", pd.Series("ok", index=runs.index)) != "ok").sum())
    print(f"{len(runs)} runs ({n_failed} failed) -> {out_dir}/noise_floor.{{md,csv,json}}")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Command line; returns the exit status."""
    parser = argparse.ArgumentParser(prog="uavplan-study noise-floor", description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs of each cell (default 5)")
    parser.add_argument("--out", type=Path, required=True, help="directory for the summary (and the runs)")
    parser.add_argument(
        "--summarise", type=Path, metavar="DIR", help="summarise the repeats already under DIR; run nothing"
    )
    parser.add_argument("overrides", nargs="*", help="run.py overrides after --: scene=tomb planner=ours")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if out_is_a_file(args.out):
        return 2
    run_path = args.summarise
    if run_path is None:
        try:
            command = sweep_command(args.repeats, args.out, args.overrides)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print("running:", " ".join(command), flush=True)
        # A failed cell is recorded in its metrics.json and does not stop the sweep's other cells.
        status = subprocess.call(command, cwd=ROOT)
        if status != 0:
            log.warning("the sweep exited with status %d; summarising the runs that finished", status)
        run_path = args.out
    try:
        summary = write_noise_floor(run_path, args.out)
    except RunDirectoryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(to_markdown(summary, noise_floor(summary), str(run_path)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
