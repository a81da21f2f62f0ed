"""Image budget levels: ``budget=<level>`` sets a planner's knob, names its value, refuses what is unknown."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from planner.budget import apply_budget, level_rank

ROOT = Path(__file__).resolve().parents[1]

CONFIG = {
    "name": "toy",
    "_target_": "toy.plan",
    "front_overlap": 0.8,
    "side_overlap": 0.8,
    "heuristics": {"k_count": 3},
    "budget": {"knob": ["front_overlap", "side_overlap"], "levels": {"low": 0.7, "highest": 0.9}},
}


def test_a_level_sets_every_knob_path_and_drops_the_budget_block():
    params, record = apply_budget(CONFIG, "highest", "toy")
    assert params == {
        "name": "toy",
        "_target_": "toy.plan",
        "front_overlap": 0.9,
        "side_overlap": 0.9,
        "heuristics": {"k_count": 3},
    }
    assert record == {"budget": "highest", "budget_knob": "front_overlap,side_overlap", "budget_value": 0.9}
    assert CONFIG["front_overlap"] == 0.8  # the config itself is left as it was


def test_default_is_the_config_as_it_is_and_a_nested_knob_works():
    nested = {**CONFIG, "budget": {"knob": "heuristics.k_count", "levels": {"high": 5}}}
    params, record = apply_budget(nested, "default", "toy")
    assert params["heuristics"]["k_count"] == 3 and record["budget_value"] == 3
    assert apply_budget(nested, "high", "toy")[0]["heuristics"]["k_count"] == 5


def test_levels_are_ordered_fewest_images_first():
    assert [level_rank(x) for x in ("lowest", "low", "mid", "default", "high", "highest")] == [
        0,
        1,
        2,
        3,
        4,
        5,
    ]


def test_a_level_may_give_each_knob_path_its_own_value():
    knob = ["front_overlap", "heuristics.k_count"]
    config = {
        **CONFIG,
        "budget": {"knob": knob, "levels": {"high": {"front_overlap": 0.85, "heuristics.k_count": 6}}},
    }
    params, record = apply_budget(config, "high", "toy")
    assert params["front_overlap"] == 0.85 and params["heuristics"]["k_count"] == 6
    assert params["side_overlap"] == 0.8
    assert record == {
        "budget": "high",
        "budget_knob": "front_overlap,heuristics.k_count",
        "budget_value": 0.85,
    }
    partial = {**CONFIG, "budget": {"knob": knob, "levels": {"high": {"front_overlap": 0.85}}}}
    with pytest.raises(ValueError, match=r"budget level 'high' sets \['front_overlap'\], its knob is"):
        apply_budget(partial, "default", "toy")


@pytest.mark.parametrize(
    ("config", "level", "message"),
    [
        (CONFIG, "medium", "budget must be one of lowest, low, mid, default, high, highest, got 'medium'"),
        (CONFIG, "high", r"planner toy has no budget level 'high' \(its levels: low, default, highest\)"),
        ({**CONFIG, "budget": {"knob": "k_count", "levels": {"low": 2}}}, "low", "'k_count' is not one of"),
        ({k: v for k, v in CONFIG.items() if k != "budget"}, "low", "planner toy has no budget knob"),
    ],
)
def test_bad_budgets_are_refused_by_name(config, level, message):
    with pytest.raises(ValueError, match=message):
        apply_budget(config, level, "toy")


def test_run_passes_the_level_to_the_planner_and_records_it():
    from hydra import compose, initialize_config_dir

    from pipeline.settings import planner_setup

    with initialize_config_dir(config_dir=os.fspath(ROOT / "conf"), version_base=None):
        cfg = compose("config", overrides=["planner=yan", "budget=low"])
        params, record = planner_setup(cfg)
        assert params.n_samples == 1000 and "budget" not in params and "version" not in params
        assert record == {
            "budget": "low",
            "budget_knob": "n_samples",
            "budget_value": 1000,
            "planner_version": 1,
        }


def test_the_budgets_preset_sweeps_levels_every_planner_defines():
    import yaml
    from hydra import compose, initialize_config_dir

    from pipeline.settings import planner_setup

    sweep = yaml.safe_load((ROOT / "conf" / "experiment" / "budgets.yaml").read_text())["hydra"]["sweeper"]
    planners, levels = (sweep["params"][k].split(",") for k in ("planner", "budget"))
    assert len(levels) >= 3
    with initialize_config_dir(config_dir=os.fspath(ROOT / "conf"), version_base=None):
        for planner in planners:
            values = []
            for level in levels:
                cfg = compose(
                    "config", overrides=["experiment=budgets", f"planner={planner}", f"budget={level}"]
                )
                values.append(planner_setup(cfg)[1]["budget_value"])
            assert len(set(values)) == len(levels), planner
            # ours' default is no image limit (null): as many images as its objective asks for
            values = [v for v in values if v is not None]
            assert values in (sorted(values), sorted(values, reverse=True)), planner


def test_a_record_with_an_unknown_budget_is_refused_by_name(tmp_path):
    import json

    from experiments.runs import RunDirectoryError, read_metrics

    (tmp_path / "metrics.json").write_text(json.dumps({"scene": "tomb", "planner": "ours", "budget": "huge"}))
    with pytest.raises(RunDirectoryError, match="unknown budget 'huge'"):
        read_metrics(tmp_path)
