"""The study's queue: every cell once, every level one its planner defines, phases in order."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
import pytest

from experiments.study_plan import (
    OWN_LEVELS,
    StudyCell,
    corrected_hours,
    estimate_hours,
    plan_table,
    study_cells,
)

ROOT = Path(__file__).resolve().parents[1]


def test_the_study_has_each_cell_once_in_phase_order():
    cells = study_cells()
    specs = [c.spec() for c in cells]
    assert len(specs) == len(set(specs)) == 162
    assert [c.phase for c in cells] == sorted(c.phase for c in cells)
    # 1: seed 0 of the tomb's and church's own-knob fronts, 20 levels a scene, the oracle beside
    phase1 = [c for c in cells if c.phase == 1]
    assert len(phase1) == 2 * sum(len(v) for v in OWN_LEVELS.values()) == 40
    assert all(c.overrides == () and c.gsd_m == 0.03 and c.seed == 0 for c in phase1)
    # 2: the cathedral, every planner at its default
    assert [c.spec() for c in cells if c.phase == 2] == [
        f"cathedral/{p}/0/default/0.03" for p in ("ours", "smith", "lawnmower", "ours_plus", "yan")
    ]
    # 3: the noise floor: ours and Smith on the church, three repeats each, on the committed proxy
    noise = [c for c in cells if c.phase == 3]
    assert [c.spec() for c in noise[:2]] == [
        "church/ours/0/default/0.03@rep0",
        "church/smith/0/default/0.03@rep0",
    ]
    assert all(c.overrides == ("reconstruct.deterministic=false",) for c in noise)
    assert {c.preset("protocol1") for c in noise} == {f"protocol1_noise/rep{k}" for k in range(3)}
    # 4: seeds 1 and 2 of phase 1, the oracle off
    seeds = [c for c in cells if c.phase == 4]
    assert len(seeds) == 80 and {c.seed for c in seeds} == {1, 2}
    assert all(c.overrides == ("reconstruct.oracle_beside=false",) for c in seeds)
    # 5: the shared meshes; 6: the GSD axis; 7: Yan at the seed paper's scale
    plant = [c for c in cells if c.scene == "powerplant"]
    assert len(plant) == 5 and all(c.overrides == ("exploration=lawnmower_orbit",) for c in plant)
    assert {c.phase for c in cells if c.scene in ("school", "powerplant")} == {5}
    gsd = [c for c in cells if c.phase == 6]
    assert {(c.budget, c.gsd_m) for c in gsd} == {("default", 0.045), ("default", 0.02)}
    assert len(gsd) == 2 * 5 * 2
    assert [c.spec() for c in cells if c.phase == 7] == ["tomb/yan/0/highest/0.03"]
    assert cells[0].preset("protocol1") == "protocol1"


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


def test_an_earlier_studys_hours_are_scaled_by_what_this_studys_same_cells_cost():
    keys = ["scene", "planner", "budget"]
    groups = pd.DataFrame(
        [
            ("tomb", "ours", "low", 0, 1.0),  # this study: 4x and 2x the earlier study's same cells
            ("tomb", "ours", "low", 1, 0.25),
            ("tomb", "ours", "high", 0, 2.0),
            ("tomb", "ours", "high", 1, 1.0),
            ("tomb", "ours", "mid", 0, 3.0),
            ("tomb", "ours", "mid", 1, 1.0),
            ("church", "smith", "low", 1, 0.5),  # only the earlier study: scaled by the median ratio
        ],
        columns=[*keys, "rank", "hours"],
    )
    hours = corrected_hours(groups, keys).set_index(keys)["hours"]
    assert hours[("tomb", "ours", "low")] == 1.0 and hours[("tomb", "ours", "high")] == 2.0
    assert hours[("church", "smith", "low")] == pytest.approx(0.5 * 3.0)  # median of 4, 2, 3
    assert len(hours) == 4


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
    # another GSD: the same cells' hours scaled by the image count (GSD^-2)
    assert estimate_hours(StudyCell(6, "tomb", "yan", 0, "default", 0.02), past) == pytest.approx(4.5)
    # a level above any record's: twice the planner's longest cell
    assert estimate_hours(StudyCell(7, "tomb", "yan", 0, "highest"), past) == pytest.approx(4.0)
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


def test_a_noise_repeat_has_its_own_records_and_cache(monkeypatch, tmp_path):
    import experiments.record
    import experiments.study_plan as study_plan

    calls = []
    monkeypatch.setattr(experiments.record, "run_queue", lambda *a, **k: calls.append((a, k)) or 0)
    monkeypatch.setattr(study_plan, "ensure_bundles", lambda cells, deadline, commit, then_hours=0.0: [])
    cells = [
        StudyCell(1, "tomb", "ours", 0),
        StudyCell(1, "church", "ours", 0),
        StudyCell(3, "church", "ours", 0, overrides=("reconstruct.deterministic=false",), repeat=1),
    ]
    preset = "no_such_preset"  # no records: no proxy to hold a group to
    assert study_plan.run_cells(cells, preset, tmp_path / "protocol1", ["a=1"]) == 0
    # one queue run per stretch of one folder, scene and seed (each proxy committed before it)
    (first, first_kwargs), (second, _), (third, _) = calls
    assert first[0] == [("tomb", "ours", 0, "default", 0.03, ())] and second[0][0][0] == "church"
    assert first[1:4] == (preset, tmp_path / "protocol1", ["a=1"])
    assert first_kwargs["proxies"] == {}
    assert third[0] == [("church", "ours", 0, "default", 0.03, ("reconstruct.deterministic=false",))]
    assert third[1] == f"{preset}_noise/rep1" and third[2] == tmp_path / "protocol1_noise" / "rep1"
    cache = (tmp_path / "protocol1_noise" / "rep1" / "cache").resolve()
    assert third[3] == ["a=1", f"cache_dir={cache}"]


def test_until_is_the_next_such_time():
    import datetime as dt

    from experiments.study_plan import parse_until

    now = dt.datetime(2026, 12, 7, 13, 0)
    assert parse_until("15:40", now) == dt.datetime(2026, 12, 7, 15, 40).timestamp()
    assert parse_until("12:30", now) == dt.datetime(2026, 12, 8, 12, 30).timestamp()
    assert parse_until("2026-12-09T08:00", now) == dt.datetime(2026, 12, 9, 8, 0).timestamp()
    with pytest.raises(ValueError, match=r"give HH:MM \(e.g. 15:40\)"):
        parse_until("soon", now)


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
