"""ours_plus' flight-time front from cell records: weights read from plan.json, seeds averaged,
each weight against ours on the same scene."""

from __future__ import annotations

import json

import pytest

from experiments.ours_plus_front import front_frame, main
from experiments.runs import load_runs, runs_frame
from tests.experiments_fixtures import write_run


def _cell(root, planner, seed, weight=None, **metrics):
    run = write_run(root, "tomb", planner, seed, budget="default", **metrics)
    if weight is not None:
        (run / "plan.json").write_text(json.dumps({"time_weight_per_pct": weight}))
    return run


@pytest.fixture
def records(tmp_path):
    root = tmp_path / "cells"
    _cell(root, "ours", 0, n_images=200, flight_time_s=1200.0, comp_050=80.0, acc90_m=0.03)
    _cell(root, "smith", 0, n_images=190, flight_time_s=1000.0, comp_050=70.0, acc90_m=0.02)
    # Weight 2 under two configs' names and two seeds: one point, the seeds' mean.
    _cell(root, "ours_plus", 0, 2.0, n_images=170, flight_time_s=960.0, comp_050=79.0, acc90_m=0.03)
    _cell(root, "ours_plus", 1, 2.0, n_images=180, flight_time_s=1000.0, comp_050=77.0, acc90_m=0.03)
    _cell(root, "ours_plus_time12", 0, 12.0, n_images=120, flight_time_s=720.0, comp_050=70.0, acc90_m=0.02)
    _cell(root, "ours_plus_time4", 0, None, n_images=1, flight_time_s=1.0, comp_050=1.0, acc90_m=0.1)
    return root


def test_weights_are_joined_in_order_and_compared_with_ours(records):
    points = front_frame(runs_frame(load_runs([records])))
    plus = points[points["curve"] == "ours_plus"]
    assert plus["time_weight"].tolist() == [2.0, 12.0]  # the cell without a recorded weight is left out
    assert plus["n"].tolist() == [2, 1]
    assert plus["flight_time_s"].tolist() == [980.0, 720.0]
    assert plus["flight_time_vs_ours_pct"].to_numpy() == pytest.approx([100 * (980 / 1200 - 1), -40.0])
    assert plus["completeness_vs_ours_points"].to_numpy() == pytest.approx([-2.0, -10.0])
    assert sorted(points.loc[points["curve"] != "ours_plus", "curve"]) == ["ours", "smith"]


def test_the_command_writes_the_figure_and_tables(records, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(records), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "front_flight_time.csv",
        "front_flight_time.md",
        "front_flight_time.png",
    ]
    table = (out / "front_flight_time.md").read_text()
    assert "| Tomb | Ours+ | 12 | 1 | 120 | 12.0 | -40 % | 70.0 | -10.0 | 2.0 |" in table


def test_no_ours_plus_cell_is_one_line_and_exit_2(tmp_path, capsys):
    root = tmp_path / "cells"
    _cell(root, "ours", 0, n_images=200, flight_time_s=1200.0, comp_050=80.0, acc90_m=0.03)
    assert main([str(root), "--out", str(tmp_path / "out")]) == 2
    assert "no successful ours_plus cell" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
