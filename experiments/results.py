"""The study's published results, regenerated from the committed cell records alone.

    uavplan-study results --readme README.md  # the current study: results/cells/protocol<N> -> results/study/
    uavplan-study results NAME --out DIR        # another folder of records: results/cells/NAME -> DIR/NAME/

A study is a folder of cell records, ``results/cells/<study>/<scene>/<planner>/gsd<g>/<budget>/seed<k>/``
(``metrics.json`` and ``plan.json``, written and committed by ``experiments.record`` as each cell
finishes). Only the records of the current protocol and of each planner's current version are read
(``current_records``; results/protocol.md). For each study this writes into ``<out>/<study>/``:

- ``tables/``: the paper's Table I and II, the surfaces table and the summaries of
  ``experiments.tables``, over the cells at the default budget (mean and spread over seeds);
- ``fronts.{md,csv,tex}``, ``front_points.csv``, ``fronts_images.png``, ``fronts_flight_time.png``:
  quality per image over every budget (``experiments.fronts``);
- ``headline.md``: the README's headline table (``--readme README.md`` splices it in between the
  README's ``HEADLINE_BEGIN`` and ``HEADLINE_END`` lines, so the README never drifts from the records);
- ``cells.csv``: every record's ``metrics.json``, one row per cell;
- ``README.md``: what the cells are, the code revisions and machines they come from (and, from the
  repository's git history, the files between two revisions), the commands.

Nothing is read from run directories (images, clouds): a fresh clone regenerates the same files.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

from evaluate.record import git
from experiments.front_core import DEFAULT_AT_IMAGES, DEFAULT_TARGETS_PCT, on_axis
from experiments.fronts import write_fronts
from experiments.noise_floor import load_repeats, noise_floor, summarise_repeats
from experiments.runs import RunDirectoryError, load_runs, method_sort_key, runs_frame, scene_name
from experiments.study_plan import (
    PAST_RECORDS,
    STUDY_PRESET,
    past_cell_hours,
    plan_table,
    recorded_specs,
    study_cells,
)
from experiments.tables import code_provenance, tables_from_runs, write_tables
from pipeline.protocol import PROTOCOL, planner_version
from planner.budget import DEFAULT_LEVEL, level_rank
from scene.io import write_text_atomic

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
CELLS = ROOT / "results" / "cells"
HEADLINE_BEGIN = "<!-- headline table: uavplan-study results --readme README.md -->"
HEADLINE_END = "<!-- end of the headline table -->"


def study_runs(cells_dir: Path) -> pd.DataFrame:
    """Every record under ``cells_dir`` as a per-run frame, ``run_dir`` relative to ``cells_dir``
    (so the tables do not depend on where the repository lies)."""
    runs = runs_frame(load_runs([cells_dir]))
    base = cells_dir.resolve()
    runs["run_dir"] = [Path(d).relative_to(base).as_posix() for d in runs["run_dir"]]
    return runs


def current_records(runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(the records of the current protocol and of their planner's current version, the others).

    A planner whose config the repository does not have (one from outside) counts at version None."""

    def version(planner: str) -> int | None:
        try:
            return planner_version(planner)
        except (HydraException, OmegaConfBaseException, ValueError):
            return None

    versions = {planner: version(planner) for planner in runs["planner"].unique()}
    protocol = runs.get("protocol", pd.Series(index=runs.index, dtype=float))
    recorded = runs.get("planner_version", pd.Series(index=runs.index, dtype=float))
    current = [
        p == PROTOCOL and (v == versions[planner] if versions[planner] is not None else pd.isna(v))
        for p, v, planner in zip(protocol, recorded, runs["planner"], strict=True)
    ]
    keep = pd.Series(current, index=runs.index, dtype=bool)
    return runs[keep].reset_index(drop=True), runs[~keep].reset_index(drop=True)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _machines(runs: pd.DataFrame) -> str:
    if "machine_cpu" not in runs:
        return "not recorded (cells that predate the machine fields of metrics.json)"
    cpu = runs["machine_cpu"].fillna("not recorded")
    cpus = runs.get("machine_cpus", pd.Series(index=runs.index, dtype=float))
    labels = [f"{c} x {int(n)}" if pd.notna(n) else str(c) for c, n in zip(cpu, cpus, strict=True)]
    counts = pd.Series(labels).value_counts(sort=False)
    return "; ".join(f"{label} ({_count(n, 'cell')})" for label, n in counts.items())


def revision_lineage(
    commits: Sequence[str], repo: Path | None = None
) -> tuple[str, dict[str, list[str]]] | None:
    """The revision of ``commits`` that contains all the others, and per other one the files it changes.

    A study whose cells come from two revisions is still one study when the newer revision is the
    older plus changes to files a reader can judge (a fix to one planner leaves the others' cells
    what the newer code computes). ``repo``: the project's by default. Returns None when the commits
    are not known to its git or none of them descends from all the others.
    """
    commits = list(dict.fromkeys(commits))
    for newest in commits:
        older = [c for c in commits if c != newest]
        if all(git("merge-base", "--is-ancestor", c, newest, repo=repo) is not None for c in older):
            diffs = {c: git("diff", "--name-only", c, newest, repo=repo) for c in older}
            if any(d is None for d in diffs.values()):
                return None
            return newest, {c: d.splitlines() for c, d in diffs.items()}
    return None


def _revision_lines(runs: pd.DataFrame) -> tuple[str, list[str]]:
    """The revision new cells run at (short) and the lines telling how the study's revisions differ.

    One revision: that one. Several: the one containing the others (``revision_lineage``), with the
    files each older one lacks; HEAD when no such revision is known."""
    commits = list(dict.fromkeys(runs.get("code_commit", pd.Series(dtype=object)).dropna()))
    if len(commits) == 1:
        return str(commits[0])[:7], []
    lineage = revision_lineage(commits) if commits else None
    if lineage is None:
        return "HEAD", []
    newest, changes = lineage
    lines = [
        f"**Between the revisions.** {newest[:10]} is {old[:10]} plus changes to "
        + (", ".join(f"`{f}`" for f in files) if files else "no file")
        + f" (`git diff {old[:10]} {newest[:10]}`): cells that run none of them compute the same at both;"
        + f" `python -m experiments.replan <record> --revision {old[:7]} {newest[:7]}` checks a cell's plan."
        for old, files in changes.items()
    ]
    return newest[:7], lines


def study_cost(runs: pd.DataFrame) -> list[str]:
    """The README's cost lines: cell-hours per scene and planner, wall (CPU), summed over the
    recorded cells' ``cell_wall_time_s`` (``cell_cpu_time_s``); none when no cell recorded them."""
    if "cell_wall_time_s" not in runs or not runs["cell_wall_time_s"].notna().any():
        return []
    hours = runs.assign(
        wall=pd.to_numeric(runs["cell_wall_time_s"], errors="coerce") / 3600.0,
        cpu=pd.to_numeric(runs.get("cell_cpu_time_s", pd.Series(index=runs.index)), errors="coerce") / 3600.0,
    )
    scenes = list(dict.fromkeys(hours["scene"]))
    planners = sorted(hours["planner"].unique(), key=method_sort_key)
    cells = hours.groupby(["planner", "scene"])[["wall", "cpu"]].sum(min_count=1)

    def cell(planner, scene) -> str:
        if (planner, scene) not in cells.index:
            return "–"
        wall, cpu = cells.loc[(planner, scene)]
        return "–" if pd.isna(wall) else f"{wall:.1f}" + ("" if pd.isna(cpu) else f" ({cpu:.1f})")

    total_wall, total_cpu = hours["wall"].sum(), hours["cpu"].sum(min_count=1)
    cpu_text = "" if pd.isna(total_cpu) else f" ({total_cpu:.1f} h CPU)"
    return [
        f"**Cost.** {total_wall:.1f} cell-hours of wall time{cpu_text}, per scene and planner (CPU hours"
        " in brackets where recorded):",
        "",
        "| planner | " + " | ".join(scene_name(sc) for sc in scenes) + " |",
        "| :-- | " + " | ".join("--:" for _ in scenes) + " |",
        *(f"| {p} | " + " | ".join(cell(p, sc) for sc in scenes) + " |" for p in planners),
        "",
    ]


def study_progress() -> list[str]:
    """The README's progress lines: per phase of the study plan, its cells, those recorded at the
    current protocol and planner versions, and the cell-hours left (estimated from the records)."""
    cells = study_cells()
    table = plan_table(cells, past_cell_hours(PAST_RECORDS), recorded_specs(STUDY_PRESET, cells))
    return [
        "**Progress.** The study plan's phases (`uavplan-study study-plan`; 1: the tomb's and church's",
        "fronts at seed 0, 2: the cathedral, 3: the noise floor, 4: seeds 1 and 2, 5: the shared meshes,",
        "6: the GSD axis, 7: Yan at the seed paper's scale); cell-hours left are estimated from the",
        "records of the same scene, planner and budget, this study's first:",
        "",
        "| phase | cells | recorded | cell-hours left |",
        "| --: | --: | --: | --: |",
        *(f"| {r.phase} | {r.cells} | {r.recorded} | {r.hours_left:.1f} |" for r in table.itertuples()),
        "",
    ]


def study_readme(study: str, runs: pd.DataFrame, n_left_out: int = 0, progress: bool = True) -> str:
    """The study folder's README: cells, protocol, code, machines, how to run and regenerate."""
    ok = runs[runs["status"] == "ok"]
    scenes = ", ".join(dict.fromkeys(scene_name(s) for s in runs["scene"]))
    per_planner = runs.groupby("planner", sort=False).agg(
        budgets=("budget", lambda b: ", ".join(sorted(set(b), key=level_rank))),
        seeds=("seed", lambda s: ", ".join(str(x) for x in sorted(set(s)))),
        cells=("seed", "size"),
    )
    per_planner = per_planner.loc[sorted(per_planner.index, key=method_sort_key)]
    _, between = _revision_lines(runs)
    lines = [
        f"# Study `{study}`",
        "",
        f"{_count(len(runs), 'cell')} ({len(runs) - len(ok)} failed) on {scenes}. Generated by "
        f"`uavplan-study results {study}` from `results/cells/{study}/`; do not edit by hand.",
        "",
        "| planner | budgets | seeds | cells |",
        "| :-- | :-- | :-- | --: |",
        *(f"| {p} | {r.budgets} | {r.seeds} | {r.cells} |" for p, r in per_planner.iterrows()),
        "",
        f"**Protocol.** Protocol {PROTOCOL} (`results/protocol.md`): every record here is of it and of its "
        f"planner's current version; {_count(n_left_out, 'record')} of other protocols, off the protocol "
        "or of an older plan left out.",
        "",
        code_provenance(runs)[0].strip(),
        "",
        *(line for text in between for line in (text, "")),
        f"**Machines.** {_machines(runs)}.",
        "",
        *study_cost(runs),
        *(study_progress() if study == STUDY_PRESET and progress else []),
        "**Files.** `tables/tables.md` (Tables I and II at the default budget), `fronts.md` and",
        "`fronts_images.png` / `fronts_flight_time.png` (quality per image over every budget),",
        "`headline.md` (the top-level README's table, per budget), `cells.csv` (every cell's metrics.json).",
        "",
        "**Run it.** One command runs the cells left (a cell counts once it has a record of the current",
        "protocol at its planner's current version), one at a time from a worktree of HEAD, commits each",
        "record as it finishes and starts no cell that would not finish by `--until`; on a cluster, add",
        "`--launcher ray --jobs N` (or `slurm`). Then the tables, fronts and the README's headline:",
        "",
        "```bash",
        "uavplan-study study-plan                     # the cells left by phase, cell-hours",
        "uavplan-study study-plan --run --until 18:00",
        "uavplan-study results --readme README.md",
        "```",
        "",
    ]
    return "\n".join(lines)


def study_noise_floor(noise_dir: Path) -> dict[str, float] | None:
    """The noise floor of a study's repeats (``results/cells/<study>_noise/rep<k>/``, the study plan's
    phase 3; ``experiments.noise_floor``) at the current protocol, or None while no cell has two
    recorded repeats."""
    if not Path(noise_dir).is_dir():
        return None
    try:
        repeats, _ = current_records(load_repeats(noise_dir))
    except RunDirectoryError:
        return None
    if repeats.empty:
        return None
    summary = summarise_repeats(repeats)
    return noise_floor(summary) or None


def write_study(
    study: str,
    cells_root: Path = CELLS,
    out_root: Path = ROOT / "results",
    targets_pct: Sequence[float] = DEFAULT_TARGETS_PCT,
    at_images: Sequence[int] = DEFAULT_AT_IMAGES,
    out_name: str | None = None,
) -> list[Path]:
    """Regenerate ``out_root/<out_name or study>/`` from the current records of
    ``cells_root/<study>/`` (``current_records``); return the files written. The fronts ask for the
    images to reach each of ``targets_pct`` and compare at each of ``at_images``.

    The folder is built beside its place and swapped in whole, so it never mixes files of two
    generations (a table a study no longer has is gone, not left stale).

    Raises:
        RunDirectoryError: the study folder is missing or holds no record.
    """
    runs, left_out = current_records(study_runs(Path(cells_root) / study))
    if runs.empty:
        raise RunDirectoryError(
            f"{Path(cells_root) / study}: no record of protocol {PROTOCOL} at its planner's current version "
            f"({_count(len(left_out), 'record')} of others)"
        )
    floor = study_noise_floor(Path(cells_root) / f"{study}_noise")
    out = Path(out_root) / (out_name or study)
    out.parent.mkdir(parents=True, exist_ok=True)
    build = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        written = []
        own_knob = on_axis(runs, "budget").drop(columns="gsd_m")  # Tables I and II: the survey's GSD
        at_default = own_knob[own_knob["budget"] == DEFAULT_LEVEL]
        if len(at_default):
            written += write_tables(
                tables_from_runs(at_default.reset_index(drop=True), floor), build / "tables"
            )
        if (runs["status"] == "ok").any():
            written += write_fronts(runs, build, targets_pct, at_images, floor=floor)
        written.append(write_text_atomic(build / "cells.csv", runs.to_csv(index=False, lineterminator="\n")))
        progress = Path(cells_root).resolve() == CELLS.resolve()  # the study plan reads results/cells
        readme = study_readme(study, runs, len(left_out), progress)
        written.append(write_text_atomic(build / "README.md", readme))
        os.chmod(build, 0o755)
        old = out.with_name(f".{out.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        if out.exists():
            os.replace(out, old)
        os.replace(build, out)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(build, ignore_errors=True)
        raise
    return [out / p.relative_to(build) for p in written]


def study_folder(study: str) -> str:
    """Where a study's results go under ``results/``: the current protocol's study in ``study/``
    (what the README links), any other in a folder of its name."""
    return "study" if study == STUDY_PRESET else study


def splice_headline(readme: str, table: str) -> str:
    """``readme`` with the lines between its ``HEADLINE_BEGIN`` and ``HEADLINE_END`` lines replaced by
    ``table``.

    Raises:
        ValueError: the README lacks either marker line, or has them out of order.
    """
    lines = readme.splitlines(keepends=True)
    stripped = [line.strip() for line in lines]
    try:
        begin, end = stripped.index(HEADLINE_BEGIN), stripped.index(HEADLINE_END)
    except ValueError:
        raise ValueError(f"the README has no '{HEADLINE_BEGIN}' ... '{HEADLINE_END}' lines") from None
    if end < begin:
        raise ValueError("the README's headline end marker comes before its begin marker")
    return "".join(lines[: begin + 1]) + table + "".join(lines[end:])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-study results", description=__doc__.split("\n")[0])
    parser.add_argument("studies", nargs="*", help="study folders under --cells (default: all of them)")
    parser.add_argument("--cells", type=Path, default=CELLS, help="the records' root (results/cells)")
    parser.add_argument("--out", type=Path, default=ROOT / "results", help="where <study>/ is written")
    parser.add_argument(
        "--readme", type=Path, help="splice the (one) study's headline.md into this README's headline block"
    )
    parser.add_argument(
        "--targets", type=float, nargs="+", default=list(DEFAULT_TARGETS_PCT), help="completeness levels (%%)"
    )
    parser.add_argument(
        "--at-images", type=int, nargs="+", default=list(DEFAULT_AT_IMAGES), help="image counts compared at"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    studies = args.studies or [STUDY_PRESET]
    if not studies:
        print(f"error: no study folder under {args.cells}", file=sys.stderr)
        return 2
    if args.readme and len(studies) != 1:
        print(f"error: --readme takes one study, not {len(studies)}", file=sys.stderr)
        return 2
    readme = None
    if args.readme:
        try:  # a README the table cannot go into is refused before the study is rewritten
            readme = args.readme.read_text()
            splice_headline(readme, "")
        except (OSError, ValueError) as exc:
            print(f"error: --readme {args.readme}: {exc}", file=sys.stderr)
            return 2
    for study in studies:
        name = study_folder(study)
        try:
            written = write_study(study, args.cells, args.out, args.targets, args.at_images, name)
        except RunDirectoryError as exc:
            print(f"error: study {study}: {exc}", file=sys.stderr)
            return 2
        print(f"{study}: {len(written)} files in {args.out / name}")
    if readme is not None:
        headline = args.out / study_folder(studies[0]) / "headline.md"
        write_text_atomic(args.readme, splice_headline(readme, headline.read_text()))
        print(f"{args.readme}: headline table from {headline}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
