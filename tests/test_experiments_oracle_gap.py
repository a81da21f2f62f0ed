"""The oracle-gap tool on cells with known real and oracle values: Spearman's rho by hand."""

from __future__ import annotations

import pytest

from experiments.oracle_gap import main
from tests.experiments_fixtures import write_run

PLANNERS = ("lawnmower", "smith", "yan", "ours")
REAL_COMP = (50.0, 60.0, 70.0, 80.0)
ORACLE_COMP = (90.0, 85.0, 95.0, 99.0)  # ranks 2 1 3 4 against 1 2 3 4: rho = 1 - 6 x 2 / 60 = 0.8
REAL_ACC = (0.03, 0.04, 0.05, 0.06)
ORACLE_ACC = (0.010, 0.015, 0.020, 0.012)  # ranks 1 3 4 2: sum d^2 = 6, rho = 1 - 36 / 60 = 0.4


def write_cells(root, with_oracle=True):
    for k, planner in enumerate(PLANNERS):
        oracle = {"oracle_comp_050": ORACLE_COMP[k], "oracle_acc90_m": ORACLE_ACC[k]} if with_oracle else {}
        write_run(
            root, "tomb", planner, 0, n_images=100 + k, comp_050=REAL_COMP[k], acc90_m=REAL_ACC[k], **oracle
        )


def test_rank_correlation_and_largest_gaps_match_the_hand_values(tmp_path, capsys):
    write_cells(tmp_path / "runs")
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "Spearman rho 0.80" in printed
    assert "largest shortfall 40.0 points (tomb / Lawnmower / seed 0)" in printed
    assert "acc90: rho 0.40; largest excess 4.80 cm (tomb / Ours / seed 0)" in printed
    assert (tmp_path / "out" / "oracle_gap.md").read_text().endswith(printed)
    rows = (tmp_path / "out" / "oracle_gap.csv").read_text().splitlines()
    assert len(rows) == 1 + len(PLANNERS)


@pytest.mark.parametrize(
    ("with_oracle", "named"),
    [(False, "oracle_comp_050"), (True, "a rank correlation needs 3")],
)
def test_cells_without_an_oracle_or_too_few_are_refused(tmp_path, capsys, with_oracle, named):
    if with_oracle:
        write_run(
            tmp_path / "runs",
            "tomb",
            "ours",
            0,
            comp_050=1.0,
            acc90_m=0.1,
            oracle_comp_050=2.0,
            oracle_acc90_m=0.05,
        )
    else:
        write_cells(tmp_path / "runs", with_oracle=False)
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 2
    assert named in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
