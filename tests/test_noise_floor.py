"""The noise floor: spread of repeated cells, the floor file, and the tie rule of the tables."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from experiments import noise_floor, tables
from tests.experiments_fixtures import write_run

OURS_COMP = [40.0, 42.0, 44.0, 46.0, 48.0]  # mean 44, std sqrt(10), range 8
LAWN_COMP = [30.0, 31.0, 32.0, 33.0, 34.0]  # mean 32, std sqrt(2.5), range 4


@pytest.fixture
def repeats(tmp_path):
    root = tmp_path / "noise"
    for rep, (ours, lawn) in enumerate(zip(OURS_COMP, LAWN_COMP, strict=True)):
        write_run(root / f"rep{rep}", "tomb", "ours", 0, comp_050=ours, acc90_m=0.030 + 0.001 * rep)
        write_run(root / f"rep{rep}", "tomb", "lawnmower", 0, comp_050=lawn, acc90_m=0.050)
    write_run(root / "rep5", "tomb", "ours", 0, status="failed", error="boom")
    return root


def test_every_repeat_counts_and_the_spread_is_exact(repeats):
    runs = noise_floor.load_repeats(repeats)
    assert len(runs) == 11  # the same seed in every repeat: none is dropped as a re-run
    summary = noise_floor.summarise_repeats(runs).set_index(["planner", "metric"])
    ours = summary.loc[("ours", "comp_050")]
    assert ours["n"] == 5  # the failed repeat is left out
    assert ours["mean"] == pytest.approx(44.0)
    assert ours["std"] == pytest.approx(math.sqrt(10.0))
    assert (ours["min"], ours["max"], ours["range"]) == (40.0, 48.0, 8.0)
    assert summary.loc[("lawnmower", "comp_050"), "std"] == pytest.approx(math.sqrt(2.5))
    assert summary.loc[("ours", "acc90_m"), "range"] == pytest.approx(0.004)
    assert summary.loc[("lawnmower", "acc90_m"), "range"] == 0.0
    # The floor is the larger range of the two planners.
    floor = noise_floor.noise_floor(summary.reset_index())
    assert floor["comp_050"] == 8.0 and floor["acc90_m"] == pytest.approx(0.004)


def test_command_line_writes_a_floor_the_tables_read(repeats, tmp_path, capsys):
    out = tmp_path / "floor"
    assert noise_floor.main(["--summarise", str(repeats), "--out", str(out)]) == 0
    floor = noise_floor.read_floor(out / noise_floor.FLOOR_FILE)
    assert floor["comp_050"] == 8.0
    record = json.loads((out / noise_floor.FLOOR_FILE).read_text())
    assert {"scene": "tomb", "planner": "ours", "repeats": 5} in record["cells"]
    text = (out / "noise_floor.md").read_text()
    assert "| comp_050 | 44 | 3.162 | 40 | 48 | 8 |" in text
    csv = pd.read_csv(out / "noise_floor.csv")
    assert len(csv) == 4
    # Nothing to measure: one clear line and a non-zero exit.
    single = tmp_path / "single"
    write_run(single, "tomb", "ours", 0, comp_050=1.0)
    assert noise_floor.main(["--summarise", str(single), "--out", str(tmp_path / "x")]) == 2
    assert "no cell has two successful repeats" in capsys.readouterr().err


def test_a_file_without_a_floor_is_refused(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"floor": {"comp_050": -1}}))
    with pytest.raises(ValueError, match="non-negative"):
        noise_floor.read_floor(bad)
    with pytest.raises(ValueError, match="not found"):
        noise_floor.read_floor(tmp_path / "missing.json")


def test_sweep_rebuilds_the_proxy_per_repeat_in_the_default_mode(tmp_path):
    command = noise_floor.sweep_command(5, tmp_path, ["scene=tomb", "planner=ours,lawnmower"])
    assert "+repeat=range(0,5)" in command and "reconstruct.deterministic=false" in command
    assert f"cache_dir={tmp_path.resolve()}/cache/rep${{repeat}}" in command
    with pytest.raises(ValueError, match="at least 2"):
        noise_floor.sweep_command(1, tmp_path, [])
    with pytest.raises(ValueError, match="sets cache_dir itself"):
        noise_floor.sweep_command(5, tmp_path, ["cache_dir=/tmp/c"])


def _runs(**by_planner) -> pd.DataFrame:
    rows = [
        {"scene": "tomb", "planner": p, "method": p, "seed": 0, "status": "ok", **m}
        for p, m in by_planner.items()
    ]
    return pd.DataFrame(rows)


def test_differences_below_the_floor_are_ties():
    runs = _runs(
        smith=dict(acc90_m=0.040, comp_050=40.0),
        yan=dict(acc90_m=0.034, comp_050=48.0),
        ours=dict(acc90_m=0.030, comp_050=50.0),
    )
    spec = {s.column: s for s in tables.TABLE_I}

    def best(floor):
        summary = tables.summarise(runs, [spec["acc90_m"], spec["comp_050"]], floor)
        return {m: set(g.loc[g["best"], "planner"]) for m, g in summary.groupby("metric")}

    assert best(None) == {"acc90_m": {"ours"}, "comp_050": {"ours"}}
    # comp 50 vs 48 under a 3-point floor: a tie; 40 is 10 points off: not.
    assert best({"comp_050": 3.0, "acc90_m": 0.005}) == {
        "acc90_m": {"ours", "yan"},
        "comp_050": {"ours", "yan"},
    }
    # A floor exactly as large as the difference is no tie (strictly smaller differences tie).
    assert best({"comp_050": 2.0, "acc90_m": 0.003})["comp_050"] == {"ours"}
    assert best({"comp_050": 2.0, "acc90_m": 0.003})["acc90_m"] == {"ours"}
    assert best({"comp_050": 10.5})["comp_050"] == {"ours", "yan", "smith"}


def test_tables_name_the_floor_they_used(tmp_path, repeats):
    runs_dir = tmp_path / "study"
    write_run(runs_dir, "tomb", "ours", 0, acc90_m=0.03, acc95_m=0.04, comp_050=50.0, comp_075=60.0)
    write_run(runs_dir, "tomb", "yan", 0, acc90_m=0.05, acc95_m=0.06, comp_050=45.0, comp_075=70.0)
    floor_dir = tmp_path / "floor"
    noise_floor.main(["--summarise", str(repeats), "--out", str(floor_dir)])
    out = tmp_path / "tables"
    code = tables.main(
        [str(runs_dir), "--out", str(out), "--noise-floor", str(floor_dir / "noise_floor.json")]
    )
    assert code == 0
    table1 = (out / "table1.md").read_text()
    # 50 vs 45 is inside the 8-point floor: both bold; 0.03 vs 0.05 is outside 0.004: ours alone.
    assert "**50.00**" in table1 and "**45.00**" in table1
    assert "**0.030**" in table1 and "**0.050**" not in table1
    assert "Comp. 0.050m (%) 8.00" in table1 and "Error 90% (m) 0.004" in table1
    assert "noise floor" in (out / "table1.tex").read_text()
    assert tables.main([str(runs_dir), "--out", str(out), "--noise-floor", str(tmp_path / "nope.json")]) == 2
