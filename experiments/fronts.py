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
from pipeline.protocol import PROTOCOL
from planner.budget import DEFAULT_LEVEL, level_rank  # noqa: E402
from scene.io import write_atomic, write_text_atomic  # noqa: E402

log = logging.getLogger(__name__)

COMPLETENESS = "comp_050"  # percent at 5 cm (evaluate/settings.py)
ACCURACY = "acc90_m"
# What a front's table asks: completeness levels to reach (%) and image counts to compare at. The
# levels span what the default cells reach (about 60-90 % at 5 cm; below 60 % only the lawnmower).
DEFAULT_TARGETS_PCT = (60.0, 70.0, 80.0, 85.0, 90.0)
DEFAULT_AT_IMAGES = (100, 150, 200, 300)  # the budgets the study asks at (experiments/study_plan.py)
COSTS = {"n_images": ("images", 1.0), "flight_time_s": ("flight time (min)", 1.0 / 60.0)}
# The study's two budget axes: each planner's own knob at the survey's GSD, and the GSD at the default
# knob.
AXES = ("budget", "gsd")


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


def on_axis(runs: pd.DataFrame, axis: str = "budget") -> pd.DataFrame:
    """The runs of one budget axis, with a ``gsd_m`` column (NaN where a record does not name it).

    ``budget``: each planner's own knob at the survey's GSD (per scene the GSD most of its runs flew;
    a record without one counts as flown at it). ``gsd``: the default knob at every GSD.

    Raises:
        ValueError: an unknown axis.
    """
    if axis not in AXES:
        raise ValueError(f"axis must be one of {', '.join(AXES)}, got {axis!r}")
    runs = runs.copy()
    if "budget" not in runs:
        runs["budget"] = DEFAULT_LEVEL
    gsd = pd.to_numeric(runs.get("target_gsd_m", pd.Series(math.nan, index=runs.index)), errors="coerce")
    runs["gsd_m"] = gsd
    if axis == "gsd":
        return runs[(runs["budget"] == DEFAULT_LEVEL) & gsd.notna()]
    survey = gsd.groupby(runs["scene"]).transform(lambda g: g.mode().iloc[0] if g.notna().any() else math.nan)
    return runs[gsd.isna() | (gsd == survey)]


def front_points(
    runs: pd.DataFrame,
    columns: Sequence[str] = ("n_images", "flight_time_s", COMPLETENESS, ACCURACY),
    axis: str = "budget",
    by_seed: bool = False,
) -> pd.DataFrame:
    """One row per (scene, planner, budget), or with ``by_seed`` per (scene, planner, seed, budget), over
    the successful runs of ``axis`` (``on_axis``; on the ``gsd`` axis the ``budget`` column names the
    GSD, ``gsd3cm``): the mean and sample standard
    deviation of each of ``columns`` (``<column>`` and ``<column>_std``), ``n`` seeds, ``budget_value``,
    in table order (scene, method, budget fewest images first: on the GSD axis the coarsest first)."""
    ok = on_axis(runs[runs["status"] == "ok"], axis)
    if axis == "gsd":
        ok["budget_value"] = ok["gsd_m"]
        ok["budget"] = ok["gsd_m"].map(gsd_level)
    rows = []
    keys = ["scene", "planner", "seed", "budget"] if by_seed else ["scene", "planner", "budget"]
    for key, group in ok.groupby(keys, sort=False):
        row = dict(zip(keys, key, strict=True))
        row.update(method=method_name(row["planner"]), n=len(group))
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
        lambda r: (
            scene_sort_key(r["scene"]),
            method_sort_key(r["planner"]),
            r["seed"] if by_seed else 0,
            axis_rank(r["budget"]),
        ),
        axis=1,
    )
    return points.loc[order.sort_values().index].reset_index(drop=True)


def gsd_level(gsd_m: float) -> str:
    """A GSD as a point of the GSD axis: ``gsd3cm``, ``gsd4.5cm``."""
    return f"gsd{gsd_m * 100:g}cm"


def axis_rank(level: str) -> float:
    """Budget order on either axis: a budget level's rank; a GSD level coarsest first."""
    if level.startswith("gsd") and level.endswith("cm"):
        return -float(level[3:-2])
    return float(level_rank(level))


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


@dataclass(frozen=True)
class Question:
    """One question a front answers, asked of every planner of a scene.

    Attributes:
        kind: ``images`` / ``minutes`` (the cost to reach ``level`` % completeness at 5 cm, lower is
            better) or ``completeness`` / ``acc90`` (the value at ``level`` images; completeness
            higher, acc90 lower is better).
        level: the completeness (%) or the image count.
    """

    kind: str
    level: float

    def text(self) -> str:
        if self.kind in ("images", "minutes"):
            unit = "images" if self.kind == "images" else "flight minutes"
            return f"{unit} to {self.level:g} %"
        return f"{'completeness' if self.kind == 'completeness' else 'acc90'} at {self.level:g} images"

    def answer(self, front: pd.DataFrame, slack: float = 0.0) -> float:
        """The front's answer (NaN: not reached, or outside the front's images). ``slack`` lowers a
        completeness level (noise floor, points) or moves a value towards better (for a tie test)."""
        images = front["n_images"].to_numpy(float)
        comp = front[COMPLETENESS].to_numpy(float)
        if self.kind == "images":
            return cost_to_reach(images, comp, self.level - slack).cost
        if self.kind == "minutes":
            return cost_to_reach(front["flight_time_s"].to_numpy(float) / 60.0, comp, self.level - slack).cost
        if self.kind == "completeness":
            return value_at(images, comp, self.level) + slack
        return value_at(images, front[ACCURACY].to_numpy(float) * 100.0, self.level) - slack

    @property
    def lower_is_better(self) -> bool:
        return self.kind != "completeness"

    def floor_key(self) -> str:
        """The noise floor's metric behind this question's tie (``noise_floor.json``)."""
        return ACCURACY if self.kind == "acc90" else COMPLETENESS


def study_questions(targets_pct=DEFAULT_TARGETS_PCT, at_images=DEFAULT_AT_IMAGES) -> list[Question]:
    """Images and flight minutes to each completeness target, completeness and acc90 at each count."""
    return (
        [Question("images", t) for t in targets_pct]
        + [Question("minutes", t) for t in targets_pct]
        + [Question("completeness", n) for n in at_images]
        + [Question("acc90", n) for n in at_images]
    )


def best_planners(fronts: dict[str, pd.DataFrame], question: Question, floor: Mapping | None = None) -> tuple:
    """The planners best at ``question`` on one draw of every front (planner -> its points in budget
    order), with every planner within the noise floor of the best: one that reaches the completeness
    target less the floor with no more images (minutes) than the best needs for the target, or whose
    value at the image count lies within the floor of the best. Empty when no front answers."""
    slack = 0.0
    if floor is not None:
        slack = float(floor.get(question.floor_key(), 0.0)) * (100.0 if question.kind == "acc90" else 1.0)
    answers = {p: question.answer(f) for p, f in fronts.items()}
    answered = {p: a for p, a in answers.items() if math.isfinite(a)}
    if not answered:
        return ()
    if question.lower_is_better:
        best = min(answered.values())
        tied = [p for p, f in fronts.items() if question.answer(f, slack) <= best]
    else:
        best = max(answered.values())
        tied = [p for p, f in fronts.items() if question.answer(f, slack) >= best]
    return tuple(sorted(tied, key=method_sort_key))


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
