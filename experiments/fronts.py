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
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from experiments.front_core import (
    ACCURACY,
    COMPLETENESS,
    COSTS,
    DEFAULT_AT_IMAGES,
    DEFAULT_TARGETS_PCT,
    Question,
    Reach,
    best_planners,
    front_points,
    front_table,
    study_questions,
)
from experiments.runs import (  # noqa: E402
    RunDirectoryError,
    load_runs,
    method_name,
    method_sort_key,
    runs_frame,
    scene_name,
)
from experiments.tables import latex_escape  # noqa: E402
from pipeline.protocol import PROTOCOL
from planner.budget import DEFAULT_LEVEL  # noqa: E402
from scene.io import write_atomic, write_text_atomic  # noqa: E402

log = logging.getLogger(__name__)


def seed_claims(
    runs: pd.DataFrame,
    questions: Sequence[Question],
    floor: Mapping | None = None,
    axis: str = "budget",
) -> pd.DataFrame:
    """Each question per scene answered on each seed's fronts alone (a planner's cells of that seed
    at each budget), and the claim that survives every seed.

    Columns: scene, question, ``best`` (the planner best on every seed and alone there, else
    ``tie: A, B`` over every planner best or tied on some seed, ``A on 1 of 3 seeds`` when some seed's
    fronts do not answer or some planner has no cell of that seed, ``–`` when none does),
    ``seed_<k>`` (that seed's best, ``A = B`` for a tie within the floor)."""
    rows = []
    points = front_points(runs, axis=axis, by_seed=True)
    seeds = sorted(points["seed"].unique()) if not points.empty else []
    for scene, at_scene in points.groupby("scene", sort=False):
        planners = set(at_scene["planner"])
        for question in questions:
            per_seed = {}
            for seed in seeds:
                fronts = {
                    planner: front
                    for planner, front in at_scene[at_scene["seed"] == seed].groupby("planner", sort=False)
                }
                # a seed some planner of the scene has no cell of compares nothing: n/a
                per_seed[seed] = best_planners(fronts, question, floor) if set(fronts) == planners else None
            answered = [b for b in per_seed.values() if b]
            tied = sorted({p for b in answered for p in b}, key=method_sort_key)
            names = ", ".join(method_name(p) for p in tied)
            if not answered:
                best = "–"
            elif len(answered) < len(per_seed):
                best = (
                    f"{'tie: ' if len(tied) > 1 else ''}{names} on {len(answered)} of {len(per_seed)} seeds"
                )
            elif len(tied) == 1:
                best = names
            else:
                best = f"tie: {names}"
            row = {"scene": scene, "question": question.text(), "best": best}
            for seed, b in per_seed.items():
                row[f"seed_{seed}"] = "n/a" if b is None else (" = ".join(method_name(p) for p in b) or "–")
            rows.append(row)
    return pd.DataFrame(rows)


def seed_ranges(runs: pd.DataFrame, questions: Sequence[Question], axis: str = "budget") -> pd.DataFrame:
    """Per scene and planner, each question's answer on each seed's front alone, as ``min–max`` over
    the seeds (``not reached`` counted: ``1 of 3 not reached``). Columns: scene, method, seeds, one per
    question."""
    points = front_points(runs, axis=axis, by_seed=True)
    rows = []
    for (scene, planner), fronts in points.groupby(["scene", "planner"], sort=False):
        per_seed = [front for _, front in fronts.groupby("seed", sort=True)]
        row = {"scene": scene, "method": method_name(planner), "seeds": len(per_seed)}
        for question in questions:
            answers = np.array([question.answer(front) for front in per_seed])
            decimals = 0 if question.kind == "images" else 1
            row[question.text()] = _range_text(answers, decimals)
        rows.append(row)
    return pd.DataFrame(rows)


def _range_text(answers: np.ndarray, decimals: int) -> str:
    finite = answers[np.isfinite(answers)]
    if not len(finite):
        return "–"
    lo, hi = float(finite.min()), float(finite.max())
    text = (
        f"{lo:,.{decimals}f}"
        if f"{lo:,.{decimals}f}" == f"{hi:,.{decimals}f}"
        else (f"{lo:,.{decimals}f}–{hi:,.{decimals}f}")
    )
    missing = len(answers) - len(finite)
    return text + (f" ({missing} of {len(answers)}: –)" if missing else "")


def seeds_markdown(ranges: pd.DataFrame, claims: pd.DataFrame, floor: Mapping | None = None) -> str:
    """Per scene: each planner's answers as ranges over seeds, then the claims that hold on every seed."""
    tie = (
        f"within the noise floor of the best (completeness {float(floor.get(COMPLETENESS, 0.0)):.1f} "
        f"points, acc90 {float(floor.get(ACCURACY, 0.0)) * 100:.1f} cm)"
        if floor
        else "equal as computed (no noise floor given)"
    )
    lines = [
        "**Seed by seed.** Each seed's fronts on their own (a planner's cells of that seed at each budget): "
        "the answer as its range over the seeds (–: not reached, or outside the front's images), and "
        f"the planner best on every seed; a planner best on one seed and not another, or {tie} on any, "
        "makes the question a tie.",
        "",
    ]
    for scene, rows in ranges.groupby("scene", sort=False):
        columns = [c for c in rows.columns if c not in ("scene",)]
        lines += [
            f"*{scene_name(scene)}*",
            "",
            "| " + " | ".join(c[0].upper() + c[1:] for c in columns) + " |",
        ]
        lines.append("| :-- | " + " | ".join("--:" for _ in columns[1:]) + " |")
        lines += ["| " + " | ".join(str(r[c]) for c in columns) + " |" for _, r in rows.iterrows()]
        lines.append("")
        at_scene = claims[claims["scene"] == scene]
        seed_columns = [c for c in at_scene.columns if c.startswith("seed_")]
        lines += [
            "| Question | Best on every seed | " + " | ".join(f"Seed {c[5:]}" for c in seed_columns) + " |"
        ]
        lines.append("| :-- | :-- | " + " | ".join(":--" for _ in seed_columns) + " |")
        lines += [
            f"| {r['question']} | {r['best']} | " + " | ".join(str(r[c]) for c in seed_columns) + " |"
            for _, r in at_scene.iterrows()
        ]
        lines.append("")
    return "\n".join(lines)


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


def _cells(n: int) -> str:
    return f"{n} cell" + ("" if n == 1 else "s")


def headline_markdown(points: pd.DataFrame) -> str:
    """The README's headline table: one row per scene and planner, each column's values per budget
    (fewest images first, ``a / b / c``), means over seeds; ``Seeds`` counts them per budget. Its
    first line names the protocol and the number of cells."""

    def per_budget(group: pd.DataFrame, column: str, scale: float, decimals: int) -> str:
        return " / ".join(_value_cell(v * scale, decimals) for v in group[column])

    n_cells = _cells(int(points["n"].sum()))
    lines = [
        f"Protocol {PROTOCOL} ([results/protocol.md](results/protocol.md)), {n_cells}:",
        "",
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
    floor: Mapping | None = None,
) -> list[Path]:
    """Write the front table (Markdown, CSV, LaTeX), its points (``front_points.csv``), the answers
    seed by seed with the claims that hold on every seed (``fronts_by_seed.md``, ``claims.csv``; ties
    within ``floor``, a ``noise_floor.json``'s floor), the GSD axis's front where cells flew more than
    one GSD (``fronts_gsd.md``, ``fronts_gsd_by_seed.md``) and the two front figures into ``out_dir``;
    return the files written."""
    out_dir = Path(out_dir)
    points = front_points(runs)
    if points.empty:
        raise RunDirectoryError("no successful run: no front to draw")
    table = front_table(points, targets_pct, at_images)
    questions = study_questions(targets_pct, at_images)
    claims = seed_claims(runs, questions, floor)
    written = [
        write_text_atomic(out_dir / "fronts.md", to_markdown(table, targets_pct, at_images)),
        write_text_atomic(out_dir / "fronts.tex", to_latex(table, targets_pct, at_images)),
        write_text_atomic(out_dir / "fronts.csv", table.to_csv(index=False, lineterminator="\n")),
        write_text_atomic(out_dir / "front_points.csv", points.to_csv(index=False, lineterminator="\n")),
        write_text_atomic(out_dir / "headline.md", headline_markdown(points)),
        write_text_atomic(
            out_dir / "fronts_by_seed.md", seeds_markdown(seed_ranges(runs, questions), claims, floor)
        ),
        write_text_atomic(out_dir / "claims.csv", claims.to_csv(index=False, lineterminator="\n")),
    ]
    gsd_points = front_points(runs, axis="gsd")
    if not gsd_points.empty and gsd_points.groupby(["scene", "planner"]).size().max() > 1:
        gsd_table = front_table(gsd_points, targets_pct, at_images)
        gsd_claims = seed_claims(runs, questions, floor, axis="gsd")
        gsd_ranges = seed_ranges(runs, questions, axis="gsd")
        written += [
            write_text_atomic(out_dir / "fronts_gsd.md", to_markdown(gsd_table, targets_pct, at_images)),
            write_text_atomic(
                out_dir / "front_points_gsd.csv", gsd_points.to_csv(index=False, lineterminator="\n")
            ),
            write_text_atomic(
                out_dir / "fronts_gsd_by_seed.md", seeds_markdown(gsd_ranges, gsd_claims, floor)
            ),
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
