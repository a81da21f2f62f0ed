"""The study's queue: every cell once, every level one its planner defines, phases in order."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
import pytest

from experiments.study_plan import (
    OWN_LEVELS,
    StudyCell,
    estimate_hours,
    plan_table,
    study_cells,
)

ROOT = Path(__file__).resolve().parents[1]


def test_the_study_has_each_cell_once_in_phase_order():
    cells = study_cells()
    specs = [c.spec() for c in cells]
    assert len(specs) == len(set(specs)) == 212
    assert [c.phase for c in cells] == sorted(c.phase for c in cells)
    # seed 0 of the tomb's and church's own-knob fronts first: 20 levels a scene
    assert sum(c.phase == 1 for c in cells) == 2 * sum(len(v) for v in OWN_LEVELS.values()) == 40
    # every planner on the GSD axis at its default knob; 3 cm is the own-knob front's default cell
    gsd = [c for c in cells if c.phase == 2]
    assert {(c.budget, c.gsd_m) for c in gsd} == {("default", 0.045), ("default", 0.02)}
    assert len(gsd) == 2 * 5 * 2
    assert {c.seed for c in cells if c.phase == 3} == {1, 2}
    assert [c.spec() for c in cells if c.phase == 6] == ["tomb/yan/0/highest/0.03"]
    noise = [c for c in cells if c.phase == 7]  # ours and Smith on the church, three repeats each
    assert [c.spec() for c in noise[:2]] == [
        "church/ours/0/default/0.03@rep0",
        "church/smith/0/default/0.03@rep0",
    ]
    assert {c.preset("settled") for c in noise} == {f"settled_noise/rep{k}" for k in range(3)}
    assert cells[0].preset("settled") == "settled"
    plant = [c for c in cells if c.scene == "powerplant"]
    assert len(plant) == 5 and all(c.overrides == ("exploration=lawnmower_orbit",) for c in plant)


def test_every_study_level_is_one_its_planner_defines():
    from hydra import compose, initialize_config_dir

    from pipeline.settings import planner_setup

    with initialize_config_dir(config_dir=os.fspath(ROOT / "conf"), version_base=None):
        for planner, levels in OWN_LEVELS.items():
            values = []
            for level in levels:
                _, record = planner_setup(
                    compose("config", overrides=[f"planner={planner}", f"budget={level}"])
                )
                values.append(record.get("budget_value"))
            assert len(values) == len(set(map(str, values))), planner


def test_cell_hours_come_from_the_most_similar_earlier_cell():
    past = pd.DataFrame(
        [
            ("tomb", "yan", "default", 2.0),
            ("tomb", "yan", "low", 0.5),
            ("church", "yan", "mid", 1.0),
        ],
        columns=["scene", "planner", "budget", "hours"],
    )
    assert estimate_hours(StudyCell(1, "tomb", "yan", 0, "low"), past) == 0.5
    assert estimate_hours(StudyCell(1, "tomb", "yan", 0, "mid"), past) == 2.0  # its default's
    assert estimate_hours(StudyCell(1, "cathedral", "yan", 0, "mid"), past) == 1.0  # the planner's level
    assert estimate_hours(StudyCell(1, "school", "ours", 0), past) == pytest.approx(0.75)
    cells = [
        StudyCell(1, "tomb", "yan", 0, "low"),
        StudyCell(1, "tomb", "yan", 1, "low"),
        StudyCell(2, "tomb", "yan", 0),
    ]
    table = plan_table(cells, past, recorded={"tomb/yan/0/low/0.03"})
    assert table.to_dict("list") == {
        "phase": [1, 2],
        "cells": [2, 1],
        "recorded": [1, 0],
        "hours_left": [0.5, 2.0],
    }


def test_a_noise_repeat_runs_from_nothing_in_its_own_records(monkeypatch, tmp_path):
    import experiments.record
    from experiments.study_plan import run_cells

    calls = []
    monkeypatch.setattr(experiments.record, "run_queue", lambda *a, **k: calls.append((a, k)) or 0)
    cells = [StudyCell(1, "tomb", "ours", 0), StudyCell(7, "church", "ours", 0, repeat=1)]
    preset = "no_such_preset"  # no records: no proxy to hold a group to
    assert run_cells(cells, preset, tmp_path / "settled", ["a=1"], "abc1234") == 0
    (first, first_kwargs), (second, kwargs) = calls
    # The study's cells run deterministic; the noise floor's repeats in the default mode.
    assert first[1:4] == (preset, tmp_path / "settled", ["a=1", "reconstruct.deterministic=true"])
    assert first_kwargs == {"revision": "abc1234", "proxies": {}}
    assert second[1] == f"{preset}_noise/rep1" and second[2] == tmp_path / "settled_noise" / "rep1"
    cache = (tmp_path / "settled_noise" / "rep1" / "cache").resolve()
    assert second[3] == ["a=1", "reconstruct.deterministic=false", f"cache_dir={cache}"]
    assert kwargs == {"revision": "abc1234", "proxies": None}


def test_records_of_another_revision_are_named_before_a_run():
    from experiments.study_plan import foreign_records

    commits = {"tomb/ours/0": "efed9486b020", "tomb/smith/0": "1234abcd5678", "tomb/yan/0": ""}
    # A full revision sha against abbreviated and full record commits; a record without a commit is foreign.
    assert foreign_records(commits, "efed9486b020255669cd73cd0eff17fab613948d") == [
        "tomb/smith/0",
        "tomb/yan/0",
    ]
    assert foreign_records({"tomb/ours/0": "efed9486b020255669cd73cd0eff17fab613948d"}, "efed948") == []


def test_cells_that_planned_on_different_proxies_are_counted_per_scene_and_seed():
    from experiments.study_plan import proxies_per_group

    cells = [
        StudyCell(1, "tomb", "ours", 0, "low"),
        StudyCell(1, "tomb", "smith", 0),
        StudyCell(1, "tomb", "yan", 0),
        StudyCell(3, "tomb", "ours", 1),
        StudyCell(7, "church", "ours", 0, repeat=0),
        StudyCell(1, "church", "lawnmower", 0),
    ]
    fingerprints = {
        "tomb/ours/0/low/0.03": "aaaa",
        "tomb/smith/0/default/0.03": "bbbb",
        "tomb/yan/0/default/0.03": "aaaa",
        "tomb/ours/1/default/0.03": "cccc",
        "church/ours/0/default/0.03@rep0": "dddd",
    }
    # The church's lawnmower has no record; the noise repeat builds its own proxy on purpose.
    assert proxies_per_group(cells, fingerprints) == {
        ("tomb", 0): {"aaaa": 2, "bbbb": 1},
        ("tomb", 1): {"cccc": 1},
    }


def test_a_group_is_held_to_the_proxy_most_of_its_records_planned_on():
    from experiments.study_plan import group_proxies

    counts = {
        ("tomb", 0): {"aaaa": 2, "bbbb": 1},
        ("church", 0): {"none": 3},
        ("tomb", 1): {"none": 2, "cccc": 1},
    }
    assert group_proxies(counts) == {("tomb", 0): "aaaa", ("tomb", 1): "cccc"}


def test_records_of_the_default_mode_are_named_before_a_run(monkeypatch):
    import experiments.study_plan as study_plan

    modes = {
        "tomb/ours/0/default/0.03": "True",
        "tomb/smith/0/default/0.03": "",
        "tomb/yan/0/default/0.03": "",
    }
    asked = []

    def fields(preset, cells, key):
        asked.append((key, [c.spec() for c in cells]))
        return modes

    monkeypatch.setattr(study_plan, "recorded_fields", fields)
    cells = [StudyCell(1, "tomb", "ours", 0), StudyCell(7, "church", "ours", 0, repeat=0)]
    assert study_plan.default_mode_records("settled", cells) == [
        "tomb/smith/0/default/0.03",
        "tomb/yan/0/default/0.03",
    ]
    # The noise floor's repeats run in the default mode on purpose: not asked about.
    assert asked == [("deterministic", ["tomb/ours/0/default/0.03"])]


def test_a_measurement_preset_can_queue_some_planners_only(tmp_path, capsys):
    from experiments.study_plan import main

    preset = f"no_records_{tmp_path.name}"  # no folder under results/cells/: every cell is left
    assert main(["--phases", "1", "--planners", "ours", "ours_plus", "--preset", preset, "--list"]) == 0
    listed = capsys.readouterr().out.split()
    # 4 own levels each, on the tomb and the church
    assert len(listed) == 16
    assert {spec.split("/")[1] for spec in listed} == {"ours", "ours_plus"}
    assert listed[0] == "tomb/ours/0/lowest/0.03"
    assert main(["--planners", "smith", "drone", "--list"]) == 2
    assert capsys.readouterr().err.strip() == (
        "error: --planners: no planner ['drone'] (planners: lawnmower, smith, yan, ours, ours_plus)"
    )
