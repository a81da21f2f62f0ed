"""ours_plus' quality-vs-flight-time front: its cells at each weight of the flight-time term joined in
weight order, with ours and the baselines (default budget) as points, one column per scene.

    uavplan-study ours-plus-front results/cells/default_v4 --out archive/pre_p1/ours_plus

A cell counts as ours_plus when its planner's name starts with ``ours_plus`` (``ours_plus``,
``ours_plus_time0``, ``..._time12``: conf/planner/); its weight is the ``time_weight_per_pct`` its
``plan.json`` recorded (the configs' names are not trusted for it); a cell whose plan records none
(older records) is left out with a warning. Seeds of one weight are averaged.
Writes ``front_flight_time.png`` (completeness at 5 cm and acc90 against flight time) and
``front_flight_time.{csv,md}`` (the points, with each weight's change in flight time and completeness
against ours on the same scene).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from experiments.front_core import ACCURACY, COMPLETENESS
from experiments.fronts import figure_legend
from experiments.runs import (
    RunDirectoryError,
    load_runs,
    method_name,
    method_sort_key,
    read_plan_record,
    runs_frame,
    scene_name,
    scene_sort_key,
)
from planner.budget import DEFAULT_LEVEL
from scene.io import write_atomic, write_text_atomic

ROOT = Path(__file__).resolve().parents[1]

log = logging.getLogger(__name__)

OURS_PLUS = "ours_plus"
# The planners drawn as single points beside ours_plus' front (their default budget).
REFERENCE_PLANNERS = ("ours", "smith", "yan", "lawnmower")
VALUES = ("n_images", "flight_time_s", COMPLETENESS, ACCURACY)


def front_frame(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per (scene, curve, weight): ours_plus' cells by their recorded time weight, the reference
    planners' default-budget cells (weight NaN); mean over seeds and ``n`` seeds. ours_plus cells whose
    plan.json records no time weight are left out (logged)."""
    ok = runs[(runs["status"] == "ok") & (runs["budget"].fillna(DEFAULT_LEVEL) == DEFAULT_LEVEL)].copy()
    is_plus = ok["planner"].str.startswith(OURS_PLUS)
    weights = []
    for run_dir, plus in zip(ok["run_dir"], is_plus, strict=True):
        if not plus:
            weights.append(math.nan)
            continue
        weight = read_plan_record(run_dir).get("time_weight_per_pct")
        if weight is None:
            log.warning("%s: its plan.json records no time weight (an older record): left out", run_dir)
        weights.append(math.nan if weight is None else float(weight))
    ok["time_weight"] = weights
    ok["curve"] = np.where(is_plus, OURS_PLUS, ok["planner"])
    ok = ok[(is_plus & ok["time_weight"].notna()) | ok["planner"].isin(REFERENCE_PLANNERS)]
    rows = []
    for (scene, curve, weight), group in ok.groupby(
        ["scene", "curve", "time_weight"], dropna=False, sort=False
    ):
        row = {"scene": scene, "curve": curve, "time_weight": weight, "n": len(group)}
        for column in VALUES:
            row[column] = float(pd.to_numeric(group[column], errors="coerce").mean())
        rows.append(row)
    points = pd.DataFrame(rows)
    if points.empty:
        return points
    order = points.apply(
        lambda r: (scene_sort_key(r["scene"]), method_sort_key(r["curve"]), np.nan_to_num(r["time_weight"])),
        axis=1,
    )
    points = points.loc[order.sort_values().index].reset_index(drop=True)
    # Each ours_plus weight against ours on the same scene (NaN where the scene has no ours cell).
    ours = points[points["curve"] == "ours"].set_index("scene")
    base_time = points["scene"].map(ours["flight_time_s"])
    base_comp = points["scene"].map(ours[COMPLETENESS])
    points["flight_time_vs_ours_pct"] = 100.0 * (points["flight_time_s"] / base_time - 1.0)
    points["completeness_vs_ours_points"] = points[COMPLETENESS] - base_comp
    return points


def plot_front(points: pd.DataFrame):
    """Completeness at 5 cm (top) and acc90 (bottom) against flight time (min), one column per scene."""
    scenes = list(dict.fromkeys(points["scene"]))
    curves = sorted(points["curve"].unique(), key=method_sort_key)
    colours = {curve: plt.get_cmap("tab10")(i % 10) for i, curve in enumerate(curves)}
    fig, axes = plt.subplots(2, len(scenes), figsize=(3.9 * len(scenes) + 1.6, 6.6), squeeze=False)
    rows = [(COMPLETENESS, 1.0, "completeness 5 cm (%)"), (ACCURACY, 100.0, "acc90 (cm)")]
    for col, scene in enumerate(scenes):
        for r, (metric, scale, label) in enumerate(rows):
            ax = axes[r][col]
            for curve in curves:
                sel = points[(points["scene"] == scene) & (points["curve"] == curve)]
                if sel.empty:
                    continue
                x = sel["flight_time_s"].to_numpy(float) / 60.0
                y = sel[metric].to_numpy(float) * scale
                plus = curve == OURS_PLUS
                ax.plot(
                    x,
                    y,
                    marker="o",
                    ms=4 if plus else 8,
                    lw=1.4 if plus else 0,
                    color=colours[curve],
                    label="Ours+ (time weight)" if plus else method_name(curve),
                )
                if plus:
                    for xi, yi, w in zip(x, y, sel["time_weight"], strict=True):
                        ax.annotate(f"{w:g}", (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7)
            ax.set_xlabel("flight time (min)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(scene_name(scene))
    figure_legend(fig, axes, 1.6 / (3.9 * len(scenes) + 1.6))
    return fig


def to_markdown(points: pd.DataFrame) -> str:
    lines = [
        "| Scene | Plan | Time weight (per %) | Seeds | Images | Flight (min) | vs ours | "
        "Completeness 5 cm (%) | vs ours (points) | acc90 (cm) |",
        "| :-- | :-- | --: | --: | --: | --: | --: | --: | --: | --: |",
    ]
    for _, p in points.iterrows():
        plus = p["curve"] == OURS_PLUS
        lines.append(
            f"| {scene_name(p['scene'])} | {'Ours+' if plus else method_name(p['curve'])} | "
            f"{p['time_weight']:g} | {p['n']} | {p['n_images']:.0f} | {p['flight_time_s'] / 60:.1f} | "
            + (f"{p['flight_time_vs_ours_pct']:+.0f} % | " if plus else "| ")
            + f"{p[COMPLETENESS]:.1f} | "
            + (f"{p['completeness_vs_ours_points']:+.1f} | " if plus else "| ")
            + f"{100 * p[ACCURACY]:.1f} |"
        )
    return "\n".join(lines).replace("| nan |", "| |") + "\n"


def write_front(runs: pd.DataFrame, out_dir: str | Path) -> list[Path]:
    """The figure, CSV and Markdown of ours_plus' front into ``out_dir``; the files written."""
    out_dir = Path(out_dir)
    points = front_frame(runs)
    if points.empty or not (points["curve"] == OURS_PLUS).any():
        raise RunDirectoryError("no successful ours_plus cell at the default budget: no front to draw")
    fig = plot_front(points)
    png = out_dir / "front_flight_time.png"
    write_atomic(png, lambda f: fig.savefig(f, format="png", dpi=150, metadata={"Software": None}))
    plt.close(fig)
    return [
        png,
        write_text_atomic(out_dir / "front_flight_time.csv", points.to_csv(index=False, lineterminator="\n")),
        write_text_atomic(out_dir / "front_flight_time.md", to_markdown(points)),
    ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-study ours-plus-front", description=__doc__.split("\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="run or record directories (searched recursively)")
    parser.add_argument("--out", type=Path, required=True, help="directory for the figure and tables")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    try:
        written = write_front(runs_frame(load_runs(args.dirs)), args.out)
    except RunDirectoryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(str(p) for p in written))
    print((args.out / "front_flight_time.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
