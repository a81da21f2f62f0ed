"""Cell records in the repository, and a queue that runs cells one at a time and commits each record.

A run directory (images, models, clouds: gigabytes) stays on the machine that ran it; its record,
``metrics.json``, ``plan/plan.json`` and ``.hydra/overrides.yaml`` (kilobytes), is what the tables
and figures are rebuilt from (``experiments.tables`` and ``experiments.figures`` read record folders
like run directories). It lives in ``results/cells/<preset>/<scene>/<planner>/gsd<g>/<budget>/seed<k>/``
(g: ``survey.target_gsd_m`` in m/px; budget: ``planner.budget``); a record from before the GSD was
recorded, in ``.../<planner>/<budget>/seed<k>/``.

    uavplan-study record study/default_v4/tomb/yan/seed0 --preset default [--commit]
    uavplan-study record --queue tomb/yan/0 church/ours/1 tomb/ours/0/high tomb/smith/0/default/0.02 \\
        --preset default --study study/default_v4 [--set reconstruct.keep_dense_workspace=false] [--force]

``--queue`` runs each ``scene/planner/seed[/budget[/gsd]]`` cell (gsd in m/px; the config's
``survey.target_gsd_m`` when absent) with ``run.py`` from a detached git worktree
of HEAD, or of ``--revision REV`` (a study's cells all from one code revision while main moves on; the
committed code: editing the checkout while a cell runs cannot change it; the stage cache
stays shared), into ``--study/<scene>/<planner>/<budget>/seed<k>``, then records and commits that cell
(``git commit -- <its record>``: nothing else staged is swept in) before it starts the next. A cell
already recorded is skipped unless ``--force``. A failed cell's ``metrics.json`` is recorded too.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from hydra import compose, initialize_config_dir

from experiments.launch import Job, launch
from experiments.runs import RunDirectoryError, read_metrics
from pipeline.protocol import PROTOCOL, planner_version
from planner.budget import DEFAULT_LEVEL, level_rank
from scene.io import write_json_atomic, write_text_atomic

ROOT = Path(__file__).resolve().parents[1]

RECORDS = ROOT / "results" / "cells"
# The Hydra overrides travel with the record: a `--set` (a memory budget, a switch) changes how a cell
# ran, and the run directory that holds them does not survive a move to a new machine. So do the
# views flown (a few kB): two cells' plans can be compared, or a plan flown again, from the record.
RECORD_FILES = {
    "metrics.json": "metrics.json",
    "plan.json": "plan/plan.json",
    "viewpoints.csv": "plan/viewpoints.csv",
    "overrides.yaml": ".hydra/overrides.yaml",
}


def cell_path(
    scene: str, planner: str, seed: int, budget: str = DEFAULT_LEVEL, gsd_m: float | None = None
) -> Path:
    """``<scene>/<planner>/gsd<g>/<budget>/seed<k>``: a cell's folder under a study or record root
    (the layout of Hydra's sweep subdirectories, conf/config.yaml); ``<scene>/<planner>/<budget>/seed<k>``
    for a cell whose GSD is not known (a record from before the GSD was recorded)."""
    level_rank(budget)
    gsd = () if gsd_m is None else (f"gsd{float(gsd_m):g}",)
    return Path(scene, planner, *gsd, budget, f"seed{int(seed)}")


def record_dir(
    preset: str,
    scene: str,
    planner: str,
    seed: int,
    budget: str = DEFAULT_LEVEL,
    gsd_m: float | None = None,
    root: Path = RECORDS,
) -> Path:
    """Where the record of one cell lives."""
    return Path(root) / preset / cell_path(scene, planner, seed, budget, gsd_m)


def record_cell(run_dir: str | Path, preset: str, root: Path = RECORDS) -> tuple[Path, dict]:
    """Copy a finished cell's ``metrics.json`` (and ``plan/plan.json``, ``plan/viewpoints.csv`` and
    its Hydra overrides where it has them) into its record folder, each file atomically. Returns the
    folder and the metrics.

    Raises:
        RunDirectoryError: no ``metrics.json``, or one without scene, planner and seed.
    """
    run_dir = Path(run_dir)
    metrics = read_metrics(run_dir)
    missing = [k for k in ("scene", "planner", "seed") if k not in metrics]
    if missing:
        raise RunDirectoryError(f"{run_dir}/metrics.json: no {missing} (not a cell's record)")
    budget = str(metrics.get("budget") or DEFAULT_LEVEL)
    gsd_m = metrics.get("target_gsd_m")
    dest = record_dir(
        preset, str(metrics["scene"]), str(metrics["planner"]), int(metrics["seed"]), budget, gsd_m, root
    )
    for name, source in RECORD_FILES.items():
        path = run_dir / source
        if path.is_file():
            write_text_atomic(dest / name, path.read_text())
    return dest, metrics


def summary_line(metrics: dict) -> str:
    """One line naming the cell and its headline figures (a commit message, a log line)."""
    budget = metrics.get("budget") or DEFAULT_LEVEL
    cell = f"{metrics.get('scene')} / {metrics.get('planner')} / seed {metrics.get('seed')}" + (
        "" if budget == DEFAULT_LEVEL else f" / {budget} budget"
    )
    if metrics.get("status", "ok") != "ok":
        stage, error = metrics.get("failed_stage", "?"), metrics.get("error", "")
        return f"Cell record: {cell} failed in stage {stage}: {error}"[:300]

    def number(key: str, scale: float = 1.0, fmt: str = ".1f") -> str:
        value = metrics.get(key)
        return "n/a" if value is None else format(float(value) * scale, fmt)

    cpu = metrics.get("cell_cpu_time_s")
    return (
        f"Cell record: {cell}: {metrics.get('n_images')} images, {metrics.get('n_registered')} registered, "
        f"acc90 {number('acc90_m', 100.0)} cm, completeness {number('comp_050')} % at 5 cm, "
        f"cell {number('cell_wall_time_s', 1 / 60.0)} min"
        + ("" if cpu is None else f" ({float(cpu) / 60.0:.1f} min CPU)")
    )


def commit_record(dest: Path, message: str, repo: Path = ROOT) -> None:
    """Commit only the record folder ``dest`` (other staged or modified files stay as they are);
    nothing when it is as committed already (a cell that ran again to the same bytes)."""
    rel = os.path.relpath(dest, repo)
    subprocess.run(["git", "-C", str(repo), "add", "--", rel], check=True)
    staged = subprocess.run(["git", "-C", str(repo), "diff", "--cached", "--quiet", "--", rel])
    if staged.returncode == 0:
        return
    subprocess.run(["git", "-C", str(repo), "commit", "-q", "-m", message, "--", rel], check=True)


Cell = tuple[str, str, int, str, "float | None"]


def parse_cell(text: str) -> Cell:
    """``scene/planner/seed[/budget[/gsd]]`` -> (scene, planner, seed, budget, gsd_m); budget
    ``default`` and gsd ``None`` (the config's) if absent.

    Raises:
        ValueError: not of that form, an unknown budget level, or a GSD that is not a positive number.
    """
    parts = text.split("/")
    if len(parts) not in (3, 4, 5) or not parts[2].isdigit():
        raise ValueError(
            "a cell is scene/planner/seed[/budget[/gsd_m]] (e.g. tomb/yan/0, tomb/ours/0/high, "
            f"tomb/smith/0/default/0.02), got {text!r}"
        )
    budget = parts[3] if len(parts) >= 4 else DEFAULT_LEVEL
    level_rank(budget)
    gsd_m = None
    if len(parts) == 5:
        try:
            gsd_m = float(parts[4])
        except ValueError:
            gsd_m = math.nan
        if not (math.isfinite(gsd_m) and gsd_m > 0):
            raise ValueError(f"cell {text!r}: the GSD must be a positive number of m/px, got {parts[4]!r}")
    return parts[0], parts[1], int(parts[2]), budget, gsd_m


def configured_gsd_m(overrides: Sequence[str] = ()) -> float:
    """``survey.target_gsd_m`` of ``run.py`` with ``overrides`` (a preset may set it)."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return float(compose("config", overrides=list(overrides)).survey.target_gsd_m)


@contextmanager
def revision_worktree(
    revision: str, prefix: str = "uavplan_tree_", parent: Path | None = None
) -> Iterator[Path]:
    """A detached worktree of ``revision`` in a temporary folder (under ``parent``: a shared file
    system for a cluster's workers; default the system's temporary folder), removed after the block.

    Raises:
        ValueError: git cannot check ``revision`` out (it names no commit)."""
    if parent is not None:
        Path(parent).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=prefix, dir=parent) as tmp:
        tree = Path(tmp) / "tree"
        added = subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(tree), revision],
            capture_output=True,
            text=True,
        )
        if added.returncode != 0:
            raise ValueError(f"--revision {revision!r}: {added.stderr.strip()}")
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


def current_record(path: Path, version: int | None, attempts: int = 1) -> dict | None:
    """The record ``path`` (a ``metrics.json``) where it counts at the current protocol and planner
    ``version``; None where it is missing, of another protocol or an older plan, or a failure of
    fewer than ``attempts`` tries (``queue_attempt``: the queue was stopped before its retry)."""
    if not path.is_file():
        return None
    metrics = json.loads(path.read_text())
    if metrics.get("protocol") != PROTOCOL or metrics.get("planner_version") != version:
        return None
    if metrics.get("status", "ok") != "ok" and int(metrics.get("queue_attempt", 1)) < attempts:
        return None
    return metrics


def commit_with_retry(dest: Path, message: str, attempts: int = 5) -> None:
    """``commit_record``, tried again while another git command holds the index (the queue commits
    beside a developer's own commits)."""
    for attempt in range(attempts):
        try:
            commit_record(dest, message)
            return
        except subprocess.CalledProcessError:
            if attempt == attempts - 1:
                raise
            time.sleep(3.0)


def free_gb(path: Path) -> float:
    """Free disk space (GB) where ``path`` (or its nearest existing parent) lies."""
    path = Path(path).resolve()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free / 1e9


@dataclass(frozen=True)
class QueueLimits:
    """When the queue stops starting cells, and what it keeps.

    Attributes:
        deadline: epoch seconds (the session's end): no cell starts whose estimate does not fit
            before it; None: no deadline.
        estimates_h: wall hours per cell (``(scene, planner, seed, budget, gsd)``), from earlier
            records (``experiments.study_plan.estimate_hours``); a cell without one counts
            ``default_estimate_h``.
        min_free_gb: no cell starts with less free disk than this where its run directory lies.
        prune: delete a cell's run directory once its record is kept (images, models, clouds).
        attempts: tries per cell (a failed one is recorded, then run again once).
        margin: a cell starts only if ``margin`` x its estimate fits before the deadline (estimates
            from another machine, or from cells that ran beside other work, run short).
    """

    deadline: float | None = None
    estimates_h: dict | None = None
    default_estimate_h: float = 0.75
    min_free_gb: float = 20.0
    prune: bool = True
    attempts: int = 2
    margin: float = 1.5


def _queue_head(revision: str) -> str:
    """The short commit ``revision`` names.

    Raises:
        ValueError: ``revision`` names no commit."""
    found = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", "--short", f"{revision}^{{commit}}"],
        capture_output=True,
        text=True,
    )
    if found.returncode != 0:
        raise ValueError(f"--revision {revision!r} names no commit of {ROOT}")
    return found.stdout.strip()


def _check_queue_records(
    revision: str, head: str, commit: bool, cells: list[tuple], preset: str, records_root: Path
):
    """Refuse records git would ignore (when committing); note uncommitted changes the cells will
    not run.

    Raises:
        ValueError: a record would be ignored by git."""
    if commit:
        records = [
            os.path.relpath(record_dir(preset, *cell[:5], root=records_root) / name, ROOT)
            for cell in cells
            for name in ("metrics.json", "plan.json")
        ]
        ignored = subprocess.run(
            ["git", "-C", str(ROOT), "check-ignore", "--stdin"],
            input="\n".join(records),
            capture_output=True,
            text=True,
        ).stdout.split()
        if ignored:
            raise ValueError(
                f"{ignored[0]} is ignored by git (.gitignore): "
                "the queue's records could not be committed; nothing run"
            )
    dirty = (
        revision == "HEAD"
        and subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    if dirty:
        print(
            f"note: the cells run the committed code at {head}; uncommitted changes are not in them",
            flush=True,
        )


@dataclass
class _QueueRun:
    """One ``run_queue`` in progress: what it runs, from where, and where it stands."""

    preset: str
    study: Path
    overrides: Sequence[str]
    commit: bool
    head: str
    proxies: dict[tuple[str, int], str]
    limits: QueueLimits
    records_root: Path
    require_bundle: bool
    tree: Path
    env: dict[str, str]
    queue: collections.deque
    stopped: bool = False
    failed: int = 0

    @staticmethod
    def name_of(cell: tuple) -> str:
        scene, planner, seed, budget, gsd_m, _ = cell
        return f"{scene}/{planner}/{seed}/{budget}/{gsd_m:g}"

    def run_dir_of(self, cell: tuple) -> Path:
        return (Path(self.study) / cell_path(*cell[:5])).resolve()

    def out_of_time_or_disk(self, cell: tuple) -> bool:
        """Stop the queue (say why) when ``cell`` would end past the deadline or the disk is low."""
        limits, name, run_dir = self.limits, self.name_of(cell), self.run_dir_of(cell)
        estimate_h = (limits.estimates_h or {}).get(cell[:5], limits.default_estimate_h)
        if limits.deadline is not None and time.time() + limits.margin * estimate_h * 3600 > limits.deadline:
            left_min = max(limits.deadline - time.time(), 0.0) / 60.0
            print(
                f"{name}: estimated {estimate_h * 60:.0f} min, {left_min:.0f} min left before the "
                "deadline: queue stopped (the same command resumes it)",
                flush=True,
            )
            self.stopped = True
            return True
        if limits.min_free_gb and free_gb(run_dir) < limits.min_free_gb:
            print(
                f"{name}: {free_gb(run_dir):.1f} GB free under {run_dir.parent}, below the queue's "
                f"{limits.min_free_gb:g} GB: queue stopped (free disk, or lower --min-free-gb)",
                flush=True,
            )
            self.stopped, self.failed = True, self.failed + 1
            return True
        return False

    def jobs(self) -> Iterator[Job]:
        """The next cell to start, pulled by the launcher when a worker is free; none past
        the deadline or below the disk floor."""
        while self.queue and not self.stopped:
            cell, attempt = self.queue.popleft()
            name, run_dir = self.name_of(cell), self.run_dir_of(cell)
            if self.out_of_time_or_disk(cell):
                return
            scene, planner, seed, budget, gsd_m, cell_overrides = cell
            command = [
                sys.executable,
                "run.py",
                f"scene={scene}",
                f"planner={planner}",
                f"seed={seed}",
                f"budget={budget}",
                f"survey.target_gsd_m={gsd_m!r}",
                f"hydra.run.dir={run_dir}",
                *cell_overrides,
                *self.overrides,
            ]
            shutil.rmtree(run_dir, ignore_errors=True)
            print(f"{name}: running at {self.head} into {run_dir} (attempt {attempt})", flush=True)
            yield Job((cell, attempt), command, self.tree, self.env)

    def take(self, job: Job, code) -> None:
        """Record (and commit) a finished cell; queue it again, or stop the queue, as it says."""
        cell, attempt = job.key
        name, run_dir = self.name_of(cell), self.run_dir_of(cell)
        scene, seed = cell[0], int(cell[2])
        limits = self.limits
        retry = attempt < max(limits.attempts, 1)
        if not (run_dir / "metrics.json").is_file():
            print(f"{name}: exit {code} and no metrics.json: nothing recorded", flush=True)
            if retry:
                self.queue.appendleft((cell, attempt + 1))
            else:
                self.failed += 1
                if limits.prune:
                    shutil.rmtree(run_dir, ignore_errors=True)
            return
        metrics = read_metrics(run_dir)
        metrics["queue_attempt"] = attempt  # a failure retried in a later run if it was the first
        write_json_atomic(run_dir / "metrics.json", metrics)
        other = other_proxy(self.proxies, metrics)
        folder = self.preset if other is None else proxy_preset(self.preset, other)
        dest, metrics = record_cell(run_dir, folder, self.records_root)
        ok = metrics.get("status", "ok") == "ok"
        line = summary_line(metrics) + f" (code {self.head}, protocol {metrics.get('protocol')})"
        print(line, flush=True)
        if self.commit:
            commit_with_retry(dest, line)
        if other is not None:
            expected = self.proxies[(scene, seed)]
            print(
                f"error: {scene} / seed {seed}: this cell planned on proxy {other[:8]}, the group's "
                f"recorded cells on {expected[:8]}; recorded under {os.path.relpath(dest, ROOT)}, "
                "queue stopped "
                "(run the group again on one proxy, or restore the proxy it planned on)",
                flush=True,
            )
            self.stopped, self.failed = True, self.failed + 1
            return
        if (
            self.require_bundle
            and metrics.get("proxy_source") == "reconstruction"
            and not metrics.get("proxy_bundle")
        ):
            print(
                f"error: {name} planned on a proxy explored here, not on the committed one: the "
                "exploration's settings no longer match its key; queue stopped (restore the "
                "setting, or rebuild the proxy: uavplan-study proxies build "
                f"{scene}/{seed} --force --commit)",
                flush=True,
            )
            self.stopped, self.failed = True, self.failed + 1
            return
        if ok and metrics.get("proxy_fingerprint"):
            self.proxies.setdefault((scene, seed), str(metrics["proxy_fingerprint"]))
        if not ok and retry:
            self.queue.appendleft((cell, attempt + 1))
            return
        self.failed += not ok
        if limits.prune:
            shutil.rmtree(run_dir, ignore_errors=True)


def run_queue(
    cells: Sequence[Cell | tuple],
    preset: str,
    study: Path,
    overrides: Sequence[str] = (),
    force: bool = False,
    commit: bool = True,
    revision: str = "HEAD",
    proxies: dict[tuple[str, int], str] | None = None,
    limits: QueueLimits = QueueLimits(deadline=None, prune=False, min_free_gb=0.0, attempts=1),
    env_extra: dict[str, str] | None = None,
    records_root: Path = RECORDS,
    launcher: str = "local",
    n_jobs: int = 1,
    status: dict | None = None,
    require_bundle: bool = False,
) -> int:
    """Run the cells one after the other from a worktree of ``revision``; record (and commit) each one.

    A cell is ``(scene, planner, seed, budget[, gsd_m[, overrides]])``: gsd_m None is the configured
    GSD; ``overrides`` are that cell's own ``run.py`` overrides (before the queue's ``overrides``).
    A cell counts as done when its record is of the current protocol and its planner's current
    version (``current_record``), failed or not; ``force`` runs it again.
    ``proxies``: the proxy (``proxy_fingerprint``) each scene and seed's recorded cells planned on. A
    cell that planned on another one is recorded under ``<preset>_proxy_<fingerprint>`` instead, and
    the queue stops: its front would mix two proxies. A group's first cell sets its proxy.
    ``limits``: the deadline, the disk floor, pruning and retries (``QueueLimits``).
    ``launcher``, ``n_jobs``: where the cells run and how many at once (``experiments.launch``);
    the workers run the cells, this driver alone records and commits them.
    ``status``: where the queue says it stopped early (``status["stopped"] = True``: the deadline,
    the disk floor, another proxy), so a caller does not go on to later cells.
    ``require_bundle``: a cell that planned on no committed proxy (``proxy_bundle`` missing: the
    exploration's settings no longer match the committed one's key) stops the queue.

    Returns the number of cells that failed (a cell on another proxy counts).

    Raises:
        ValueError: ``revision`` names no commit of the repository."""
    head = _queue_head(revision)
    default_gsd = None
    if any(len(cell) < 5 or cell[4] is None for cell in cells):
        default_gsd = configured_gsd_m([o for o in overrides if not o.startswith("hydra")])

    def complete(cell: tuple) -> tuple:
        """(scene, planner, seed, budget, gsd_m, overrides of this cell alone)."""
        gsd_m = cell[4] if len(cell) > 4 and cell[4] is not None else default_gsd
        return (*cell[:4], gsd_m, tuple(cell[5]) if len(cell) > 5 else ())

    cells = [complete(cell) for cell in cells]
    _check_queue_records(revision, head, commit, cells, preset, records_root)
    # A cluster's workers reach the worktree only on a shared file system: the study folder's.
    shared = Path(study).resolve().parent if launcher in ("ray", "slurm") else None
    with revision_worktree(head, prefix="uavplan_queue_", parent=shared) as tree:
        # the versions of the code the cells run, not of the checkout's edits
        versions = {
            planner: planner_version(planner, tree / "conf") for planner in {cell[1] for cell in cells}
        }
        env = dict(
            os.environ,
            UAVPLAN_CACHE=str(ROOT / "cache"),
            UAVPLAN_PROXIES=str(ROOT / "proxies"),
            PYTHONPATH=str(tree),
            **(env_extra or {}),
        )
        # the shared meshes' folder (conf/scene/school.yaml) as seen from the checkout, not the worktree
        env.setdefault("UAVPLAN_MESHES", str((ROOT.parent / "shared" / "data" / "meshes").resolve()))
        todo = []
        for scene, planner, seed, budget, gsd_m, cell_overrides in cells:
            recorded = record_dir(preset, scene, planner, seed, budget, gsd_m, records_root) / "metrics.json"
            if not force and current_record(recorded, versions[planner], limits.attempts) is not None:
                print(
                    f"{scene}/{planner}/{seed}/{budget}/{gsd_m:g}: recorded already (--force runs it again)"
                )
                continue
            todo.append((scene, planner, seed, budget, gsd_m, cell_overrides))
        run = _QueueRun(
            preset, study, overrides, commit, head, dict(proxies or {}), limits, records_root,
            require_bundle, tree, env, collections.deque((cell, 1) for cell in todo),
        )  # fmt: skip
        while run.queue and not run.stopped:
            for job, code in launch(run.jobs(), launcher, n_jobs):
                run.take(job, code)
    if status is not None:
        status["stopped"] = run.stopped
    return run.failed


def other_proxy(proxies: dict[tuple[str, int], str], metrics: dict) -> str | None:
    """The proxy a cell planned on (``metrics.json``) where it is not its scene and seed's in
    ``proxies``; None where it is, or where either is unknown."""
    got = metrics.get("proxy_fingerprint")
    expected = proxies.get((str(metrics.get("scene")), int(metrics.get("seed", -1))))
    return str(got) if got and expected and got != expected else None


def proxy_preset(preset: str, fingerprint: str) -> str:
    """The record folder of a cell that planned on another proxy than its group's."""
    return f"{preset}_proxy_{fingerprint[:8]}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="*", type=Path, help="finished run directories to record")
    parser.add_argument("--preset", default="default", help="record folder under results/cells/")
    parser.add_argument("--commit", action="store_true", help="commit each record (always with --queue)")
    parser.add_argument(
        "--queue", nargs="+", metavar="SCENE/PLANNER/SEED[/BUDGET[/GSD_M]]", help="cells to run, in order"
    )
    parser.add_argument(
        "--study", type=Path, default=Path("study") / "default", help="run directories of --queue"
    )
    parser.add_argument("--set", action="append", default=[], help="a run.py override for every queued cell")
    parser.add_argument("--force", action="store_true", help="run queued cells that are recorded already")
    parser.add_argument(
        "--revision", default="HEAD", help="the commit the queued cells run (default HEAD): one per study"
    )
    args = parser.parse_args(argv)
    try:
        if args.queue:
            cells = [parse_cell(c) for c in args.queue]
            failed = run_queue(cells, args.preset, args.study, args.set, args.force, revision=args.revision)
            return 1 if failed else 0
        if not args.run_dirs:
            parser.error("give run directories to record, or --queue")
        for run_dir in args.run_dirs:
            dest, metrics = record_cell(run_dir, args.preset)
            line = summary_line(metrics)
            print(f"{line}\n  -> {dest}")
            if args.commit:
                commit_record(dest, line)
    except (RunDirectoryError, ValueError, json.JSONDecodeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
