"""``uavplan stage``'s refusals: one line naming the problem and the command that fixes it, before
any work. (Each stage reproducing a kept run's files: tests/test_pipeline_smoke.py.)"""

from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.stages import main

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def kept_run(tmp_path: Path, *overrides: str) -> Path:
    """A run directory as ``uavplan run`` leaves it before any stage wrote: its composed config."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(config_name="config", overrides=["experiment=smoke", *overrides])
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    return run


def test_a_folder_that_is_no_run_is_refused(tmp_path, capsys):
    assert main(["dense", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: {tmp_path} is not a run directory of `uavplan run` (no .hydra/config.yaml)"


def test_a_missing_input_names_the_stage_that_writes_it(tmp_path, capsys):
    run = kept_run(tmp_path)
    assert main(["sfm", str(run)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {run / 'images'} is missing: run `uavplan stage render {run}` first"
    (run / "images").mkdir()
    assert main(["dense", str(run)]) == 1
    assert capsys.readouterr().err.strip().endswith(f"run `uavplan stage sfm {run}` first")
    assert main(["render", str(run)]) == 1
    assert capsys.readouterr().err.strip().endswith("is missing: run `uavplan run` first")


def test_a_bad_override_is_refused_with_the_settings_line(tmp_path, capsys):
    run = kept_run(tmp_path)
    assert main(["dense", str(run), "reconstruct.dense.num_partners=0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: reconstruct.dense.num_partners must be >= 1, got 0"
    assert main(["dense", str(run), "reconstruct.dense.num_partners"]) == 2
    assert "expected KEY=VALUE" in capsys.readouterr().err
    assert not (run / "recon").exists()


def test_the_plan_folder_gives_the_render_stage_the_planners_own_floats(tmp_path):
    """viewpoints.csv keeps 6 decimals; plan.json the views as planned, which ``read_plan`` returns
    while they agree with the CSV; a CSV edited by hand is taken as it reads."""
    import numpy as np

    from scene.plan import Plan, read_plan, write_plan

    rng = np.random.default_rng(0)
    views = np.column_stack(
        [
            rng.uniform(-50, 50, (7, 2)),
            rng.uniform(10, 40, 7),
            rng.uniform(-180, 180, 7),
            rng.uniform(-90, 0, 7),
        ]
    )
    write_plan(Plan(views, ["detail"] * 7, "test"), tmp_path)
    exact, kinds = read_plan(tmp_path)
    assert np.array_equal(exact, views) and kinds == ["detail"] * 7
    csv_path = tmp_path / "viewpoints.csv"
    lines = csv_path.read_text().splitlines()
    fields = lines[3].split(",")
    fields[3] = f"{float(fields[3]) + 1.5:.6f}"  # view 2 one and a half metres higher
    lines[3] = ",".join(fields)
    csv_path.write_text("\n".join(lines) + "\n")
    edited, _ = read_plan(tmp_path)
    assert edited[2, 2] == round(views[2, 2] + 1.5, 6)
    assert np.abs(edited - views).max() == np.abs(edited[2, 2] - views[2, 2])
