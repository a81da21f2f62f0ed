"""The paper's Table I (accuracy, completeness) and Table II (images, alignment time) from run directories.

    uavplan-study tables multirun/2026-11-23_06-00-00 outputs/tomb --out tables/

writes ``table1.{md,tex,csv}``, ``table2.{md,tex,csv}``, ``surfaces.{md,tex,csv}`` (completeness
at 0.050 m per kind of surface: where a flight misses), ``tables.md`` (all three, for reading),
``all_metrics.csv`` (every numeric metric summarised) and ``runs.csv`` (one row per run).
``tables.md`` ends with the code revisions the runs came from; runs of several revisions are
flagged (a table that mixes code versions compares more than the planners).
Across seeds a cell shows mean ± sample standard deviation (ddof 1) over the runs that succeeded.

With ``--noise-floor noise_floor.json`` (``experiments.noise_floor``) a method whose value lies closer
to the best than the floor of that metric is tied for best and bold with it: the same cell run again
moves by that much on its own. The tables then say which floor they used.
"""

from __future__ import annotations

import io
import logging
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.noise_floor import read_floor
from experiments.runs import (
    RunDirectoryError,
    load_runs,
    method_sort_key,
    out_is_a_file,
    runs_frame,
    scene_name,
    scene_sort_key,
    tool_parser,
)
from experiments.table_specs import (
    METHOD_CITATIONS,
    NOTE_MAX_CHARS,
    SUMMARY_COLUMNS,
    TABLE_ABLATION,
    TABLE_ABLATION_CAPTION,
    TABLE_I,
    TABLE_I_CAPTION,
    TABLE_II,
    TABLE_II_CAPTION,
    TABLE_SURFACES,
    TABLE_SURFACES_CAPTION,
    MetricSpec,
    ablation_planners,
)
from planner.budget import DEFAULT_LEVEL, level_rank
from scene.io import write_text_atomic

log = logging.getLogger(__name__)


def summarise(
    runs: pd.DataFrame, specs: Sequence[MetricSpec], noise_floor: Mapping[str, float] | None = None
) -> pd.DataFrame:
    """Mean, spread and best flag of each metric per (scene, planner, budget), in table order.

    Args:
        runs: one row per run (``experiments.runs.runs_frame``): scene, planner, method, seed,
            status, error and the metric columns.
        specs: the metrics to summarise.
        noise_floor: metric -> run-to-run noise in the stored unit (``experiments.noise_floor``);
            a value closer to the best than this is a tie and marked best too. None: exact ties only.

    Returns:
        A tidy frame with ``SUMMARY_COLUMNS``: one row per (scene, planner, budget, metric); the
        method name carries a budget other than the default. ``mean`` and
        ``std`` (sample, ddof 1; NaN below two runs) are in the shown unit over the successful runs
        with a finite value, ``n`` counts them, ``n_runs``/``n_failed`` count the group's runs and
        failures, ``errors`` lists the failed seeds' errors, ``best`` marks the best shown value of
        the scene for metrics with a direction (ties all marked, within the noise floor when one is
        given; only where two methods have a value).
    """
    missing = {"scene", "planner", "seed", "status"} - set(runs.columns)
    if missing:
        raise ValueError(f"run records lack {sorted(missing)}")
    rows = []
    if "budget" not in runs:  # records that predate budgets ran at the default one
        runs = runs.assign(budget=DEFAULT_LEVEL)
    groups = sorted(
        runs.groupby(["scene", "planner", "budget"], sort=False),
        key=lambda g: (scene_sort_key(g[0][0]), method_sort_key(g[0][1]), level_rank(g[0][2])),
    )
    for (scene, planner, budget), group in groups:
        ok = group[group["status"] == "ok"]
        failed = group[group["status"] != "ok"]
        errors = _error_summary(failed)
        method = group["method"].iloc[0] if "method" in group else planner
        for spec in specs:
            if spec.column in ok:
                values = pd.to_numeric(ok[spec.column], errors="coerce").to_numpy(dtype=float) * spec.scale
            else:
                values = np.array([], dtype=float)
            values = values[np.isfinite(values)]
            rows.append(
                {
                    "scene": scene,
                    "planner": planner,
                    "budget": budget,
                    "method": method,
                    "metric": spec.column,
                    "label": spec.label,
                    "mean": float(values.mean()) if len(values) else math.nan,
                    "std": float(values.std(ddof=1)) if len(values) > 1 else math.nan,
                    "n": len(values),
                    "n_runs": len(group),
                    "n_failed": len(failed),
                    "best": False,
                    "errors": errors,
                }
            )
    summary = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    for spec in specs:
        if spec.better is None:
            continue
        for _, cells in summary[summary["metric"] == spec.column].groupby("scene", sort=False):
            # Compare the values as printed, so two cells that read the same are both bold.
            shown = cells.loc[cells["n"] > 0, "mean"].map(
                lambda v, s=spec: float(s.format(v).replace(",", ""))
            )
            if len(shown) < 2:
                continue
            target = shown.min() if spec.better == "lower" else shown.max()
            summary.loc[shown.index[tied_with(shown, target, spec, noise_floor)], "best"] = True
    return summary


def tied_with(
    shown: pd.Series, target: float, spec: MetricSpec, noise_floor: Mapping[str, float] | None
) -> pd.Series:
    """Which ``shown`` values (in the shown unit) tie ``target``: equal as printed, or closer to it
    than the metric's noise floor (stored unit, scaled here)."""
    floor = float((noise_floor or {}).get(spec.column, 0.0)) * spec.scale
    return (shown == target) | ((shown - target).abs() < floor)


def floor_sentence(specs: Sequence[MetricSpec], noise_floor: Mapping[str, float] | None) -> str:
    """The sentence under a table that names the noise floor its bolding used ('' without one)."""
    if not noise_floor:
        return ""
    parts = [
        f"{spec.label} {spec.format(noise_floor[spec.column] * spec.scale)}"
        for spec in specs
        if spec.better is not None and spec.column in noise_floor
    ]
    if not parts:
        return ""
    return (
        "Bold: the best value and every value closer to it than the noise floor (a tie): "
        + "; ".join(parts)
        + "."
    )


def _error_summary(failed: pd.DataFrame) -> str:
    by_error: dict[str, list[int]] = {}
    for seed, error in zip(failed["seed"], failed.get("error", pd.Series([""] * len(failed))), strict=True):
        text = " ".join(str(error or "unknown error").split())
        by_error.setdefault(text, []).append(int(seed))
    parts = []
    for error, seeds in by_error.items():
        label = "seed" if len(seeds) == 1 else "seeds"
        parts.append(f"{label} {', '.join(str(s) for s in sorted(seeds))}: {error}")
    return "; ".join(parts)


def read_summary_csv(path: str | Path) -> pd.DataFrame:
    """Read a table CSV written by ``write_tables`` back into the frame ``summarise`` returned."""
    frame = pd.read_csv(path, keep_default_na=False, na_values={"mean": [""], "std": [""]})
    missing = set(SUMMARY_COLUMNS) - set(frame.columns)
    if missing:
        raise ValueError(f"{path}: not a table CSV (missing {sorted(missing)})")
    frame = frame[list(SUMMARY_COLUMNS)]
    frame = frame.astype({"mean": float, "std": float, "n": int, "n_runs": int, "n_failed": int})
    frame["best"] = frame["best"].astype(str).str.lower() == "true"
    for column in ("scene", "planner", "budget", "method", "metric", "label", "errors"):
        frame[column] = frame[column].astype(str)
    return frame


def summary_csv(summary: pd.DataFrame) -> str:
    """The CSV text of a summary (full float precision; read back with ``read_summary_csv``)."""
    buf = io.StringIO()
    summary.to_csv(buf, index=False, lineterminator="\n")
    return buf.getvalue()


@dataclass
class _Cell:
    text: str
    best: bool


class _Layout:
    """Rows (scene, planner, budget) of a table with their shown cells and footnote markers."""

    def __init__(self, summary: pd.DataFrame, specs: Sequence[MetricSpec]):
        self.specs = list(specs)
        self.show_runs = bool((summary["n_runs"] > 1).any())
        self.rows: list[dict] = []
        self.notes: list[tuple[str, str]] = []
        for (scene, planner, _), cells in summary.groupby(["scene", "planner", "budget"], sort=False):
            by_metric = {row.metric: row for row in cells.itertuples()}
            first = cells.iloc[0]
            marker = ""
            if first["n_failed"] > 0:
                marker = _note_marker(len(self.notes))
                errors = first["errors"]
                if len(errors) > NOTE_MAX_CHARS:
                    errors = errors[: NOTE_MAX_CHARS - 1] + "…"
                self.notes.append((marker, f"{first['method']} on {scene_name(scene)}: {errors}"))
            metric_cells = [self._cell(by_metric.get(spec.column), spec) for spec in self.specs]
            n_ok = int(first["n_runs"] - first["n_failed"])
            runs = f"{n_ok}" if first["n_failed"] == 0 else f"{n_ok}/{int(first['n_runs'])}"
            self.rows.append(
                {
                    "scene": scene,
                    "planner": planner,
                    "method": first["method"],
                    "marker": marker,
                    "runs": runs,
                    "cells": metric_cells,
                }
            )

    @staticmethod
    def _cell(row, spec: MetricSpec) -> _Cell:
        if row is None or row.n == 0:
            failed = row is not None and row.n_failed > 0 and row.n_failed == row.n_runs
            return _Cell("failed" if failed else "n/a", False)
        text = spec.format(row.mean)
        if row.n > 1:
            text += f" ± {spec.format(row.std)}"
        return _Cell(text, bool(row.best))

    def scenes(self) -> list[tuple[str, list[dict]]]:
        grouped: dict[str, list[dict]] = {}
        for row in self.rows:
            grouped.setdefault(row["scene"], []).append(row)
        return list(grouped.items())


def _note_marker(index: int) -> str:
    letters = "abcdefghijklmnopqrstuvwxyz"
    return letters[index % 26] * (index // 26 + 1)


def to_markdown(
    summary: pd.DataFrame,
    specs: Sequence[MetricSpec],
    title: str = "",
    noise_floor: Mapping[str, float] | None = None,
) -> str:
    """A Markdown table of ``summary`` (best cells in bold, failures as footnotes); with
    ``noise_floor`` (the one ``summarise`` used) a sentence names the floor behind the bolding."""
    layout = _Layout(summary, specs)
    header = ["Scene", "Method"] + (["Runs"] if layout.show_runs else []) + [s.label for s in specs]
    align = [":--", ":--"] + (["--:"] if layout.show_runs else []) + ["--:"] * len(specs)
    lines = [f"**{title}**", ""] if title else []
    lines += ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    for scene, rows in layout.scenes():
        for i, row in enumerate(rows):
            method = row["method"] + (f" ({row['marker']})" if row["marker"] else "")
            cells = [f"**{c.text}**" if c.best else c.text for c in row["cells"]]
            lead = [scene_name(scene) if i == 0 else "", method] + ([row["runs"]] if layout.show_runs else [])
            lines.append("| " + " | ".join(lead + cells) + " |")
    if layout.show_runs:
        lines += [
            "",
            "Cells: mean ± sample standard deviation over the runs (seeds) that succeeded; "
            "Runs: succeeded/all.",
        ]
    floor_text = floor_sentence(specs, noise_floor)
    if floor_text:
        lines += ["", floor_text]
    if layout.notes:
        lines.append("")
        lines += [f"({marker}) {text}  " for marker, text in layout.notes]
    return "\n".join(lines) + "\n"


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped."""
    replacements = {
        "\\": r"\textbackslash{}",
        "&": r"\&",
        "%": r"\%",
        "$": r"\$",
        "#": r"\#",
        "_": r"\_",
        "{": r"\{",
        "}": r"\}",
        "~": r"\textasciitilde{}",
        "^": r"\textasciicircum{}",
        "<": r"\textless{}",
        ">": r"\textgreater{}",
        "|": r"\textbar{}",
        "…": r"\ldots{}",
    }
    return "".join(replacements.get(ch, ch) for ch in str(text))


def to_latex(
    summary: pd.DataFrame,
    specs: Sequence[MetricSpec],
    caption: str,
    label: str,
    noise_floor: Mapping[str, float] | None = None,
) -> str:
    """A booktabs + multirow LaTeX table of ``summary`` in the paper's layout (needs makecell too)."""
    layout = _Layout(summary, specs)
    floor_text = floor_sentence(specs, noise_floor)
    if floor_text:
        caption += " " + latex_escape(floor_text)
    columns = "ll" + ("r" if layout.show_runs else "") + "r" * len(specs)
    if layout.show_runs:
        caption += r" Mean $\pm$ sample standard deviation over the seeds that succeeded (Runs)."
    lines = [
        r"% Generated by experiments.tables; needs \usepackage{booktabs,multirow,makecell}",
        r"\begin{table}[t]",
        r"\centering",
        rf"\caption{{{caption}}}",
        rf"\label{{{label}}}",
        r"\setlength{\tabcolsep}{4pt}",
        rf"\begin{{tabular}}{{{columns}}}",
        r"\toprule",
        "Scene & Method"
        + (" & Runs" if layout.show_runs else "")
        + "".join(f"\n& {s.latex}" for s in specs)
        + r" \\",
    ]
    for scene, rows in layout.scenes():
        lines.append(r"\midrule")
        lines.append(rf"\multirow{{{len(rows)}}}{{*}}{{{latex_escape(scene_name(scene))}}}")
        for row in rows:
            method = latex_escape(row["method"])
            if row["planner"] in METHOD_CITATIONS:
                method += rf"~\cite{{{METHOD_CITATIONS[row['planner']]}}}"
            if row["marker"]:
                method += rf"\textsuperscript{{{row['marker']}}}"
            cells = [latex_escape(c.text).replace("±", r"$\pm$") for c in row["cells"]]
            cells = [rf"\textbf{{{t}}}" if c.best else t for t, c in zip(cells, row["cells"], strict=True)]
            runs = [row["runs"]] if layout.show_runs else []
            lines.append("& " + " & ".join([method, *runs, *cells]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    if layout.notes:
        lines.append(r"\par\smallskip\footnotesize\raggedright")
        lines += [rf"\textsuperscript{{{m}}}~{latex_escape(t)}\\" for m, t in layout.notes]
    lines.append(r"\end{table}")
    return "\n".join(lines) + "\n"


def build_tables(
    run_paths: Sequence[str | Path], noise_floor: Mapping[str, float] | None = None
) -> dict[str, pd.DataFrame]:
    """Load the runs under ``run_paths`` and summarise them (ties within ``noise_floor``, see
    ``summarise``).

    Returns:
        ``{"runs": per-run frame, "table1": Table I summary, "table2": Table II summary,
        "surfaces": completeness per surface class, "all_metrics": summary of every numeric metric}``.

    Raises:
        RunDirectoryError: a path holds no run or a run breaks the contract.
    """
    return tables_from_runs(runs_frame(load_runs(run_paths)), noise_floor)


def tables_from_runs(
    runs: pd.DataFrame, noise_floor: Mapping[str, float] | None = None
) -> dict[str, pd.DataFrame]:
    """``build_tables`` on a per-run frame (``experiments.runs.runs_frame``) already loaded."""
    at_default = runs["budget"] == DEFAULT_LEVEL if "budget" in runs else True
    ours_variants = runs[runs["planner"].astype(str).isin(ablation_planners()) & at_default]
    ablation = (
        summarise(ours_variants, TABLE_ABLATION, noise_floor)
        if ours_variants["planner"].nunique() > 1
        else None
    )
    return {
        "runs": runs,
        **({"ablation": ablation} if ablation is not None else {}),
        "table1": summarise(runs, TABLE_I, noise_floor),
        "table2": summarise(runs, TABLE_II, noise_floor),
        "surfaces": summarise(runs, TABLE_SURFACES, noise_floor),
        "all_metrics": summarise(runs, _numeric_specs(runs)),
    }


def _numeric_specs(runs: pd.DataFrame) -> list[MetricSpec]:
    skip = {"seed"}
    specs = []
    for column in runs.columns:
        if column in skip or runs[column].dtype == bool:
            continue
        values = pd.to_numeric(runs[column], errors="coerce")
        if values.notna().any() and values.notna().sum() == runs[column].notna().sum():
            specs.append(MetricSpec(column, column, latex_escape(column), 4))
    return specs


UNRECORDED_REVISION = "unrecorded"


def _cell_names(runs: pd.DataFrame, name_seeds: bool) -> str:
    """ "Tomb Ours seeds 0-2, Church Smith et al. seeds 0/2, Church Ours seed 1": the cells of ``runs``
    in the order they come, seeds merged per scene and method (a run of consecutive seeds as a range)."""
    names: dict[str, list[int]] = {}
    for scene, method, seed in zip(runs["scene"], runs["method"], runs["seed"], strict=True):
        names.setdefault(f"{scene_name(scene)} {method}", []).append(int(seed))
    if not name_seeds:
        return ", ".join(names)

    def seeds_text(seeds: list[int]) -> str:
        seeds = sorted(set(seeds))
        if len(seeds) == 1:
            return f"seed {seeds[0]}"
        consecutive = seeds == list(range(seeds[0], seeds[-1] + 1))
        return f"seeds {seeds[0]}-{seeds[-1]}" if consecutive else "seeds " + "/".join(map(str, seeds))

    return ", ".join(f"{name} {seeds_text(seeds)}" for name, seeds in names.items())


def code_provenance(runs: pd.DataFrame) -> tuple[str, bool]:
    """A Markdown paragraph naming the code revisions of ``runs`` (``code_commit``, ``code_dirty``
    of metrics.json) and the cells of each, and whether the code behind the cells may differ: the
    runs span several revisions, or one lacks a revision or ran with uncommitted changes."""
    none = pd.Series(None, index=runs.index, dtype=object)
    commits, dirty = runs.get("code_commit", none), runs.get("code_dirty", none)
    known = commits.map(lambda c: isinstance(c, str) and bool(c))
    labels = commits.where(known, UNRECORDED_REVISION).map(
        lambda c: c[:10] if c != UNRECORDED_REVISION else c
    )
    labels = labels.where(dirty.map(lambda d: d is not True), labels + " with uncommitted changes")
    several_seeds = runs["seed"].nunique() > 1
    uncertain = labels.nunique() > 1 or not known.all() or (dirty == True).any()  # noqa: E712
    if labels.nunique() == 1:
        text = (
            f"**Code.** All {len(runs)} runs: revision {labels.iloc[0]}."
            if len(runs) > 1
            else f"**Code.** The run: revision {labels.iloc[0]}."
        )
    else:
        groups = labels.groupby(labels, sort=False).groups
        # A revision holding most cells comes first, named by the cells it lacks: a long study's
        # paragraph stays readable.
        most = max(groups, key=lambda label: len(groups[label]))
        most = most if len(groups[most]) * 2 > len(runs) else None
        order = sorted(groups, key=lambda label: label != most)
        parts = [
            f"{label} ({len(groups[label])}: "
            + (
                "every cell not named here"
                if label == most
                else _cell_names(runs.loc[groups[label]], several_seeds)
            )
            + ")"
            for label in order
        ]
        text = f"**Code.** The runs come from {labels.nunique()} revisions: " + "; ".join(parts) + "."
    if uncertain:
        text += " Differences between these cells may come from the code as well as the planners."
    return text + "\n", uncertain


def write_tables(
    tables: dict[str, pd.DataFrame], out_dir: str | Path, noise_floor: Mapping[str, float] | None = None
) -> list[Path]:
    """Write the tables of ``build_tables`` into ``out_dir`` atomically; return the files written.
    ``noise_floor`` is the one ``build_tables`` used (named under each table)."""
    out_dir = Path(out_dir)
    written = []
    floor = noise_floor
    table1_md = to_markdown(tables["table1"], TABLE_I, "Table I. " + TABLE_I_CAPTION, floor)
    table2_md = to_markdown(tables["table2"], TABLE_II, "Table II. " + TABLE_II_CAPTION, floor)
    surfaces_md = to_markdown(tables["surfaces"], TABLE_SURFACES, TABLE_SURFACES_CAPTION, floor)
    files = {
        "table1.md": table1_md,
        "table1.tex": to_latex(tables["table1"], TABLE_I, TABLE_I_CAPTION, "tab:recon_results", floor),
        "table1.csv": summary_csv(tables["table1"]),
        "table2.md": table2_md,
        "table2.tex": to_latex(tables["table2"], TABLE_II, TABLE_II_CAPTION, "tab:align_results", floor),
        "table2.csv": summary_csv(tables["table2"]),
        "surfaces.md": surfaces_md,
        "surfaces.tex": to_latex(
            tables["surfaces"], TABLE_SURFACES, TABLE_SURFACES_CAPTION, "tab:surfaces", floor
        ),
        "surfaces.csv": summary_csv(tables["surfaces"]),
        "tables.md": "\n".join((table1_md, table2_md, surfaces_md, code_provenance(tables["runs"])[0])),
        "all_metrics.csv": summary_csv(tables["all_metrics"]),
        "runs.csv": tables["runs"].to_csv(index=False, lineterminator="\n"),
    }
    if "ablation" in tables:
        ablation_md = to_markdown(tables["ablation"], TABLE_ABLATION, TABLE_ABLATION_CAPTION, floor)
        files["ablation.md"] = ablation_md
        files["ablation.tex"] = to_latex(
            tables["ablation"], TABLE_ABLATION, TABLE_ABLATION_CAPTION, "tab:ablation", floor
        )
        files["ablation.csv"] = summary_csv(tables["ablation"])
        files["tables.md"] = files["tables.md"].replace(surfaces_md, surfaces_md + "\n" + ablation_md)
    for name, text in files.items():
        written.append(write_text_atomic(out_dir / name, text))
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan-study tables DIR... --out OUT``; returns the exit status."""
    parser = tool_parser("uavplan-study tables", __doc__, "directory for the tables")
    parser.add_argument(
        "--noise-floor",
        type=Path,
        help="noise_floor.json of experiments.noise_floor: values closer to the best than it tie",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if out_is_a_file(args.out):
        return 2
    try:
        floor = read_floor(args.noise_floor) if args.noise_floor is not None else None
        tables = build_tables(args.dirs, floor)
    except (RunDirectoryError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    written = write_tables(tables, args.out, floor)
    runs = tables["runs"]
    n_failed = int((runs["status"] != "ok").sum())
    print(f"{len(runs)} runs ({n_failed} failed) -> {len(written)} files in {args.out}")
    provenance, mixed = code_provenance(runs)
    if mixed:
        log.warning(provenance.replace("**", "").strip())
    print(to_markdown(tables["table1"], TABLE_I, "Table I", floor))
    print(to_markdown(tables["table2"], TABLE_II, "Table II", floor))
    return 0


if __name__ == "__main__":
    sys.exit(main())
