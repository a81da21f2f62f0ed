"""The results command regenerates a study's committed tables from its cell records alone, exactly."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.results import HEADLINE_BEGIN, HEADLINE_END, main, splice_headline, write_study

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


def test_the_fixture_headline_row_holds_the_seed_means_per_budget(regenerated):
    """Tomb / ours: 150, 215 (mean of three seeds), 390 images; 66.0, 78.07, 84.0 % at 5 cm."""
    tmp_path, _ = regenerated
    rows = (tmp_path / "fixture" / "headline.md").read_text().splitlines()
    ours = next(r for r in rows if r.startswith("| Tomb | Ours |"))
    cells = [c.strip() for c in ours.strip("|").split("|")]
    assert cells[2:6] == ["low / default / high", "1 / 3 / 1", "150 / 215 / 390", "66.0 / 78.1 / 84.0"]


def test_the_headline_is_spliced_between_the_markers_and_nothing_else_changes():
    readme = f"# Title\n\nBefore.\n\n{HEADLINE_BEGIN}\n| old |\n| row |\n{HEADLINE_END}\n\nAfter.\n"
    spliced = splice_headline(readme, "| new |\n")
    assert spliced == f"# Title\n\nBefore.\n\n{HEADLINE_BEGIN}\n| new |\n{HEADLINE_END}\n\nAfter.\n"
    assert splice_headline(spliced, "| new |\n") == spliced
    with pytest.raises(ValueError, match="no '<!-- headline table"):
        splice_headline("# Title\n| old |\n", "| new |\n")


def test_a_readme_without_markers_is_one_line_and_left_as_it_was(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text("# No markers here\n")
    cells = FIXTURE / "cells"
    assert main(["fixture", "--cells", str(cells), "--out", str(tmp_path), "--readme", str(readme)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: --readme {readme}: the README has no")
    assert readme.read_text() == "# No markers here\n"
    assert not (tmp_path / "fixture").exists()  # nothing of the study was written either


def test_the_repository_readme_shows_the_committed_study_headline():
    """The README's headline table is the one `experiments.results study` wrote from the records."""
    root = Path(__file__).resolve().parents[1]
    headline = (root / "results" / "study" / "headline.md").read_text()
    readme = (root / "README.md").read_text()
    assert splice_headline(readme, headline) == readme
