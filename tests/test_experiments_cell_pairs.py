"""Cells recorded twice, paired by scene, planner, seed, budget and GSD, with hand-computed differences."""

from __future__ import annotations

from experiments.cell_pairs import main
from tests.experiments_fixtures import write_run


def test_cells_pair_on_their_keys_and_the_largest_difference_is_named(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    write_run(
        a, "tomb", "ours", 0, budget="lowest", target_gsd_m=0.03, n_images=100, comp_050=60.9, acc90_m=0.021
    )
    write_run(
        a, "tomb", "smith", 0, budget="lowest", target_gsd_m=0.03, n_images=73, comp_050=79.1, acc90_m=0.026
    )
    write_run(a, "tomb", "yan", 0, target_gsd_m=0.03, n_images=400, comp_050=70.0, acc90_m=0.04)  # only in a
    write_run(
        b, "tomb", "ours", 0, budget="lowest", target_gsd_m=0.03, n_images=100, comp_050=66.4, acc90_m=0.0261
    )
    write_run(
        b, "tomb", "smith", 0, budget="lowest", target_gsd_m=0.03, n_images=73, comp_050=74.2, acc90_m=0.0252
    )
    # the same planner and budget at another GSD is another cell
    write_run(
        b, "tomb", "smith", 1, budget="lowest", target_gsd_m=0.045, n_images=50, comp_050=1.0, acc90_m=0.1
    )
    assert main([str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert "| tomb / Ours (lowest budget) | 0 | 100 / 100 | 60.9 / 66.4 | 2.10 / 2.61 |" in printed
    assert "| tomb / Smith et al. (lowest budget) | 0 | 73 / 73 | 79.1 / 74.2 | 2.60 / 2.52 |" in printed
    assert "- comp. 5 cm (%): 5.5 (tomb / Ours (lowest budget))" in printed
    assert "- acc90 (cm): 0.51 (tomb / Ours (lowest budget))" in printed
    assert len((tmp_path / "out" / "cell_pairs.csv").read_text().splitlines()) == 1 + 2


def test_folders_without_a_common_cell_are_refused(tmp_path, capsys):
    write_run(tmp_path / "a", "tomb", "ours", 0, n_images=100, comp_050=60.0, acc90_m=0.02)
    write_run(tmp_path / "b", "church", "ours", 0, n_images=100, comp_050=60.0, acc90_m=0.02)
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "out")]) == 2
    assert "no cell is recorded in both folders" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
