"""The results command regenerates a study's committed tables from its cell records alone, exactly."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from experiments.results import (
    HEADLINE_BEGIN,
    HEADLINE_END,
    main,
    revision_lineage,
    splice_headline,
    write_study,
)

FIXTURE = Path(__file__).resolve().parent / "data" / "results_study"
CURRENT = {"protocol": 1, "planner_version": 1}
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


def test_only_the_current_protocol_and_planner_versions_are_read(regenerated):
    """The fixture holds two stale records: a Smith cell of protocol 0 (99 % at 999 images) and an
    ours cell of planner version 0; neither is in a table, a front or the cell list."""
    import pandas as pd

    tmp_path, _ = regenerated
    cells = pd.read_csv(tmp_path / "fixture" / "cells.csv")
    assert len(cells) == 18 and set(cells["protocol"]) == {1} and set(cells["planner_version"]) == {1}
    assert "smith" not in set(cells["planner"]) and 1.0 not in set(cells["comp_050"])
    assert "| Smith" not in (tmp_path / "fixture" / "headline.md").read_text()
    assert "2 records of other protocols" in (tmp_path / "fixture" / "README.md").read_text()


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


def test_revision_lineage_names_the_newest_revision_and_the_files_it_changes(tmp_path):
    """Cells of a base commit and of a fix on top of it: the fix contains the base and changes one
    file; a commit on a side branch descends from neither, so the lineage is unknown."""
    repo = tmp_path / "repo"
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(["git", "init", "-q", "-b", "main", str(repo)], check=True)

    def commit(path: str, text: str) -> str:
        (repo / path).parent.mkdir(parents=True, exist_ok=True)
        (repo / path).write_text(text)
        subprocess.run([*git, "add", path], check=True)
        subprocess.run([*git, "commit", "-qm", path], check=True)
        return subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()

    base = commit("planner/a.py", "x = 1\n")
    commit("planner/b.py", "y = 1\n")
    fix = commit("planner/b.py", "y = 2\n")
    assert revision_lineage([base, fix], repo=repo) == (fix, {base: ["planner/b.py"]})
    assert revision_lineage([fix, base], repo=repo) == (fix, {base: ["planner/b.py"]})
    subprocess.run([*git, "checkout", "-q", "-b", "side", base], check=True)
    side = commit("planner/c.py", "z = 1\n")
    assert revision_lineage([fix, side], repo=repo) is None
    assert revision_lineage([base, "0" * 40], repo=repo) is None  # a commit the repository lacks


def test_the_study_cost_sums_each_planners_cell_hours_per_scene():
    import pandas as pd

    from experiments.results import study_cost

    runs = pd.DataFrame(
        {
            "scene": ["tomb", "tomb", "church", "tomb"],
            "planner": ["ours", "ours", "ours", "yan"],
            "cell_wall_time_s": [1800.0, 3600.0, 900.0, 7200.0],
            "cell_cpu_time_s": [3600.0, 7200.0, 1800.0, float("nan")],
        }
    )
    lines = study_cost(runs)
    assert lines[0].startswith("**Cost.** 3.8 cell-hours of wall time (3.5 h CPU)")
    assert lines[4:6] == ["| yan | 2.0 | – |", "| ours | 1.5 (3.0) | 0.2 (0.5) |"]
    assert study_cost(runs.drop(columns="cell_wall_time_s")) == []


def test_a_studys_noise_floor_comes_from_its_repeats(tmp_path):
    from experiments.results import study_noise_floor
    from tests.experiments_fixtures import write_run

    noise = tmp_path / "settled_noise"
    assert study_noise_floor(noise) is None  # no repeats yet: no floor, exact ties only
    for repeat, (comp, acc) in enumerate([(80.0, 0.020), (77.5, 0.023), (79.0, 0.021)]):
        write_run(noise / f"rep{repeat}", "church", "ours", 0, comp_050=comp, acc90_m=acc, **CURRENT)
    write_run(noise / "rep0", "church", "smith", 0, comp_050=70.0, acc90_m=0.03, **CURRENT)
    write_run(noise / "rep1", "church", "smith", 0, comp_050=73.0, acc90_m=0.03, **CURRENT)
    # a repeat of another protocol is not part of the floor
    old = {"protocol": 0, "planner_version": 1}
    write_run(noise / "rep2", "church", "smith", 0, comp_050=50.0, acc90_m=0.03, **old)
    floor = study_noise_floor(noise)
    assert floor["comp_050"] == pytest.approx(3.0)  # Smith's range; ours' is 2.5
    assert floor["acc90_m"] == pytest.approx(0.003)
