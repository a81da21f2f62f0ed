"""The study at protocol 1: its cells in the order they run, what they cost, and the queue.

    uavplan-study study-plan                               # the cells by phase, cell-hours left
    uavplan-study study-plan --run --until 15:40           # resume the queue until 15:40 (any machine)
    uavplan-study study-plan --run --launcher ray --jobs 16   # fan the cells out over a Ray cluster

``--run`` hands the cells left to the record queue (``experiments.record.run_queue``): one at a time
from a worktree of HEAD, each record committed to ``results/cells/protocol<N>/`` as it finishes.
A cell counts as done when its record is of the current protocol and of its planner's current
version (``pipeline.protocol``): a planner whose version is bumped has its cells run again, nothing
else. The committed proxies the cells need (``proxies/default/<scene>/seed<k>``) are built and
committed first where one is missing. No cell starts whose estimate does not fit before
``--until``; none starts with less free disk than ``--min-free-gb``; a failed cell is recorded with
its error line and run once more; a run directory is deleted once its record is kept.

The phases, each a complete answer before the next starts:

1. the fronts at seed 0 on the tomb and the church: each planner's own budget knob at the survey's
   GSD (3 cm), with the oracle beside every cell;
2. the cathedral: every planner at its default, seed 0;
3. the noise floor: ours' and Smith's default church cells three times each from the same committed
   proxy, in the default (non-deterministic) mode, recorded under
   ``results/cells/protocol<N>_noise/rep<k>/``: the reconstruction's own spread, which the tables'
   and fronts' tie rule reads (a proxy's spread is what seeds measure);
4. seeds 1 and 2 of phase 1 (oracle off: seed 0's oracle answers plan against matcher);
5. the shared meshes (school, power plant): every planner at its default, seed 0;
6. the GSD axis at seed 0 on the tomb and the church: every planner at its default knob at 2 and
   4.5 cm (3 cm is phase 1's default cell);
7. Yan at the seed paper's scale (3000+ images), tomb, seed 0.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from experiments.launch import LAUNCHERS
from experiments.runs import RunDirectoryError, load_runs, runs_frame
from pipeline.protocol import PROTOCOL, STUDY_SCENES, planner_version
from pipeline.proxy_bundle import MANIFEST, bundle_dir
from planner.budget import DEFAULT_LEVEL, level_rank

ROOT = Path(__file__).resolve().parents[1]

PLANNERS = ("lawnmower", "smith", "yan", "ours", "ours_plus")
# The order a scene's cells run in: the paper's planner and the baseline it is read against first,
# Yan's (the slowest: hours a cell above 1000 images) last, so an interrupted phase has answers.
QUEUE_ORDER = ("ours", "smith", "lawnmower", "ours_plus", "yan")
# Each planner's own-knob levels in the study (conf/planner/<name>.yaml says what a level sets). Chosen
# so that every front spans 100-300 images where the planner can fly that few (the budget questions
# are asked at 100, 150, 200 and 300 images); Yan's start at about 220 and leave no gap over 2x.
OWN_LEVELS = {
    "lawnmower": ("low", "default", "high"),
    "smith": ("lowest", "low", "default", "high"),
    "yan": ("lowest", "low", "mid", "default", "high"),
    "ours": ("lowest", "low", "default", "high"),
    "ours_plus": ("lowest", "low", "default", "high"),
}
STUDY_PRESET = f"protocol{PROTOCOL}"  # records: results/cells/protocol<N>/; runs: study/protocol<N>/
SURVEY_GSD_M = 0.03  # conf/config.yaml survey.target_gsd_m: the own-knob axis flies at it
GSD_AXIS_M = (0.045, 0.02)  # the GSD axis besides the survey's, coarsest first
FRONT_SCENES = ("tomb", "church")
MESH_SCENES = ("school", "powerplant")
SEEDS = (0, 1, 2)
# Overrides a scene needs in every cell (conf/scene/powerplant.yaml says why).
SCENE_OVERRIDES = {scene: overrides for scene, overrides in STUDY_SCENES.items() if overrides}
# Seeds 1 and 2 without the oracle: seed 0's answers plan against matcher, and it costs a fusion.
NO_ORACLE = ("reconstruct.oracle_beside=false",)
# The noise floor's repeats reconstruct in the default, non-deterministic mode (every other cell is
# deterministic, conf/reconstruct/default.yaml), each with a stage cache of its own.
NOISE_MODE = ("reconstruct.deterministic=false",)
# The noise floor's cells (the issue asks for ours and one baseline on the church) and repeats.
NOISE_CELLS = (("church", "ours"), ("church", "smith"))
NOISE_REPEATS = 3
# Where the cell-hours of a cell not run before are guessed from: this study's records, then those
# of the studies before protocol 1 (archive/pre_p1/cells).
PAST_RECORDS = (ROOT / "results" / "cells", ROOT / "archive" / "pre_p1" / "cells")
BUNDLE_HOURS = 0.2  # building and committing one scene's proxy (about 6-10 minutes on 2 cores)
UNKNOWN_CELL_H = 0.75  # a cell no earlier record resembles (a mesh scene, a new level)


@dataclass(frozen=True)
class StudyCell:
    """One cell of the study: what ``run.py`` is given."""

    phase: int
    scene: str
    planner: str
    seed: int
    budget: str = DEFAULT_LEVEL
    gsd_m: float = SURVEY_GSD_M
    overrides: tuple[str, ...] = field(default_factory=tuple)
    repeat: int | None = None  # a noise-floor repeat: its own records and stage cache

    def spec(self) -> str:
        """The record queue's ``scene/planner/seed/budget/gsd`` form (``@rep<k>`` for a repeat)."""
        tail = "" if self.repeat is None else f"@rep{self.repeat}"
        return f"{self.scene}/{self.planner}/{self.seed}/{self.budget}/{self.gsd_m:g}{tail}"

    def preset(self, study_preset: str) -> str:
        """The record folder under results/cells/ (a repeat's: ``<preset>_noise/rep<k>``)."""
        return study_preset if self.repeat is None else f"{study_preset}_noise/rep{self.repeat}"

    def queue_cell(self) -> tuple:
        return (self.scene, self.planner, self.seed, self.budget, self.gsd_m, self.overrides)


def study_cells() -> list[StudyCell]:
    """Every cell of the study, in the order the queue runs them."""
    cells: list[StudyCell] = []

    def add(phase, scene, planner, seed, budget=DEFAULT_LEVEL, gsd_m=SURVEY_GSD_M, extra=()):
        overrides = (*SCENE_OVERRIDES.get(scene, ()), *extra)
        cells.append(StudyCell(phase, scene, planner, seed, budget, gsd_m, overrides))

    def fronts(phase, seed, extra=()):
        for scene in FRONT_SCENES:
            for planner in QUEUE_ORDER:
                for level in OWN_LEVELS[planner]:
                    add(phase, scene, planner, seed, level, extra=extra)

    fronts(1, 0)
    for planner in QUEUE_ORDER:
        add(2, "cathedral", planner, 0)
    for repeat in range(NOISE_REPEATS):
        for scene, planner in NOISE_CELLS:
            cells.append(StudyCell(3, scene, planner, 0, overrides=NOISE_MODE, repeat=repeat))
    for seed in SEEDS[1:]:
        fronts(4, seed, NO_ORACLE)
    for scene in MESH_SCENES:
        for planner in QUEUE_ORDER:
            add(5, scene, planner, 0)
    for scene in FRONT_SCENES:
        for planner in QUEUE_ORDER:
            for gsd in GSD_AXIS_M:
                add(6, scene, planner, 0, DEFAULT_LEVEL, gsd)
    add(7, "tomb", "yan", 0, "highest")
    return cells


def past_cell_hours(roots: Path | Sequence[Path]) -> pd.DataFrame:
    """Median wall hours of earlier cells per (scene, planner, budget, GSD), from the records under
    ``roots``: a group's hours come from the first root that has a cell of it (this study's own
    records before those of earlier studies)."""
    roots = [roots] if isinstance(roots, Path) else list(roots)
    frames = []
    for rank, root in enumerate(roots):
        runs = []
        for path in sorted(p for p in Path(root).iterdir() if p.is_dir()) if Path(root).is_dir() else []:
            try:
                runs += load_runs([path])
            except RunDirectoryError:
                continue
        if not runs:
            continue
        frame = runs_frame(runs)
        wall = frame.get("cell_wall_time_s", pd.Series(index=frame.index, dtype=float))
        frame = frame[(frame["status"] == "ok") & wall.notna()]
        gsd = frame.get("target_gsd_m", pd.Series(index=frame.index, dtype=float))
        frame = frame.assign(
            hours=frame["cell_wall_time_s"].astype(float) / 3600.0,
            rank=rank,
            gsd=pd.to_numeric(gsd, errors="coerce").fillna(SURVEY_GSD_M).round(6),
        )
        frames.append(frame)
    if not frames:
        return pd.DataFrame(columns=["scene", "planner", "budget", "gsd", "hours"])
    frame = pd.concat(frames, ignore_index=True)
    keys = ["scene", "planner", "budget", "gsd"]
    groups = frame.groupby([*keys, "rank"], as_index=False)["hours"].median()
    return corrected_hours(groups, keys)


def corrected_hours(groups: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Per group of ``keys``, the hours of its first root (``rank`` 0: this study's own records).
    Hours from an earlier study's root are scaled by what this study's cells cost against that
    study's same cells (the median ratio over the groups both recorded): the code in between got
    slower or faster, and its cells' estimates with it."""
    first = groups.loc[groups.groupby(keys)["rank"].idxmin()].set_index(keys)
    own = groups[groups["rank"] == 0].set_index(keys)["hours"]
    for rank in sorted(r for r in first["rank"].unique() if r > 0):
        earlier = groups[groups["rank"] == rank].set_index(keys)["hours"]
        shared = own.index.intersection(earlier.index)
        if len(shared):
            first.loc[first["rank"] == rank, "hours"] *= float((own[shared] / earlier[shared]).median())
    return first.reset_index()[[*keys, "hours"]]


def estimate_hours(cell: StudyCell, past: pd.DataFrame) -> float:
    """A cell's wall hours guessed from the earlier cells most like it: the same scene, planner and
    budget; else the same scene and planner at the default budget; else the planner's budget on any
    scene. Cells at the cell's GSD first; else those at any GSD, scaled by the image count's
    (GSD^-2). A planner at a level no record has (Yan at the seed paper's scale) counts its longest
    recorded cell twice over; a planner without any record ``UNKNOWN_CELL_H``."""
    gsd = past["gsd"] if "gsd" in past else pd.Series(SURVEY_GSD_M, index=past.index)
    masks = [
        (past["scene"] == cell.scene) & (past["planner"] == cell.planner) & (past["budget"] == cell.budget),
        (past["planner"] == cell.planner) & (past["budget"] == cell.budget),
    ]
    if level_rank(cell.budget) <= level_rank(DEFAULT_LEVEL):  # a larger budget costs more than its default
        masks.insert(
            1,
            (past["scene"] == cell.scene)
            & (past["planner"] == cell.planner)
            & (past["budget"] == DEFAULT_LEVEL),
        )
    same_gsd = (gsd - cell.gsd_m).abs() < 1e-9
    for mask in masks:
        if (mask & same_gsd).any():
            return float(past.loc[mask & same_gsd, "hours"].median())
    for mask in masks:
        if mask.any():
            return float(past.loc[mask, "hours"].median()) * (SURVEY_GSD_M / cell.gsd_m) ** 2
    planner = past["planner"] == cell.planner
    if planner.any():
        return 2.0 * float(past.loc[planner, "hours"].max())
    return UNKNOWN_CELL_H


def plan_table(cells: Sequence[StudyCell], past: pd.DataFrame, recorded: set[str]) -> pd.DataFrame:
    """Per phase: cells, cells recorded, and estimated cell-hours left."""
    rows = []
    for cell in cells:
        done = cell.spec() in recorded
        rows.append(
            {
                "phase": cell.phase,
                "cells": 1,
                "recorded": int(done),
                "hours_left": 0.0 if done else estimate_hours(cell, past),
            }
        )
    table = pd.DataFrame(rows).groupby("phase", as_index=False).sum()
    return table


def recorded_specs(preset: str, cells: Sequence[StudyCell]) -> set[str]:
    """The cells of ``cells`` whose record under ``results/cells/<preset>`` (a repeat's under its own
    folder) counts: of the current protocol and of its planner's current version."""
    # a test replaces it on its module: imported on use
    from experiments.record import current_record, record_dir

    versions = {planner: planner_version(planner) for planner in {c.planner for c in cells}}
    return {
        c.spec()
        for c in cells
        if current_record(
            record_dir(c.preset(preset), c.scene, c.planner, c.seed, c.budget, c.gsd_m) / "metrics.json",
            versions[c.planner],
        )
        is not None
    }


def recorded_fields(preset: str, cells: Sequence[StudyCell], key: str) -> dict[str, str]:
    """``metrics.json``'s ``key`` of every recorded cell of ``cells``, by spec ("" where it has none)."""

    # a test replaces it on its module: imported on use
    from experiments.record import record_dir

    values = {}
    for c in cells:
        path = record_dir(c.preset(preset), c.scene, c.planner, c.seed, c.budget, c.gsd_m) / "metrics.json"
        if path.is_file():
            values[c.spec()] = str(json.loads(path.read_text()).get(key) or "")
    return values


def proxies_per_group(
    cells: Sequence[StudyCell], fingerprints: dict[str, str]
) -> dict[tuple[str, int], dict[str, int]]:
    """Per scene and seed, how many recorded cells planned on each proxy (``proxy_fingerprint``;
    noise repeats left out: each builds its own on purpose). A proxy rebuilt on another machine
    differs in a few faces, and ours' plan follows them; a group with two proxies mixes that noise
    into its front."""
    groups: dict[tuple[str, int], dict[str, int]] = {}
    for c in cells:
        fingerprint = fingerprints.get(c.spec())
        if c.repeat is not None or fingerprint is None:
            continue
        counts = groups.setdefault((c.scene, c.seed), {})
        counts[fingerprint or "none"] = counts.get(fingerprint or "none", 0) + 1
    return groups


def cell_estimates(cells: Sequence[StudyCell], past: pd.DataFrame) -> dict[tuple, float]:
    """``estimate_hours`` of each cell, keyed as the record queue asks (scene, planner, seed, budget,
    gsd)."""
    return {(c.scene, c.planner, c.seed, c.budget, c.gsd_m): estimate_hours(c, past) for c in cells}


def ensure_bundles(
    cells: Sequence[StudyCell],
    deadline: float | None,
    commit: bool = True,
    revision: str = "HEAD",
    then_hours: float = 0.0,
) -> list[tuple[str, int]]:
    """Build, export and commit the committed proxy (``proxies/default/<scene>/seed<k>``) of every
    scene and seed of ``cells`` that has none at the current protocol, from a worktree of
    ``revision``; none is started that would not finish, with ``then_hours`` of cells after it,
    before ``deadline``. Returns the scenes and seeds still without one."""

    # a test replaces it on its module: imported on use
    from experiments.record import commit_with_retry, revision_worktree

    wanted = list(dict.fromkeys((c.scene, c.seed) for c in cells))

    def missing(scene: str, seed: int) -> bool:
        path = bundle_dir("default", scene, seed, ROOT / "proxies") / MANIFEST
        return not path.is_file() or json.loads(path.read_text()).get("protocol") != PROTOCOL

    todo = [pair for pair in wanted if missing(*pair)]
    if not todo:
        return []
    left = []
    with revision_worktree(revision, prefix="uavplan_proxies_") as tree:
        env = dict(os.environ, UAVPLAN_CACHE=str(ROOT / "cache"), UAVPLAN_PROXIES=str(ROOT / "proxies"))
        env.setdefault("UAVPLAN_MESHES", str((ROOT.parent / "shared" / "data" / "meshes").resolve()))
        env["PYTHONPATH"] = str(tree)
        for scene, seed in todo:
            if deadline is not None and time.time() + (BUNDLE_HOURS + then_hours) * 3600.0 > deadline:
                left.append((scene, seed))
                continue
            print(f"{scene}/{seed}: building its committed proxy", flush=True)
            command = [sys.executable, "-m", "experiments.proxies", "build", f"{scene}/{seed}", "--force"]
            done = subprocess.run(command, cwd=tree, env=env)
            if done.returncode != 0:
                print(f"{scene}/{seed}: the proxy build failed (exit {done.returncode})", flush=True)
                left.append((scene, seed))
                continue
            if commit:
                commit_with_retry(
                    bundle_dir("default", scene, seed, ROOT / "proxies"),
                    f"Proxy bundle: {scene} seed {seed} at protocol {PROTOCOL} (uavplan-study proxies build)",
                )
    return left


def run_cells(
    cells: Sequence[StudyCell],
    preset: str,
    study: Path,
    overrides: Sequence[str],
    limits=None,
    commit: bool = True,
    launcher: str = "local",
    n_jobs: int = 1,
) -> int:
    """Run ``cells`` through the record queue, each group of one record folder in order (a noise
    repeat with a stage cache of its own), each scene and seed on its committed proxy, within
    ``limits`` (``experiments.record.QueueLimits``), on ``launcher`` with ``n_jobs`` cells at once
    (``experiments.launch``). Returns the number of failed cells."""
    # a test replaces it on its module: imported on use
    from experiments.record import QueueLimits, run_queue

    limits = limits or QueueLimits()
    failed = 0
    # One queue run per stretch of cells of one record folder and one scene and seed, the proxy
    # committed just before its first cell (a scene explored hours before its cells would hold
    # the queue's first answers back).
    stretches: list[list[StudyCell]] = []
    for cell in cells:
        last = stretches[-1][-1] if stretches else None
        same = last is not None and (last.preset(preset), last.scene, last.seed) == (
            cell.preset(preset),
            cell.scene,
            cell.seed,
        )
        if same:
            stretches[-1].append(cell)
        else:
            stretches.append([cell])
    for stretch in stretches:
        if limits.deadline is not None and time_left_h(limits.deadline) <= 0:
            break
        first = stretch[0]
        first_hours = limits.margin * (limits.estimates_h or {}).get(
            (first.scene, first.planner, first.seed, first.budget, first.gsd_m), limits.default_estimate_h
        )
        if ensure_bundles(stretch, limits.deadline, commit, then_hours=first_hours):
            # the phases run in order: no later cell goes before these
            where = f"{first.scene}/{first.seed}"
            print(
                f"note: no committed proxy for {where} yet: the queue stops here until the next run",
                flush=True,
            )
            break
        folder = first.preset(preset)
        runs = Path(study)
        extra = list(overrides)
        proxies = None
        if first.repeat is None:
            proxies = group_proxies(
                proxies_per_group(stretch, recorded_fields(preset, stretch, "proxy_fingerprint"))
            )
        else:
            runs = runs.parent / f"{runs.name}_noise" / f"rep{first.repeat}"
            extra += [f"cache_dir={(runs / 'cache').resolve()}"]
        status: dict = {}
        failed += run_queue(
            [c.queue_cell() for c in stretch],
            folder,
            runs,
            extra,
            proxies=proxies,
            limits=limits,
            commit=commit,
            launcher=launcher,
            n_jobs=n_jobs,
            status=status,
            require_bundle=True,
        )
        if status.get("stopped"):  # the deadline, the disk, another proxy: no later cell first
            break
    return failed


def time_left_h(deadline: float) -> float:

    return (deadline - time.time()) / 3600.0


def parse_until(text: str, now=None) -> float:
    """``HH:MM`` (today, or tomorrow where that has passed) or an ISO date-time -> epoch seconds.

    Raises:
        ValueError: neither form."""
    now = now or dt.datetime.now()
    try:
        clock = dt.datetime.strptime(text, "%H:%M").time()
    except ValueError:
        try:
            return dt.datetime.fromisoformat(text).timestamp()
        except ValueError:
            raise ValueError(
                f"--until {text!r}: give HH:MM (e.g. 15:40) or a date-time (2026-12-07T15:40)"
            ) from None
    when = dt.datetime.combine(now.date(), clock)
    if when <= now:
        when += dt.timedelta(days=1)
    return when.timestamp()


def group_proxies(counts: dict[tuple[str, int], dict[str, int]]) -> dict[tuple[str, int], str]:
    """Per scene and seed, the proxy most of its recorded cells planned on (``proxies_per_group``'s
    counts; records without a fingerprint left out)."""
    known = {key: {fp: n for fp, n in c.items() if fp != "none"} for key, c in counts.items()}
    return {key: max(c, key=c.get) for key, c in known.items() if c}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-study study-plan", description=__doc__.splitlines()[0])
    parser.add_argument("--phases", type=int, nargs="+", help="only these phases (default: all)")
    parser.add_argument(
        "--planners", nargs="+", help="only these planners' cells (default: all), for a measurement preset"
    )
    parser.add_argument("--preset", default=STUDY_PRESET, help="record folder under results/cells/")
    parser.add_argument("--study", type=Path, default=Path("study") / STUDY_PRESET, help="run directories")
    parser.add_argument("--list", action="store_true", help="print the cells left, one per line")
    parser.add_argument("--run", action="store_true", help="run the cells left through the record queue")
    parser.add_argument("--until", help="with --run: start no cell that would not finish by HH:MM")
    parser.add_argument(
        "--min-free-gb", type=float, default=20.0, help="with --run: start no cell with less free disk"
    )
    parser.add_argument("--keep-runs", action="store_true", help="keep run directories after recording")
    parser.add_argument(
        "--launcher", default="local", choices=LAUNCHERS, help="where cells run (experiments/launch.py)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="cells at once (joblib, ray, slurm)")
    parser.add_argument(
        "--set", action="append", default=[], help="a run.py override for every cell (off the protocol)"
    )
    args = parser.parse_args(argv)
    cells = study_cells()
    if args.phases:
        unknown = sorted(set(args.phases) - {c.phase for c in cells})
        if unknown:
            print(f"error: --phases: no phase {unknown} (phases 1-7)", file=sys.stderr)
            return 2
        cells = [c for c in cells if c.phase in args.phases]
    if args.planners:
        unknown = sorted(set(args.planners) - set(PLANNERS))
        if unknown:
            known = ", ".join(PLANNERS)
            print(f"error: --planners: no planner {unknown} (planners: {known})", file=sys.stderr)
            return 2
        cells = [c for c in cells if c.planner in args.planners]
    for cell in cells:
        level_rank(cell.budget)
    try:
        deadline = parse_until(args.until) if args.until else None
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    recorded = recorded_specs(args.preset, cells)
    left = [c for c in cells if c.spec() not in recorded]
    if args.list:
        print("\n".join(c.spec() for c in left))
        return 0
    past = past_cell_hours(PAST_RECORDS)
    table = plan_table(cells, past, recorded)
    print(f"protocol {PROTOCOL}, records in results/cells/{args.preset}/")
    print(table.to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    total = float(table["hours_left"].sum())
    print(f"{len(left)} of {len(cells)} cells left, about {total:.0f} cell-hours on 2 cores")
    proxies = proxies_per_group(cells, recorded_fields(args.preset, cells, "proxy_fingerprint"))
    for (scene, seed), counts in sorted(proxies.items()):
        if len(counts) > 1:
            listed = ", ".join(
                f"{fp[:8]}: {n} cells" for fp, n in sorted(counts.items(), key=lambda kv: -kv[1])
            )
            print(f"note: {scene} / seed {seed} planned on {len(counts)} proxies ({listed})")
    if not args.run:
        return 0
    # a test replaces it on its module: imported on use
    from experiments.record import QueueLimits

    limits = QueueLimits(
        deadline=deadline,
        estimates_h=cell_estimates(left, past),
        default_estimate_h=UNKNOWN_CELL_H,
        min_free_gb=args.min_free_gb,
        prune=not args.keep_runs,
    )
    failed = run_cells(
        left, args.preset, args.study, args.set, limits, launcher=args.launcher, n_jobs=args.jobs
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
