"""Tables I and II from run directories with known metrics: numbers, bolding, seeds, failures, CSV."""

from __future__ import annotations

import math
import os
import shutil
import subprocess

import numpy as np
import pytest

from experiments import tables
from experiments.runs import RunDirectoryError, load_runs
from tests.experiments_fixtures import write_run

PAPER_TOMB = {  # the paper's Table I and II values for Tomb (align time stored in seconds)
    "smith": dict(
        acc90_m=0.266, acc95_m=0.389, comp_050=18.92, comp_075=27.47, n_images=322, align_time_s=46.2
    ),
    "yan": dict(
        acc90_m=0.238, acc95_m=0.281, comp_050=24.29, comp_075=35.61, n_images=3795, align_time_s=10440.0
    ),
}
OURS_TOMB_SEEDS = [  # three seeds of ours on Tomb
    dict(acc90_m=0.190, acc95_m=0.240, comp_050=31.0, comp_075=42.0, n_images=290, align_time_s=45.0),
    dict(acc90_m=0.200, acc95_m=0.250, comp_050=32.0, comp_075=43.0, n_images=292, align_time_s=48.0),
    dict(acc90_m=0.210, acc95_m=0.260, comp_050=33.0, comp_075=44.0, n_images=294, align_time_s=51.0),
]


@pytest.fixture
def study(tmp_path):
    root = tmp_path / "multirun" / "2026-11-23_06-00-00"
    for planner, metrics in PAPER_TOMB.items():
        write_run(root, "tomb", planner, 0, **metrics)
    for seed, metrics in enumerate(OURS_TOMB_SEEDS):
        write_run(root, "tomb", "ours", seed, **metrics)
    # Church: smith succeeds, yan succeeds, ours fails on seed 0 and succeeds on seed 1.
    write_run(
        root,
        "church",
        "smith",
        0,
        acc90_m=0.115,
        acc95_m=0.139,
        comp_050=51.97,
        comp_075=61.66,
        n_images=874,
        align_time_s=96.6,
    )
    write_run(
        root,
        "church",
        "yan",
        0,
        acc90_m=0.1152,
        acc95_m=0.145,
        comp_050=59.39,
        comp_075=69.92,
        n_images=3441,
        align_time_s=1150.8,
    )
    write_run(
        root, "church", "ours", 0, status="failed", error="PlanningError: no viewpoint sees the roof_1 & 50%"
    )
    write_run(
        root,
        "church",
        "ours",
        1,
        acc90_m=0.093,
        acc95_m=0.118,
        comp_050=57.23,
        comp_075=70.95,
        n_images=419,
        align_time_s=66.0,
    )
    # A user scene sorts after the paper's; its only method failed on both seeds.
    write_run(root, "bridge", "lawnmower", 0, status="failed", error="RuntimeError: SfM registered 2 images")
    write_run(root, "bridge", "lawnmower", 1, status="failed", error="RuntimeError: SfM registered 2 images")
    return root


def cell(summary, scene, planner, metric):
    rows = summary[(summary.scene == scene) & (summary.planner == planner) & (summary.metric == metric)]
    assert len(rows) == 1
    return rows.iloc[0]


def test_table_numbers_and_seed_statistics(study):
    built = tables.build_tables([study])
    t1, t2 = built["table1"], built["table2"]
    assert cell(t1, "tomb", "smith", "acc90_m")["mean"] == pytest.approx(0.266)
    assert math.isnan(cell(t1, "tomb", "smith", "acc90_m")["std"])
    ours = cell(t1, "tomb", "ours", "comp_075")
    assert ours["mean"] == pytest.approx(43.0) and ours["std"] == pytest.approx(1.0) and ours["n"] == 3
    acc = cell(t1, "tomb", "ours", "acc95_m")
    assert acc["mean"] == pytest.approx(0.25) and acc["std"] == pytest.approx(
        np.std([0.24, 0.25, 0.26], ddof=1)
    )
    # Table II shows minutes.
    assert cell(t2, "tomb", "yan", "align_time_s")["mean"] == pytest.approx(174.0)
    assert cell(t2, "tomb", "ours", "align_time_s")["mean"] == pytest.approx(48.0 / 60.0)
    assert cell(t2, "tomb", "ours", "n_images")["mean"] == pytest.approx(292.0)
    assert cell(t2, "tomb", "ours", "n_images")["std"] == pytest.approx(2.0)
    # Order: paper scenes first, then others; baselines first, ours last.
    order = t1.drop_duplicates(["scene", "planner"])[["scene", "planner"]].values.tolist()
    assert order == [
        ["tomb", "smith"],
        ["tomb", "yan"],
        ["tomb", "ours"],
        ["church", "smith"],
        ["church", "yan"],
        ["church", "ours"],
        ["bridge", "lawnmower"],
    ]
    assert set(t1.method) == {"Smith et al.", "Yan et al.", "Ours", "Lawnmower"}


def test_bolding_marks_best_shown_value_per_scene_and_metric(study):
    t1 = tables.build_tables([study])["table1"]
    best = {(r.scene, r.metric): r.planner for r in t1[t1.best].itertuples() if r.scene == "tomb"}
    assert best == {
        ("tomb", "acc90_m"): "ours",
        ("tomb", "acc95_m"): "ours",
        ("tomb", "comp_050"): "ours",
        ("tomb", "comp_075"): "ours",
    }
    church = t1[(t1.scene == "church") & t1.best]
    # Lower error: ours 0.093; higher completeness at 0.050: yan 59.39; at 0.075: ours 70.95.
    assert sorted(zip(church.metric, church.planner, strict=True)) == [
        ("acc90_m", "ours"),
        ("acc95_m", "ours"),
        ("comp_050", "yan"),
        ("comp_075", "ours"),
    ]
    # A scene whose only method failed has nothing to bold.
    assert not t1[t1.scene == "bridge"].best.any()


def test_bolding_ties_at_shown_precision(tmp_path):
    write_run(tmp_path, "tomb", "smith", 0, acc90_m=0.1151, acc95_m=0.2, comp_050=1.0, comp_075=2.0)
    write_run(tmp_path, "tomb", "yan", 0, acc90_m=0.1149, acc95_m=0.3, comp_050=1.0, comp_075=2.5)
    t1 = tables.build_tables([tmp_path])["table1"]
    assert set(t1[t1.best & (t1.metric == "acc90_m")].planner) == {"smith", "yan"}  # both show 0.115
    assert set(t1[t1.best & (t1.metric == "comp_050")].planner) == {"smith", "yan"}
    assert set(t1[t1.best & (t1.metric == "comp_075")].planner) == {"yan"}


def test_failed_cells_and_footnotes(study):
    built = tables.build_tables([study])
    t1 = built["table1"]
    church = cell(t1, "church", "ours", "acc90_m")
    assert church["n"] == 1 and church["n_runs"] == 2 and church["n_failed"] == 1
    assert church["mean"] == pytest.approx(0.093)
    assert church["errors"] == "seed 0: PlanningError: no viewpoint sees the roof_1 & 50%"
    bridge = cell(t1, "bridge", "lawnmower", "comp_050")
    assert bridge["n"] == 0 and math.isnan(bridge["mean"])
    assert bridge["errors"] == "seeds 0, 1: RuntimeError: SfM registered 2 images"

    md = tables.to_markdown(t1, tables.TABLE_I)
    bridge_line = next(line for line in md.splitlines() if line.startswith("| Bridge"))
    assert bridge_line.count("| failed") == len(tables.TABLE_I) == 6
    assert "(b) Lawnmower on Bridge: seeds 0, 1: RuntimeError: SfM registered 2 images" in md
    assert "(a) Ours on Church: seed 0: PlanningError" in md
    tex = tables.to_latex(t1, tables.TABLE_I, "cap", "tab:x")
    assert r"roof\_1 \& 50\%" in tex  # the error is escaped for LaTeX
    assert r"Ours\textsuperscript{a}" in tex


def test_markdown_and_latex_render_the_numbers(study):
    t1 = tables.build_tables([study])["table1"]
    md = tables.to_markdown(t1, tables.TABLE_I)
    tomb_ours = next(line for line in md.splitlines() if "| Ours |" in line and "0.200" in line)
    cells = [c.strip() for c in tomb_ours.strip("|").split("|")]
    assert cells == [
        "",
        "Ours",
        "3",
        "**0.200 ± 0.010**",
        "**0.250 ± 0.010**",
        "**32.00 ± 1.00**",
        "**43.00 ± 1.00**",
        "n/a",  # walls and the oracle: not recorded by these cells
        "n/a",
    ]
    tex = tables.to_latex(t1, tables.TABLE_I, tables.TABLE_I_CAPTION, "tab:recon_results")
    assert r"\multirow{3}{*}{Tomb}" in tex and r"\toprule" in tex and r"\bottomrule" in tex
    assert r"& Smith et al.~\cite{Smith2018} & 1 & 0.266 & 0.389 & 18.92 & 27.47 & n/a & n/a \\" in tex
    assert r"\textbf{0.200 $\pm$ 0.010}" in tex
    assert tex.count(r"\midrule") == 3  # one per scene
    t2 = tables.build_tables([study])["table2"]
    tex2 = tables.to_latex(t2, tables.TABLE_II, tables.TABLE_II_CAPTION, "tab:align_results")
    # The paper's values have no flight time, batteries, CPU or dense time: n/a, never 0.
    assert r"& Yan et al.~\cite{Yan2021} & 1 & 3,795 & n/a & n/a & 174.00 & n/a & n/a & n/a \\" in tex2
    assert r"\textbf" not in tex2  # Table II has no "best"


def test_cli_writes_files_and_csv_round_trips(study, tmp_path, capsys):
    out = tmp_path / "tables"
    assert tables.main([str(study), "--out", str(out)]) == 0
    assert "11 runs (3 failed)" in capsys.readouterr().out
    names = {p.name for p in out.iterdir()}
    assert {
        "table1.md",
        "table1.tex",
        "table1.csv",
        "table2.md",
        "table2.tex",
        "table2.csv",
        "tables.md",
        "surfaces.md",
        "surfaces.tex",
        "surfaces.csv",
        "all_metrics.csv",
        "runs.csv",
    } <= names
    assert not [n for n in names if n.startswith(".")]  # no temporary file left behind
    built = tables.build_tables([study])
    for name in ("table1", "table2", "all_metrics"):
        back = tables.read_summary_csv(out / f"{name}.csv")
        expected = built[name].reset_index(drop=True)
        assert back[["scene", "planner", "metric", "errors"]].equals(
            expected[["scene", "planner", "metric", "errors"]]
        )
        np.testing.assert_allclose(back["mean"], expected["mean"], rtol=0, atol=0)
        np.testing.assert_allclose(back["std"], expected["std"], rtol=0, atol=0)
        assert (back["best"] == expected["best"]).all() and (back["n"] == expected["n"]).all()
    allm = tables.read_summary_csv(out / "all_metrics.csv")
    assert cell(allm, "tomb", "ours", "align_time_s")["mean"] == pytest.approx(48.0)


def test_surface_table_shows_where_each_method_covers(tmp_path):
    root = tmp_path / "multirun"
    per_class = {
        "lawnmower": dict(comp_050_ground=80.0, comp_050_roofs=70.0, comp_050_walls=20.0),
        "ours": dict(comp_050_ground=60.0, comp_050_roofs=65.0, comp_050_walls=45.5),
    }
    for planner, values in per_class.items():
        write_run(root, "tomb", planner, 0, comp_050_undersides=5.0, **values)
    surfaces = tables.build_tables([root])["surfaces"]
    assert cell(surfaces, "tomb", "ours", "comp_050_walls")["mean"] == 45.5
    assert cell(surfaces, "tomb", "ours", "comp_050_walls")["best"]
    assert cell(surfaces, "tomb", "lawnmower", "comp_050_ground")["best"]
    assert not cell(surfaces, "tomb", "ours", "comp_050_ground")["best"]
    assert cell(surfaces, "tomb", "ours", "comp_050_undersides")["best"]  # a tie marks both
    markdown = tables.to_markdown(surfaces, tables.TABLE_SURFACES)
    assert "| Walls 0.050m (%) |" in markdown and "**45.50**" in markdown


def test_several_directories_and_reruns(study, tmp_path):
    other = tmp_path / "outputs"
    write_run(
        other,
        "cathedral",
        "ours",
        0,
        acc90_m=0.198,
        acc95_m=0.366,
        comp_050=36.88,
        comp_075=49.87,
        n_images=828,
        align_time_s=169.8,
    )
    # The same (scene, planner, seed) again: the newer record replaces the older one.
    rerun = write_run(
        other,
        "tomb",
        "smith",
        0,
        acc90_m=0.3,
        acc95_m=0.4,
        comp_050=10.0,
        comp_075=20.0,
        n_images=300,
        align_time_s=60.0,
    )
    older = (study / "tomb" / "smith" / "seed0" / "metrics.json").stat().st_mtime
    os.utime(rerun / "metrics.json", (older + 10.0, older + 10.0))
    runs = load_runs([study, other])
    assert len(runs) == 12
    t1 = tables.build_tables([study, other])["table1"]
    assert cell(t1, "cathedral", "ours", "acc95_m")["mean"] == pytest.approx(0.366)
    assert cell(t1, "tomb", "smith", "acc90_m")["mean"] == pytest.approx(0.3)
    assert [r.run_dir for r in runs if (r.scene, r.planner) == ("tomb", "smith")] == [rerun.resolve()]


def test_tables_name_the_code_revisions_of_the_runs(tmp_path, caplog):
    same = tmp_path / "same"
    for planner in ("ours", "smith"):
        write_run(same, "tomb", planner, 0, acc90_m=0.1, code_commit="a" * 40, code_dirty=False)
    text, uncertain = tables.code_provenance(tables.build_tables([same])["runs"])
    assert (text, uncertain) == ("**Code.** All 2 runs: revision aaaaaaaaaa.\n", False)

    mixed = tmp_path / "mixed"
    write_run(mixed, "tomb", "ours", 0, acc90_m=0.1, code_commit="a" * 40, code_dirty=False)
    write_run(mixed, "tomb", "smith", 0, acc90_m=0.1, code_commit="b" * 40, code_dirty=True)
    write_run(mixed, "church", "ours", 0, acc90_m=0.1)  # written before revisions were recorded
    out = tmp_path / "out"
    assert tables.main([str(mixed), "--out", str(out)]) == 0
    paragraph = (out / "tables.md").read_text().strip().splitlines()[-1]
    assert paragraph == (
        "**Code.** The runs come from 3 revisions: "
        "bbbbbbbbbb with uncommitted changes (1: Tomb Smith et al.); "
        "aaaaaaaaaa (1: Tomb Ours); unrecorded (1: Church Ours). "
        "Differences between these cells may come from the code as well as the planners."
    )
    assert "The runs come from 3 revisions" in caplog.text

    # A revision holding most cells comes first and is named by the cells it lacks; seeds merge.
    study = tmp_path / "study"
    for seed in (0, 1, 2):
        write_run(study, "tomb", "ours", seed, acc90_m=0.1, code_commit="a" * 40, code_dirty=False)
        write_run(study, "tomb", "lawnmower", seed, acc90_m=0.1, code_commit="a" * 40, code_dirty=False)
    for seed in (0, 2):
        write_run(study, "church", "smith", seed, acc90_m=0.1, code_commit="b" * 40, code_dirty=False)
    write_run(study, "church", "ours", 1, acc90_m=0.1, code_commit="b" * 40, code_dirty=False)
    text, uncertain = tables.code_provenance(tables.build_tables([study])["runs"])
    assert uncertain
    assert text.startswith(
        "**Code.** The runs come from 2 revisions: aaaaaaaaaa (6: every cell not named here); "
        "bbbbbbbbbb (3: Church "
    )
    assert "Church Smith et al. seeds 0/2" in text and "Church Ours seed 1" in text
    every = tables._cell_names(tables.build_tables([study])["runs"], True).split(", ")
    assert sorted(every) == sorted(
        [
            "Tomb Ours seeds 0-2",
            "Tomb Lawnmower seeds 0-2",
            "Church Smith et al. seeds 0/2",
            "Church Ours seed 1",
        ]
    )


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert tables.main([str(empty), "--out", str(tmp_path / "out")]) == 2
    assert f"no run found under {empty}" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(RunDirectoryError, match="not found"):
        load_runs([tmp_path / "missing"])
    broken = tmp_path / "broken" / "run"
    broken.mkdir(parents=True)
    (broken / "metrics.json").write_text("{not json")
    with pytest.raises(RunDirectoryError, match="metrics.json: not valid JSON"):
        load_runs([broken.parent])


def test_a_run_that_never_finished_counts_as_failed(tmp_path):
    write_run(tmp_path, "tomb", "ours", 0, status="running", acc90_m=0.5)
    write_run(tmp_path, "tomb", "smith", 0, acc90_m=0.3, acc95_m=0.4, comp_050=10.0, comp_075=20.0)
    t1 = tables.build_tables([tmp_path])["table1"]
    ours = cell(t1, "tomb", "ours", "acc90_m")
    assert ours["n"] == 0 and ours["n_failed"] == 1
    assert ours["errors"] == "seed 0: run ended with status 'running'"
    assert not t1.best.any()  # one method with values: nothing to compare


@pytest.mark.skipif(shutil.which("pdflatex") is None, reason="pdflatex not installed")
def test_latex_tables_compile(study, tmp_path):
    out = tmp_path / "tables"
    tables.write_tables(tables.build_tables([study]), out)
    doc = tmp_path / "doc.tex"
    doc.write_text(
        "\\documentclass{article}\n\\usepackage{booktabs,multirow,makecell}\n\\begin{document}\n"
        f"\\input{{{out / 'table1.tex'}}}\n\\input{{{out / 'table2.tex'}}}\n\\end{{document}}\n"
    )
    result = subprocess.run(
        ["pdflatex", "-interaction=nonstopmode", "-halt-on-error", doc.name],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout[-2000:]
    assert (tmp_path / "doc.pdf").read_bytes()[:4] == b"%PDF"


def test_ablation_variants_of_ours_get_their_own_table(tmp_path):
    root = tmp_path / "ablation"
    common = dict(acc90_m=0.03, acc95_m=0.04, comp_050=40.0, comp_075=50.0, n_images=150)
    write_run(root, "tomb", "ours", 0, **common, comp_050_walls=35.0, predicted_well_observed_walls_pct=90.0)
    write_run(
        root,
        "tomb",
        "ours_literal_score",
        0,
        **common,
        comp_050_walls=12.5,
        predicted_well_observed_walls_pct=31.0,
    )
    write_run(root, "tomb", "yan", 0, **common, comp_050_walls=50.0, predicted_well_observed_walls_pct=75.0)
    write_run(
        root, "tomb", "ours_plus", 0, **common, comp_050_walls=36.0, predicted_well_observed_walls_pct=91.0
    )
    built = tables.build_tables([root])
    ablation = built["ablation"]
    # neither the baselines nor ours_plus (a method of its own) are variants
    assert set(ablation["planner"]) == {"ours", "ours_literal_score"}
    assert (
        "ours_plain_overlap" in tables.ablation_planners() and "ours_plus" not in tables.ablation_planners()
    )
    walls = ablation[ablation["metric"] == "comp_050_walls"].set_index("planner")
    assert walls.loc["ours", "mean"] == 35.0 and walls.loc["ours", "best"]
    assert not walls.loc["ours_literal_score", "best"]
    out = tmp_path / "tables"
    tables.write_tables(built, out)
    text = (out / "ablation.md").read_text()
    assert "| Tomb | Ours Literal Score | 150 |" in text and "**35.00**" in text
    assert "Ablation of ours" in (out / "tables.md").read_text()
    # Without variants there is no ablation table.
    assert "ablation" not in tables.build_tables([root / "tomb" / "yan"])
