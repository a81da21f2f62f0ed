"""The results command regenerates a study's committed tables from its cell records alone, exactly."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.results import main, write_study

FIXTURE = Path(__file__).resolve().parent / "data" / "results_study"
TEXT_SUFFIXES = {".md", ".csv", ".tex"}


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory) -> tuple[Path, list[Path]]:
    out = tmp_path_factory.mktemp("results")
    return out, write_study("fixture", FIXTURE / "cells", out)


def test_a_fixture_study_reproduces_its_committed_tables_byte_for_byte(regenerated):
    tmp_path, written = regenerated
    expected_dir = FIXTURE / "expected" / "fixture"
    expected = sorted(p.relative_to(expected_dir) for p in expected_dir.rglob("*") if p.is_file())
    produced = sorted(p.relative_to(tmp_path / "fixture") for p in written)
    assert produced == expected
    for rel in expected:
        if rel.suffix in TEXT_SUFFIXES:
            assert (tmp_path / "fixture" / rel).read_text() == (expected_dir / rel).read_text(), rel
        else:  # figures: written, and not empty
            assert (tmp_path / "fixture" / rel).stat().st_size > 10_000, rel


def test_the_fixture_front_numbers_are_the_hand_computed_ones(regenerated):
    """Tomb / ours: budgets at (150, 66 %), (215, 78.07 %: three seeds), (390, 84 %)."""
    import pandas as pd

    tmp_path, _ = regenerated
    fronts = pd.read_csv(tmp_path / "fixture" / "fronts.csv")
    ours = fronts[(fronts["scene"] == "tomb") & (fronts["planner"] == "ours")].iloc[0]
    assert ours["images_to_70"] == pytest.approx(150 + (70 - 66) / (78.0666667 - 66) * 65, rel=1e-6)
    assert bool(ours["images_to_60_at_most"]) and ours["images_to_60"] == 150
    church = fronts[(fronts["scene"] == "church") & (fronts["planner"] == "ours")].iloc[0]
    assert church["budgets"] == 2  # the failed low-budget cell is not a point of the front


def test_a_missing_study_is_one_line_and_a_non_zero_exit(tmp_path, capsys):
    assert main(["nothing", "--cells", str(FIXTURE / "cells"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: study nothing: run directory not found")
    assert not (tmp_path / "nothing").exists()
