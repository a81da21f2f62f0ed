"""Cell records: copied into results/cells/<preset>/..., summarised, committed alone."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from experiments.record import commit_record, parse_cell, record_cell, record_dir, run_queue, summary_line
from experiments.runs import RunDirectoryError
from tests.experiments_fixtures import square_plan, write_run


def test_a_cell_record_holds_its_metrics_and_plan(tmp_path):
    run = write_run(
        tmp_path / "study",
        "tomb",
        "yan",
        2,
        plan=square_plan("yan"),
        n_images=1343,
        n_registered=1340,
        acc90_m=0.0512,
        comp_050=71.25,
        cell_wall_time_s=7260.0,
        cell_cpu_time_s=12600.0,
    )
    overrides = "- scene=tomb\n- planner=yan\n- seed=2\n- reconstruct.dense.fusion.max_memory_gb=8\n"
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text(overrides)
    dest, metrics = record_cell(run, "default", root=tmp_path / "cells")
    assert dest == record_dir("default", "tomb", "yan", 2, root=tmp_path / "cells")
    assert dest == tmp_path / "cells" / "default" / "tomb" / "yan" / "default" / "seed2"
    assert json.loads((dest / "metrics.json").read_text()) == json.loads((run / "metrics.json").read_text())
    assert (dest / "plan.json").read_text() == (run / "plan" / "plan.json").read_text()
    assert (dest / "viewpoints.csv").read_text() == (run / "plan" / "viewpoints.csv").read_text()
    assert (dest / "overrides.yaml").read_text() == overrides
    assert summary_line(metrics) == (
        "Cell record: tomb / yan / seed 2: 1343 images, 1340 registered, acc90 5.1 cm, "
        "completeness 71.2 % at 5 cm, cell 121.0 min (210.0 min CPU)"
    )


def test_a_failed_cell_is_recorded_with_its_error(tmp_path):
    run = write_run(tmp_path, "church", "ours", 0, status="failed", error="no model", failed_stage="mapping")
    dest, metrics = record_cell(run, "default", root=tmp_path / "cells")
    assert not (dest / "plan.json").exists()
    assert not (dest / "viewpoints.csv").exists()
    assert not (dest / "overrides.yaml").exists()
    assert summary_line(metrics) == "Cell record: church / ours / seed 0 failed in stage mapping: no model"


def test_no_metrics_no_record(tmp_path):
    with pytest.raises(RunDirectoryError, match="metrics.json: not found"):
        record_cell(tmp_path, "default", root=tmp_path / "cells")


def test_commit_takes_the_record_and_nothing_else(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / "code.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "code.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "code"], check=True)
    (repo / "code.py").write_text("x = 2\n")  # an edit in progress, staged
    subprocess.run([*git, "add", "code.py"], check=True)
    run = write_run(tmp_path / "study", "tomb", "ours", 0, n_images=215)
    dest, _ = record_cell(run, "default", root=repo / "results" / "cells")
    env_git = ["git", "-C", str(repo)]
    subprocess.run([*env_git, "config", "user.name", "t"], check=True)
    subprocess.run([*env_git, "config", "user.email", "t@t"], check=True)
    commit_record(dest, "Cell record: tomb / ours / seed 0", repo=repo)
    shown = subprocess.run(
        [*env_git, "show", "--name-only", "--format=%s", "HEAD"], capture_output=True, text=True
    )
    lines = [line for line in shown.stdout.splitlines() if line]
    assert lines == [
        "Cell record: tomb / ours / seed 0",
        "results/cells/default/tomb/ours/default/seed0/metrics.json",
    ]
    staged = subprocess.run([*env_git, "diff", "--cached", "--name-only"], capture_output=True, text=True)
    assert staged.stdout.split() == ["code.py"]  # the edit stays staged, uncommitted


def test_cells_are_scene_planner_seed_budget_and_gsd():
    assert parse_cell("tomb/yan/0") == ("tomb", "yan", 0, "default", None)
    assert parse_cell("tomb/ours/2/high") == ("tomb", "ours", 2, "high", None)
    assert parse_cell("tomb/smith/1/default/0.045") == ("tomb", "smith", 1, "default", 0.045)
    with pytest.raises(ValueError, match="scene/planner/seed"):
        parse_cell("tomb/yan")
    with pytest.raises(ValueError, match="budget must be one of"):
        parse_cell("tomb/yan/0/huge")
    for gsd in ("0", "-0.02", "nan", "fine"):
        with pytest.raises(ValueError, match="the GSD must be a positive number of m/px"):
            parse_cell(f"tomb/yan/0/default/{gsd}")


def test_a_cell_that_records_its_gsd_is_filed_under_it(tmp_path):
    run = write_run(tmp_path / "study", "church", "yan", 0, n_images=300, budget="mid", target_gsd_m=0.045)
    dest, _ = record_cell(run, "study", root=tmp_path / "cells")
    assert dest == tmp_path / "cells" / "study" / "church" / "yan" / "gsd0.045" / "mid" / "seed0"
    assert dest == record_dir("study", "church", "yan", 0, "mid", 0.045, root=tmp_path / "cells")


def test_a_budget_cell_has_its_own_record_and_name(tmp_path):
    run = write_run(tmp_path / "study", "tomb", "ours", 1, n_images=402, budget="high")
    dest, metrics = record_cell(run, "study", root=tmp_path / "cells")
    assert dest == tmp_path / "cells" / "study" / "tomb" / "ours" / "high" / "seed1"
    assert summary_line(metrics).startswith("Cell record: tomb / ours / seed 1 / high budget: 402 images")


def test_a_queue_on_an_unknown_revision_runs_nothing(tmp_path):
    with pytest.raises(ValueError, match="names no commit"):
        run_queue([("tomb", "ours", 0, "default")], "default", tmp_path, revision="no-such-revision-x")
    assert not any(tmp_path.iterdir())


def test_a_queue_whose_records_git_ignores_runs_nothing(tmp_path):
    # .gitignore ignores __pycache__/ folders anywhere: a study of that name could never be committed.
    with pytest.raises(ValueError, match="is ignored by git"):
        run_queue([("tomb", "ours", 0, "default")], "__pycache__", tmp_path)
    assert not any(tmp_path.iterdir())


def test_the_ignore_check_looks_at_every_cell_of_the_queue(tmp_path):
    # The first cell's records could be committed, the second's not (a __pycache__/ folder on its path).
    cells = [("tomb", "ours", 0, "default"), ("__pycache__", "ours", 0, "default")]
    with pytest.raises(ValueError, match=r"cells/queue_check/__pycache__/ours/.*is ignored by git"):
        run_queue(cells, "queue_check", tmp_path)
    assert not any(tmp_path.iterdir())


def test_a_cell_on_another_proxy_than_its_group_is_named_and_filed_apart():
    from experiments.record import other_proxy, proxy_preset

    proxies = {("tomb", 0): "ff4b3dae0123abcd"}
    cell = {"scene": "tomb", "seed": 0, "proxy_fingerprint": "e761cbcb4567ef01"}
    assert other_proxy(proxies, cell) == "e761cbcb4567ef01"
    assert proxy_preset("settled", "e761cbcb4567ef01") == "settled_proxy_e761cbcb"
    # The group's proxy, another group, a record without a fingerprint: nothing to say.
    assert other_proxy(proxies, cell | {"proxy_fingerprint": "ff4b3dae0123abcd"}) is None
    assert other_proxy(proxies, cell | {"seed": 1}) is None
    assert other_proxy(proxies, {"scene": "tomb", "seed": 0}) is None


FAKE_RUN = """
import fcntl, json, os, sys
from pathlib import Path
values = dict(item.split("=", 1) for item in sys.argv[1:])
outcomes = Path(os.environ["FAKE_OUTCOMES"])
with open(os.environ["FAKE_RUNS"], "a") as log:  # the lock: two workers take two outcomes
    fcntl.flock(log, fcntl.LOCK_EX)
    script = outcomes.read_text().split()
    status, rest = script[0], script[1:]
    outcomes.write_text(" ".join(rest))
    log.write(values["hydra.run.dir"] + "\\n")
run_dir = Path(values["hydra.run.dir"])
metrics = {
    "scene": values["scene"], "planner": values["planner"], "seed": int(values["seed"]),
    "budget": values["budget"], "target_gsd_m": float(values["survey.target_gsd_m"]),
    "status": status, "protocol": 1, "planner_version": 1, "n_images": 10, "cell_wall_time_s": 60.0,
}
if status != "ok":
    metrics.update(failed_stage="reconstruct", error="RuntimeError: no model")
(run_dir / "images").mkdir(parents=True)
(run_dir / "metrics.json").write_text(json.dumps(metrics))
sys.exit(0 if status == "ok" else 1)
"""


class FakeCells:
    """Stands in for ``run.py`` under the queue: a script in the queue's worktree that writes the
    ``metrics.json`` its outcomes say (``ok`` or ``failed``) into ``hydra.run.dir``, a process of its
    own as ``run.py`` is (so every launcher runs it as it would a cell); git runs for real."""

    def __init__(self, monkeypatch, tmp_path, outcomes):
        from contextlib import contextmanager

        import experiments.record as record

        tree = tmp_path / "tree"
        tree.mkdir()
        (tree / "run.py").write_text(FAKE_RUN)
        (tree / "conf").symlink_to(Path(record.ROOT) / "conf")  # the planners' versions
        self.outcomes, self.log = tmp_path / "outcomes.txt", tmp_path / "runs.txt"
        self.outcomes.write_text(" ".join(outcomes))
        self.log.write_text("")
        monkeypatch.setenv("FAKE_OUTCOMES", str(self.outcomes))
        monkeypatch.setenv("FAKE_RUNS", str(self.log))

        @contextmanager
        def worktree(revision, prefix="", parent=None):
            yield tree

        monkeypatch.setattr(record, "revision_worktree", worktree)

    @property
    def runs(self) -> list[str]:
        return self.log.read_text().split()


CELL = ("tomb", "ours", 0, "default", 0.03)


def queue(tmp_path, limits, force=False, cells=(CELL,), **launch):
    from experiments.record import run_queue

    return run_queue(
        list(cells),
        "q",
        tmp_path / "runs",
        commit=False,
        limits=limits,
        force=force,
        records_root=tmp_path / "cells",
        **launch,
    )


def test_a_failed_cell_is_recorded_and_run_once_more(monkeypatch, tmp_path, capsys):
    from experiments.record import QueueLimits

    cells = FakeCells(monkeypatch, tmp_path, ["failed", "failed"])
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0)) == 1
    assert len(cells.runs) == 2
    record = json.loads((record_dir("q", *CELL, root=tmp_path / "cells") / "metrics.json").read_text())
    assert record["status"] == "failed" and record["error"] == "RuntimeError: no model"
    assert "failed in stage reconstruct: RuntimeError: no model" in capsys.readouterr().out
    # recorded at this protocol and planner version, failed twice: the next run leaves it
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0)) == 0 and len(cells.runs) == 2


def test_a_failure_whose_retry_never_ran_is_run_again(monkeypatch, tmp_path):
    """The deadline stopped the queue after a cell's first, failed try: the next run retries it."""
    from experiments.record import QueueLimits

    cells = FakeCells(monkeypatch, tmp_path, ["failed", "ok"])
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0, attempts=1)) == 1  # one try this time
    path = record_dir("q", *CELL, root=tmp_path / "cells") / "metrics.json"
    assert json.loads(path.read_text())["queue_attempt"] == 1
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0)) == 0 and len(cells.runs) == 2
    assert json.loads(path.read_text())["status"] == "ok"


def test_a_cell_that_fails_once_is_recorded_from_its_second_run_and_pruned(monkeypatch, tmp_path):
    from experiments.record import QueueLimits

    cells = FakeCells(monkeypatch, tmp_path, ["failed", "ok"])
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0)) == 0
    assert len(cells.runs) == 2
    record = json.loads((record_dir("q", *CELL, root=tmp_path / "cells") / "metrics.json").read_text())
    assert record["status"] == "ok"
    assert not Path(cells.runs[-1]).exists()  # the run directory, pruned


def test_no_cell_starts_past_the_deadline_or_below_the_disk_floor(monkeypatch, tmp_path, capsys):
    import time

    from experiments.record import QueueLimits

    cells = FakeCells(monkeypatch, tmp_path, ["ok"])
    soon = QueueLimits(deadline=time.time() + 30 * 60, estimates_h={CELL: 0.75}, min_free_gb=0.0, margin=1.0)
    assert queue(tmp_path, soon) == 0 and cells.runs == []
    assert "estimated 45 min, 30 min left before the deadline: queue stopped" in capsys.readouterr().out
    assert queue(tmp_path, QueueLimits(min_free_gb=1e9)) == 1 and cells.runs == []
    assert (
        "below the queue's 1e+09 GB: queue stopped (free disk, or lower --min-free-gb)"
        in capsys.readouterr().out
    )
    tight = QueueLimits(deadline=time.time() + 60 * 60, estimates_h={CELL: 0.75}, min_free_gb=0.0, margin=1.5)
    assert queue(tmp_path, tight) == 0 and cells.runs == []  # 1.5 x 45 min does not fit in an hour
    later = QueueLimits(deadline=time.time() + 60 * 60, estimates_h={CELL: 0.75}, min_free_gb=0.0, margin=1.0)
    assert queue(tmp_path, later) == 0 and len(cells.runs) == 1


def test_a_record_of_another_protocol_or_planner_version_is_run_again(monkeypatch, tmp_path):
    from experiments.record import QueueLimits, current_record

    cells = FakeCells(monkeypatch, tmp_path, ["ok", "ok", "ok"])
    limits = QueueLimits(min_free_gb=0.0)
    path = record_dir("q", *CELL, root=tmp_path / "cells") / "metrics.json"
    assert queue(tmp_path, limits) == 0 and len(cells.runs) == 1
    assert queue(tmp_path, limits) == 0 and len(cells.runs) == 1  # current: left alone
    for stale in ({"protocol": None}, {"planner_version": 0}):
        path.write_text(json.dumps({**json.loads(path.read_text()), **stale}))
        assert current_record(path, 1) is None
        assert queue(tmp_path, limits) == 0
    assert len(cells.runs) == 3


@pytest.mark.parametrize("launcher", ["joblib", "ray_local"])
def test_a_launcher_runs_the_cells_and_the_driver_records_them(monkeypatch, tmp_path, launcher):
    """Three cells, two workers: every cell recorded once by the driver, the failed one run again."""
    from experiments.record import QueueLimits

    cells = [CELL, ("tomb", "smith", 0, "default", 0.03), ("church", "ours", 0, "low", 0.03)]
    fake = FakeCells(monkeypatch, tmp_path, ["ok", "failed", "ok", "ok"])
    assert queue(tmp_path, QueueLimits(min_free_gb=0.0), cells=cells, launcher=launcher, n_jobs=2) == 0
    assert len(fake.runs) == 4
    for cell in cells:
        record = json.loads((record_dir("q", *cell, root=tmp_path / "cells") / "metrics.json").read_text())
        assert record["status"] == "ok" and record["planner"] == cell[1]
