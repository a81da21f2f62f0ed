"""Quality per image: each planner's cells joined in budget order, and the questions a front answers.

    uavplan-study fronts results/cells/study --out results/study

A planner's front on a scene is its cells at each image budget (``planner.budget``: lowest ... highest),
the seeds of a budget averaged: (images, completeness) points joined fewest images first. From the
fronts, per scene:

- how many images (and minutes of flight) each planner needs to reach a completeness, interpolated
  linearly between the two budgets that bracket it on its front ("not reached" above its best budget;
  "<= n" when its smallest budget already reaches it);
- each planner's completeness and acc90 at equal image counts (interpolated on its front; none outside
  the front's image range: a front is not extrapolated).

Writes ``fronts.{md,csv,tex}`` and ``fronts_images.png`` / ``fronts_flight_time.png`` (completeness at
5 cm and acc90 against images or flight time, one column per scene, spread over seeds as error bars).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from experiments.runs import (  # noqa: E402
    RunDirectoryError,
    load_runs,
    method_name,
    method_sort_key,
    runs_frame,
    scene_name,
    scene_sort_key,
)
from experiments.tables import latex_escape  # noqa: E402
from planner.budget import DEFAULT_LEVEL, level_rank  # noqa: E402
from scene.io import write_atomic, write_text_atomic  # noqa: E402

log = logging.getLogger(__name__)

COMPLETENESS = "comp_050"  # percent at 5 cm (evaluate/settings.py)
ACCURACY = "acc90_m"
# What a front's table asks: completeness levels to reach (%) and image counts to compare at. The
# levels span what the default cells reach (about 60-90 % at 5 cm; below 60 % only the lawnmower).
DEFAULT_TARGETS_PCT = (60.0, 70.0, 80.0, 85.0, 90.0)
DEFAULT_AT_IMAGES = (200, 400, 800)
COSTS = {"n_images": ("images", 1.0), "flight_time_s": ("flight time (min)", 1.0 / 60.0)}


@dataclass(frozen=True)
class Reach:
    """The cost at which a front first reaches a level.

    Attributes:
        cost: interpolated cost (images or minutes), NaN when not reached or not known.
        at_most: the front's smallest budget already reaches the level (the cost is an upper bound).
        missing: a cost the answer needs was not recorded (e.g. flight time in older records).
    """

    cost: float
    at_most: bool = False
    missing: bool = False

    @property
    def reached(self) -> bool:
        return math.isfinite(self.cost)

    def text(self, decimals: int = 0) -> str:
        if self.missing:
            return "n/a"
        if not self.reached:
            return "not reached"
        return ("≤ " if self.at_most else "") + f"{self.cost:,.{decimals}f}"


def cost_to_reach(costs: Sequence[float], values: Sequence[float], level: float) -> Reach:
    """Where the front ``(costs[i], values[i])`` (budget order) first reaches ``level``.

    Linear between the last point below ``level`` and the first at or above it; ``at_most`` when the
    first point is already there; NaN when no point is; ``missing`` when a cost the answer needs
    (the points up to the first one at the level) was not recorded.
    """
    x, y = np.asarray(costs, float), np.asarray(values, float)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"a front needs as many costs as values, got {x.shape} and {y.shape}")
    hits = np.flatnonzero(y >= level)
    if not len(hits):
        return Reach(math.nan)
    i = int(hits[0])
    if not np.isfinite(x[max(i - 1, 0) : i + 1]).all():
        return Reach(math.nan, missing=True)
    if i == 0:
        return Reach(float(x[0]), at_most=True)
    t = (level - y[i - 1]) / (y[i] - y[i - 1])
    return Reach(float(x[i - 1] + t * (x[i] - x[i - 1])))


def value_at(costs: Sequence[float], values: Sequence[float], cost: float) -> float:
    """The front's value at ``cost``: linear on the first segment (budget order) that spans it, the
    point itself on a one-point front at exactly that cost, NaN outside the front's range."""
    x, y = np.asarray(costs, float), np.asarray(values, float)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"a front needs as many costs as values, got {x.shape} and {y.shape}")
    for i in range(len(x)):
        if x[i] == cost:
            return float(y[i])
        if i and min(x[i - 1], x[i]) <= cost <= max(x[i - 1], x[i]):
            return float(y[i - 1] + (cost - x[i - 1]) / (x[i] - x[i - 1]) * (y[i] - y[i - 1]))
    return math.nan


def front_points(
    runs: pd.DataFrame, columns: Sequence[str] = ("n_images", "flight_time_s", COMPLETENESS, ACCURACY)
) -> pd.DataFrame:
    """One row per (scene, planner, budget) over the successful runs: the mean and sample standard
    deviation of each of ``columns`` (``<column>`` and ``<column>_std``), ``n`` seeds, ``budget_value``,
    in table order (scene, method, budget fewest images first)."""
    ok = runs[runs["status"] == "ok"].copy()
    if "budget" not in ok:
        ok["budget"] = DEFAULT_LEVEL
    rows = []
    for (scene, planner, budget), group in ok.groupby(["scene", "planner", "budget"], sort=False):
        row = {
            "scene": scene,
            "planner": planner,
            "budget": budget,
            "method": method_name(planner),
            "n": len(group),
        }
        if "budget_value" in group:
            row["budget_value"] = group["budget_value"].iloc[0]
        for column in columns:
            values = pd.to_numeric(group.get(column, pd.Series(dtype=float)), errors="coerce").dropna()
            row[column] = float(values.mean()) if len(values) else math.nan
            row[f"{column}_std"] = float(values.std(ddof=1)) if len(values) > 1 else math.nan
        rows.append(row)
    points = pd.DataFrame(rows)
    if points.empty:
        return points
    order = points.apply(
        lambda r: (scene_sort_key(r["scene"]), method_sort_key(r["planner"]), level_rank(r["budget"])), axis=1
    )
    return points.loc[order.sort_values().index].reset_index(drop=True)


def front_table(
    points: pd.DataFrame,
    targets_pct: Sequence[float] = DEFAULT_TARGETS_PCT,
    at_images: Sequence[int] = DEFAULT_AT_IMAGES,
) -> pd.DataFrame:
    """Per (scene, planner): budgets on the front, images and flight minutes to reach each of
    ``targets_pct`` (completeness at 5 cm), completeness and acc90 at each of ``at_images``.

    Columns: scene, planner, method, budgets, images_min, images_max, ``images_to_<t>``,
    ``images_to_<t>_at_most``, ``minutes_to_<t>``, ``minutes_to_<t>_at_most``, ``minutes_to_<t>_missing``
    (flight time not recorded), ``comp_at_<n>``, ``acc90_cm_at_<n>``.
    """
    rows = []
    for (scene, planner), front in points.groupby(["scene", "planner"], sort=False):
        images = front["n_images"].to_numpy(float)
        minutes = front["flight_time_s"].to_numpy(float) / 60.0
        comp = front[COMPLETENESS].to_numpy(float)
        acc_cm = front[ACCURACY].to_numpy(float) * 100.0
        row = {
            "scene": scene,
            "planner": planner,
            "method": method_name(planner),
            "budgets": len(front),
            "images_min": float(np.nanmin(images)),
            "images_max": float(np.nanmax(images)),
        }
        for target in targets_pct:
            key = f"{target:g}"
            by_images = cost_to_reach(images, comp, target)
            by_minutes = cost_to_reach(minutes, comp, target)
            row[f"images_to_{key}"] = by_images.cost
            row[f"images_to_{key}_at_most"] = by_images.at_most
            row[f"minutes_to_{key}"] = by_minutes.cost
            row[f"minutes_to_{key}_at_most"] = by_minutes.at_most
            row[f"minutes_to_{key}_missing"] = by_minutes.missing
        for n in at_images:
            row[f"comp_at_{n}"] = value_at(images, comp, n)
            row[f"acc90_cm_at_{n}"] = value_at(images, acc_cm, n)
        rows.append(row)
    return pd.DataFrame(rows)


def _reach_cell(row, prefix: str, key: str, decimals: int) -> str:
    missing = bool(row.get(f"{prefix}_to_{key}_missing", False))
    return Reach(row[f"{prefix}_to_{key}"], bool(row[f"{prefix}_to_{key}_at_most"]), missing).text(decimals)


def _value_cell(value: float, decimals: int) -> str:
    return "–" if not math.isfinite(value) else f"{value:.{decimals}f}"


def _table_rows(
    table: pd.DataFrame, targets_pct, at_images
) -> tuple[list[str], list[tuple[str, list[list[str]]]]]:
    header = ["Method", "Budgets", "Images"]
    header += [f"Images to {t:g} %" for t in targets_pct]
    header += [f"Flight min to {t:g} %" for t in targets_pct]
    header += [f"Compl. at {n} img (%)" for n in at_images]
    header += [f"acc90 at {n} img (cm)" for n in at_images]
    scenes = []
    for scene, rows in table.groupby("scene", sort=False):
        body = []
        for _, row in rows.iterrows():
            cells = [
                row["method"],
                str(int(row["budgets"])),
                f"{row['images_min']:.0f}–{row['images_max']:.0f}",
            ]
            cells += [_reach_cell(row, "images", f"{t:g}", 0) for t in targets_pct]
            cells += [_reach_cell(row, "minutes", f"{t:g}", 1) for t in targets_pct]
            cells += [_value_cell(row[f"comp_at_{n}"], 1) for n in at_images]
            cells += [_value_cell(row[f"acc90_cm_at_{n}"], 1) for n in at_images]
            body.append(cells)
        scenes.append((scene, body))
    return header, scenes


FRONT_CAPTION = (
    "Quality per image. Images (and minutes of flight) each planner needs to reach a completeness at "
    "5 cm, interpolated on its budget front (≤: its smallest budget reaches it already; n/a: flight "
    "time not recorded); completeness and acc90 at equal image counts (–: outside the images its "
    "budgets span)."
)


def to_markdown(table: pd.DataFrame, targets_pct=DEFAULT_TARGETS_PCT, at_images=DEFAULT_AT_IMAGES) -> str:
    """The front table as Markdown, one block per scene."""
    header, scenes = _table_rows(table, targets_pct, at_images)
    lines = [f"**{FRONT_CAPTION}**", ""]
    for scene, body in scenes:
        lines += [f"*{scene_name(scene)}*", "", "| " + " | ".join(header) + " |"]
        lines.append("| :-- | " + " | ".join("--:" for _ in header[1:]) + " |")
        lines += ["| " + " | ".join(cells) + " |" for cells in body]
        lines.append("")
    return "\n".join(lines)


def to_latex(table: pd.DataFrame, targets_pct=DEFAULT_TARGETS_PCT, at_images=DEFAULT_AT_IMAGES) -> str:
    """The front table as a booktabs LaTeX table (one block per scene)."""
    header, scenes = _table_rows(table, targets_pct, at_images)
    lines = [
        r"% Generated by experiments.fronts; needs \usepackage{booktabs}",
        r"\begin{table*}[t]",
        r"\centering",
        rf"\caption{{{latex_escape(FRONT_CAPTION)}}}",
        r"\label{tab:fronts}",
        r"\setlength{\tabcolsep}{3pt}",
        rf"\begin{{tabular}}{{l{'r' * (len(header) - 1)}}}",
        r"\toprule",
        " & ".join(latex_escape(h) for h in header) + r" \\",
    ]
    for scene, body in scenes:
        lines += [
            r"\midrule",
            rf"\multicolumn{{{len(header)}}}{{l}}{{\emph{{{latex_escape(scene_name(scene))}}}}} \\",
        ]
        lines += [" & ".join(latex_escape(c) for c in cells) + r" \\" for cells in body]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table*}"]
    return "\n".join(lines) + "\n"


def headline_markdown(points: pd.DataFrame) -> str:
    """The README's headline table: one row per scene and planner, each column's values per budget
    (fewest images first, ``a / b / c``), means over seeds; ``Seeds`` counts them per budget."""

    def per_budget(group: pd.DataFrame, column: str, scale: float, decimals: int) -> str:
        return " / ".join(_value_cell(v * scale, decimals) for v in group[column])

    lines = [
        "| Scene | Planner | Budgets | Seeds | Images | Completeness 5 cm (%) | acc90 (cm) | Flight (min) |",
        "| :-- | :-- | :-- | :-- | :-- | :-- | :-- | :-- |",
    ]
    for (scene, planner), group in points.groupby(["scene", "planner"], sort=False):
        lines.append(
            f"| {scene_name(scene)} | {method_name(planner)} | {' / '.join(group['budget'])} "
            f"| {' / '.join(str(int(n)) for n in group['n'])} | {per_budget(group, 'n_images', 1.0, 0)} "
            f"| {per_budget(group, COMPLETENESS, 1.0, 1)} | {per_budget(group, ACCURACY, 100.0, 1)} "
            f"| {per_budget(group, 'flight_time_s', 1.0 / 60.0, 1)} |"
        )
    return "\n".join(lines) + "\n"


def plot_fronts(points: pd.DataFrame, cost: str = "n_images") -> Figure:
    """Completeness at 5 cm (top) and acc90 (bottom) against ``cost`` (a key of ``COSTS``), one column
    per scene; each planner's budgets joined fewest images first, seeds' spread as error bars, the
    default budget drawn larger."""
    if cost not in COSTS:
        raise ValueError(f"cost must be one of {sorted(COSTS)}, got {cost!r}")
    label, scale = COSTS[cost]
    scenes = list(dict.fromkeys(points["scene"]))
    planners = sorted(points["planner"].unique(), key=method_sort_key)
    colours = plt.get_cmap("tab10")
    legend_in = 1.6
    width_in = 3.8 * len(scenes) + legend_in
    fig, axes = plt.subplots(2, len(scenes), figsize=(width_in, 6.6), squeeze=False)
    rows = [(COMPLETENESS, 1.0, "completeness 5 cm (%)"), (ACCURACY, 100.0, "acc90 (cm)")]
    for col, scene in enumerate(scenes):
        for r, (metric, metric_scale, metric_label) in enumerate(rows):
            ax = axes[r][col]
            for i, planner in enumerate(planners):
                front = points[(points["scene"] == scene) & (points["planner"] == planner)]
                x = front[cost].to_numpy(float) * scale
                y = front[metric].to_numpy(float) * metric_scale
                if not np.isfinite(x).any():
                    continue
                xerr = np.nan_to_num(front[f"{cost}_std"].to_numpy(float) * scale)
                yerr = np.nan_to_num(front[f"{metric}_std"].to_numpy(float) * metric_scale)
                colour = colours(i % 10)
                ax.errorbar(
                    x,
                    y,
                    xerr=xerr,
                    yerr=yerr,
                    color=colour,
                    marker="o",
                    ms=4,
                    lw=1.4,
                    capsize=2,
                    label=method_name(planner),
                )
                default = (front["budget"] == DEFAULT_LEVEL).to_numpy()
                ax.scatter(x[default], y[default], s=70, color=colour, edgecolor="black", zorder=3)
            ax.set_xlabel(label)
            ax.set_ylabel(metric_label)
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(scene_name(scene))
    figure_legend(fig, axes, legend_in / width_in, title="black edge: default budget", title_fontsize=7)
    return fig


def figure_legend(fig: Figure, axes, width_fraction: float, **kwargs) -> None:
    """One legend for all ``axes`` (each label once) in the right ``width_fraction`` of ``fig``, the
    panels laid out in the rest."""
    handles = {}
    for ax in np.ravel(axes):
        for handle, text in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(text, handle)
    fig.legend(list(handles.values()), list(handles), loc="center right", frameon=False, **kwargs)
    fig.tight_layout(rect=(0.0, 0.0, 1.0 - width_fraction, 1.0))


def write_fronts(
    runs: pd.DataFrame,
    out_dir: str | Path,
    targets_pct: Sequence[float] = DEFAULT_TARGETS_PCT,
    at_images: Sequence[int] = DEFAULT_AT_IMAGES,
) -> list[Path]:
    """Write the front table (Markdown, CSV, LaTeX), its points (``front_points.csv``) and the two
    front figures into ``out_dir``; return the files written."""
    out_dir = Path(out_dir)
    points = front_points(runs)
    if points.empty:
        raise RunDirectoryError("no successful run: no front to draw")
    table = front_table(points, targets_pct, at_images)
    written = [
        write_text_atomic(out_dir / "fronts.md", to_markdown(table, targets_pct, at_images)),
        write_text_atomic(out_dir / "fronts.tex", to_latex(table, targets_pct, at_images)),
        write_text_atomic(out_dir / "fronts.csv", table.to_csv(index=False, lineterminator="\n")),
        write_text_atomic(out_dir / "front_points.csv", points.to_csv(index=False, lineterminator="\n")),
        write_text_atomic(out_dir / "headline.md", headline_markdown(points)),
    ]
    for cost, stem in (("n_images", "fronts_images"), ("flight_time_s", "fronts_flight_time")):
        fig = plot_fronts(points, cost)
        path = out_dir / f"{stem}.png"
        # Agg PNGs carry no date, so the same records give the same bytes.
        write_atomic(
            path, lambda f, fig=fig: fig.savefig(f, format="png", dpi=150, metadata={"Software": None})
        )
        plt.close(fig)
        written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-study fronts", description=__doc__.split("\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="run or record directories (searched recursively)")
    parser.add_argument("--out", type=Path, required=True, help="directory for the tables and figures")
    parser.add_argument(
        "--targets", type=float, nargs="+", default=list(DEFAULT_TARGETS_PCT), help="completeness levels (%%)"
    )
    parser.add_argument(
        "--at-images", type=int, nargs="+", default=list(DEFAULT_AT_IMAGES), help="image counts"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        runs = runs_frame(load_runs(args.dirs))
        written = write_fronts(runs, args.out, args.targets, args.at_images)
    except RunDirectoryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{len(runs)} runs -> {len(written)} files in {args.out}")
    print((args.out / "fronts.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
