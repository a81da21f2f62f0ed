"""What a budget front is and what the study asks of it: a planner's points on one axis (budget or
GSD), the cost to reach a completeness and the value at an image count (``Reach``,
``cost_to_reach``, ``value_at``), the front table, and the study's questions with the planners that
answer them best. ``experiments.fronts`` writes them (tables, headline, seeds, plots)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from experiments.runs import (
    method_name,
    method_sort_key,
    scene_sort_key,
)
from planner.budget import DEFAULT_LEVEL, level_rank

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
