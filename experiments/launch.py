"""Where the study queue's cells run: one at a time here, several at once here, or on a cluster.

The queue's driver (``experiments.record.run_queue``) hands each cell's ``run.py`` command to a
launcher and gets the cells back as they finish; the workers only run the command (which writes
the cell's run directory and ``metrics.json``), the driver alone records and commits. The same
launchers as the project's Hydra sweeps (``conf/hydra/launcher/``):

- ``local``: one cell at a time in this process's machine (the default; a 2-core machine);
- ``joblib``: ``--jobs`` cells at once on this machine (joblib's threading backend: each worker
  waits on its cell's process);
- ``ray_local``: a Ray instance started on this machine (``ray.init(num_cpus=--jobs)``, Ray's local
  mode since ``local_mode=True`` was removed), as ``hydra/launcher=ray_local`` does;
- ``ray``: a running Ray cluster (``ray.init(address="auto")``): workers need the repository, its
  worktree and the stage cache at the same paths (a shared file system), as Hydra's Ray launcher does;
- ``slurm``: submitit jobs on SLURM (``pip install .[slurm]``), the same shared-file-system rule.

Jobs are pulled from an iterator lazily, so the driver decides at each start whether another cell
still fits before its deadline.
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

LAUNCHERS = ("local", "joblib", "ray_local", "ray", "slurm")


@dataclass(frozen=True)
class Job:
    """One cell's ``run.py`` command: what a worker runs, and the driver's key for it."""

    key: tuple
    command: Sequence[str]
    cwd: Path
    env: dict = field(default_factory=dict, compare=False, repr=False)


def run_job(job: Job) -> tuple[Job, int]:
    """Run one job's command to its end; (the job, its exit code)."""
    return job, subprocess.run(list(job.command), cwd=job.cwd, env=job.env).returncode


def launch(jobs: Iterable[Job], launcher: str = "local", n_jobs: int = 1) -> Iterator[tuple[Job, int]]:
    """Run ``jobs`` on ``launcher``, at most ``n_jobs`` at once; yield (job, exit code) as each ends.

    Raises:
        ValueError: an unknown launcher, or one whose package is not installed (named with the
            install that brings it)."""
    if launcher not in LAUNCHERS:
        raise ValueError(f"--launcher must be one of {', '.join(LAUNCHERS)}, got {launcher!r}")
    jobs = iter(jobs)
    if launcher == "local":
        for job in jobs:
            yield run_job(job)
    elif launcher == "joblib":
        # heavy (joblib): imported on use
        from joblib import Parallel, delayed

        parallel = Parallel(
            n_jobs=max(n_jobs, 1), backend="threading", return_as="generator_unordered", pre_dispatch="n_jobs"
        )
        yield from parallel(delayed(run_job)(job) for job in jobs)
    elif launcher in ("ray_local", "ray"):
        yield from _ray(jobs, launcher == "ray_local", n_jobs)
    else:
        yield from _slurm(jobs, n_jobs)


def _ray(jobs: Iterator[Job], local_mode: bool, n_jobs: int) -> Iterator[tuple[Job, int]]:
    try:
        # optional dependency: imported on use
        import ray
    except ImportError:
        raise ValueError("--launcher ray needs Ray: pip install -e '.[ray]'") from None
    if not ray.is_initialized():
        if local_mode:
            ray.init(num_cpus=max(n_jobs, 1), include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address="auto")
    remote = ray.remote(num_cpus=1)(run_job)
    in_flight = []
    for job in jobs:
        in_flight.append(remote.remote(job))
        while len(in_flight) >= max(n_jobs, 1):
            done, in_flight = ray.wait(in_flight, num_returns=1)
            yield ray.get(done[0])
    while in_flight:
        done, in_flight = ray.wait(in_flight, num_returns=1)
        yield ray.get(done[0])


def _slurm(jobs: Iterator[Job], n_jobs: int) -> Iterator[tuple[Job, int]]:
    try:
        # optional dependency: imported on use
        import submitit
    except ImportError:
        raise ValueError("--launcher slurm needs submitit: pip install -e '.[slurm]'") from None

    executor = submitit.AutoExecutor(folder=Path("study") / "slurm_logs")
    executor.update_parameters(timeout_min=24 * 60, cpus_per_task=2)
    in_flight: list = []

    def finished() -> Iterator[tuple[Job, int]]:
        while True:
            done = [j for j in in_flight if j.done()]
            if done:
                for j in done:
                    in_flight.remove(j)
                    yield j.result()
                return
            time.sleep(30.0)

    for job in jobs:
        in_flight.append(executor.submit(run_job, job))
        if len(in_flight) >= max(n_jobs, 1):
            yield from finished()
    while in_flight:
        yield from finished()
