"""The study: its cells in the order they run, and what they cost.

    uavplan-study study-plan                                  # the queue by phase, with cell-hours
    uavplan-study study-plan --phases 1 2 --run --revision REV [--set KEY=VALUE]

``--run`` hands the cells to the record queue (``experiments.record``): one at a time from a worktree
of ``REV`` (every cell of the study from one revision), each record committed to
``results/cells/<--preset>/`` as it finishes, a cell recorded already skipped. So the study is
resumed on any machine by the same command.

The phases, each a complete answer before the next starts:

1. the fronts at seed 0 on the tomb and the church: each planner's own budget knob at the survey's
   GSD (3 cm);
2. the GSD axis at seed 0 on the tomb and the church: every planner at its default knob at 2 and
   4.5 cm (3 cm is phase 1's default cell);
3. seeds 1 and 2 of phases 1 and 2;
4. the cathedral's own-knob fronts (low, default, high), seed 0;
5. the shared meshes (school, power plant): every planner at its default, seed 0;
6. Yan at the seed paper's scale (3000+ images), tomb, seed 0;
7. the noise floor: ours' and Smith's default church cells three times each from nothing (each
   repeat its own stage cache, so its own exploration and proxy; ``reconstruct.deterministic=false``),
   recorded under ``results/cells/<--preset>_noise/rep<k>/`` for ``uavplan-study noise-floor
   --summarise``, whose floor the tables' and fronts' tie rule reads.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from experiments.runs import RunDirectoryError, load_runs, runs_frame
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
STUDY_PRESET = "settled"  # its records: results/cells/settled/; its run directories: study/settled/
SURVEY_GSD_M = 0.03  # conf/config.yaml survey.target_gsd_m: the own-knob axis flies at it
GSD_AXIS_M = (0.045, 0.02)  # the GSD axis besides the survey's, coarsest first
FRONT_SCENES = ("tomb", "church")
MESH_SCENES = ("school", "powerplant")
SEEDS = (0, 1, 2)
# Overrides a scene needs in every cell (conf/scene/powerplant.yaml says why).
SCENE_OVERRIDES = {"powerplant": ("exploration=lawnmower_orbit",)}
# Every cell but the noise floor's reconstructs in the deterministic mode (results/reproducibility.md;
# about 8 % more wall time): a session that starts on a new machine rebuilds each scene's exploration,
# and in the default mode that gives another proxy (two sessions' tomb proxies differed, and so did
# the plans on them by up to 5 points of completeness), so a front run over several sessions would
# mix proxies. The queue stops where a rebuilt proxy still differs (experiments.record.run_queue).
STUDY_MODE = ("reconstruct.deterministic=true",)
# The noise floor's cells (the issue asks for ours and one baseline on the church) and repeats.
NOISE_CELLS = (("church", "ours"), ("church", "smith"))
NOISE_REPEATS = 3
# Where the cell-hours of a cell not run before are guessed from: the records of earlier studies.
PAST_RECORDS = ROOT / "results" / "cells"
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

    def add(phase, scene, planner, seed, budget=DEFAULT_LEVEL, gsd_m=SURVEY_GSD_M):
        cells.append(StudyCell(phase, scene, planner, seed, budget, gsd_m, SCENE_OVERRIDES.get(scene, ())))

    def fronts(phase, seed):
        for scene in FRONT_SCENES:
            for planner in QUEUE_ORDER:
                for level in OWN_LEVELS[planner]:
                    add(phase, scene, planner, seed, level)

    def gsd_axis(phase, seed):
        for scene in FRONT_SCENES:
            for planner in QUEUE_ORDER:
                for gsd in GSD_AXIS_M:
                    add(phase, scene, planner, seed, DEFAULT_LEVEL, gsd)

    fronts(1, 0)
    gsd_axis(2, 0)
    for seed in SEEDS[1:]:
        fronts(3, seed)
        gsd_axis(3, seed)
    for planner in PLANNERS:
        for level in ("low", DEFAULT_LEVEL, "high"):
            add(4, "cathedral", planner, 0, level)
    for scene in MESH_SCENES:
        for planner in PLANNERS:
            add(5, scene, planner, 0)
    add(6, "tomb", "yan", 0, "highest")
    for repeat in range(NOISE_REPEATS):
        for scene, planner in NOISE_CELLS:
            cells.append(StudyCell(7, scene, planner, 0, repeat=repeat))
    return cells


def past_cell_hours(root: Path) -> pd.DataFrame:
    """Median wall hours of earlier cells per (scene, planner, budget), from the records of each
    study under ``root`` (each study's cells its own samples)."""
    runs = []
    for path in sorted(p for p in Path(root).iterdir() if p.is_dir()):
        try:
            runs += load_runs([path])
        except RunDirectoryError:
            continue
    if not runs:
        return pd.DataFrame(columns=["scene", "planner", "budget", "hours"])
    frame = runs_frame(runs)
    frame = frame[(frame["status"] == "ok") & frame.get("cell_wall_time_s", pd.Series(dtype=float)).notna()]
    frame = frame.assign(hours=frame["cell_wall_time_s"].astype(float) / 3600.0)
    return frame.groupby(["scene", "planner", "budget"], as_index=False)["hours"].median()


def estimate_hours(cell: StudyCell, past: pd.DataFrame) -> float:
    """A cell's wall hours guessed from the earlier cell most like it: the same scene, planner and
    budget; else the same scene and planner at the default budget; else the planner anywhere."""
    for mask in (
        (past["scene"] == cell.scene) & (past["planner"] == cell.planner) & (past["budget"] == cell.budget),
        (past["scene"] == cell.scene) & (past["planner"] == cell.planner) & (past["budget"] == DEFAULT_LEVEL),
        (past["planner"] == cell.planner) & (past["budget"] == cell.budget),
    ):
        if mask.any():
            return float(past.loc[mask, "hours"].median())
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
    """The cells of ``cells`` that have a record under ``results/cells/<preset>`` (a repeat's under its
    own folder)."""
    from experiments.record import record_dir

    return {
        c.spec()
        for c in cells
        if (
            record_dir(c.preset(preset), c.scene, c.planner, c.seed, c.budget, c.gsd_m) / "metrics.json"
        ).is_file()
    }


def recorded_fields(preset: str, cells: Sequence[StudyCell], key: str) -> dict[str, str]:
    """``metrics.json``'s ``key`` of every recorded cell of ``cells``, by spec ("" where it has none)."""
    import json

    from experiments.record import record_dir

    values = {}
    for c in cells:
        path = record_dir(c.preset(preset), c.scene, c.planner, c.seed, c.budget, c.gsd_m) / "metrics.json"
        if path.is_file():
            values[c.spec()] = str(json.loads(path.read_text()).get(key) or "")
    return values


def recorded_commits(preset: str, cells: Sequence[StudyCell]) -> dict[str, str]:
    """The code commit (``metrics.json``'s ``code_commit``) of every recorded cell of ``cells``, by spec."""
    return recorded_fields(preset, cells, "code_commit")


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


def foreign_records(commits: dict[str, str], revision_sha: str) -> list[str]:
    """The specs recorded at another commit than ``revision_sha`` (full or abbreviated)."""
    return sorted(
        spec
        for spec, sha in commits.items()
        if not (sha and (sha.startswith(revision_sha) or revision_sha.startswith(sha)))
    )


def run_cells(
    cells: Sequence[StudyCell], preset: str, study: Path, overrides: Sequence[str], revision: str
) -> int:
    """Run ``cells`` through the record queue, each group of one record folder in order: the study's
    cells in the deterministic mode (``STUDY_MODE``), each scene and seed on the proxy its recorded
    cells planned on; a noise repeat in the default mode with a stage cache of its own. Returns the
    number of failed cells."""
    from experiments.record import run_queue

    failed = 0
    groups: dict[str, list[StudyCell]] = {}
    for cell in cells:
        groups.setdefault(cell.preset(preset), []).append(cell)
    for folder, group in groups.items():
        repeat = group[0].repeat
        extra = list(overrides)
        runs = Path(study)
        proxies = None
        if repeat is None:
            extra += STUDY_MODE
            proxies = group_proxies(
                proxies_per_group(group, recorded_fields(preset, group, "proxy_fingerprint"))
            )
        else:
            runs = runs.parent / f"{runs.name}_noise" / f"rep{repeat}"
            extra += ["reconstruct.deterministic=false", f"cache_dir={(runs / 'cache').resolve()}"]
        failed += run_queue(
            [c.queue_cell() for c in group], folder, runs, extra, revision=revision, proxies=proxies
        )
    return failed


def group_proxies(counts: dict[tuple[str, int], dict[str, int]]) -> dict[tuple[str, int], str]:
    """Per scene and seed, the proxy most of its recorded cells planned on (``proxies_per_group``'s
    counts; records without a fingerprint left out)."""
    known = {key: {fp: n for fp, n in c.items() if fp != "none"} for key, c in counts.items()}
    return {key: max(c, key=c.get) for key, c in known.items() if c}


def default_mode_records(preset: str, cells: Sequence[StudyCell]) -> list[str]:
    """The specs of ``cells`` (noise repeats left out) recorded in the default, non-deterministic mode:
    their proxies cannot be rebuilt, so they do not belong in a front with the study's cells."""
    modes = recorded_fields(preset, [c for c in cells if c.repeat is None], "deterministic")
    return sorted(spec for spec, mode in modes.items() if mode != "True")


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
    parser.add_argument("--revision", default="HEAD", help="the commit every cell runs (with --run)")
    parser.add_argument("--set", action="append", default=[], help="a run.py override for every cell")
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
    recorded = recorded_specs(args.preset, cells)
    left = [c for c in cells if c.spec() not in recorded]
    if args.list:
        print("\n".join(c.spec() for c in left))
        return 0
    past = past_cell_hours(PAST_RECORDS)
    table = plan_table(cells, past, recorded)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    total = float(table["hours_left"].sum())
    print(f"{len(left)} of {len(cells)} cells left, about {total:.0f} cell-hours on 2 cores")
    proxies = proxies_per_group(cells, recorded_fields(args.preset, cells, "proxy_fingerprint"))
    for (scene, seed), counts in sorted(proxies.items()):
        if len(counts) > 1:
            listed = ", ".join(
                f"{fp[:8]}: {n} cells" for fp, n in sorted(counts.items(), key=lambda kv: -kv[1])
            )
            print(
                f"note: {scene} / seed {seed} planned on {len(counts)} proxies ({listed}), "
                "each rebuilt in another session"
            )
    if not args.run:
        return 0
    # Every cell of the study comes from one revision: a record of another would sit in its tables.
    import subprocess

    found = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", f"{args.revision}^{{commit}}"],
        capture_output=True,
        text=True,
    )
    if found.returncode != 0:
        print(f"error: --revision {args.revision!r} names no commit", file=sys.stderr)
        return 2
    foreign = foreign_records(recorded_commits(args.preset, cells), found.stdout.strip())
    if foreign:
        print(
            f"error: {len(foreign)} cell(s) of results/cells/{args.preset} were recorded at another revision "
            f"than {args.revision} (first: {foreign[0]}); move them aside or run at their revision",
            file=sys.stderr,
        )
        return 2
    default_mode = default_mode_records(args.preset, cells)
    if default_mode:
        print(
            f"error: {len(default_mode)} cell(s) of results/cells/{args.preset} were recorded in the default "
            f"(non-deterministic) mode (first: {default_mode[0]}); move them aside: the study runs "
            f"{' '.join(STUDY_MODE)}",
            file=sys.stderr,
        )
        return 2
    failed = run_cells(left, args.preset, args.study, args.set, args.revision)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
