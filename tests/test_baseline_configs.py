"""The baselines' Hydra configs name their planner and carry exactly the code's defaults."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import yaml

CONF = Path(__file__).resolve().parents[1] / "conf"


def resolve_survey(cfg: dict) -> dict:
    """The planner config with ``${survey.*}`` interpolations replaced by conf/config.yaml's values."""
    survey = yaml.safe_load((CONF / "config.yaml").read_text())["survey"]
    return {
        k: survey[v[len("${survey.") : -1]] if isinstance(v, str) and v.startswith("${survey.") else v
        for k, v in cfg.items()
    }


@pytest.mark.parametrize("name", ["lawnmower", "smith", "yan"])
def test_planner_config_matches_code_defaults(name):
    cfg = resolve_survey(yaml.safe_load((CONF / "planner" / f"{name}.yaml").read_text()))
    module = importlib.import_module(f"planner.{name}.{name}")
    assert cfg.pop("name") == name
    assert cfg.pop("_target_") == f"planner.{name}.{name}.plan"
    cfg.pop("budget")  # its knob: test_budget_knobs_name_settings_and_move_them_one_way
    assert cfg.pop("version") == 1  # its plans' version (results/protocol.md), not a parameter
    assert set(cfg) == set(module.DEFAULTS)
    for key, value in cfg.items():
        default = module.DEFAULTS[key]
        if isinstance(default, float):
            assert value == pytest.approx(default, rel=1e-9), key
        else:
            assert value == default, key


def test_exploration_config_is_a_lawnmower_config():
    from planner.lawnmower import lawnmower

    cfg = yaml.safe_load((CONF / "exploration" / "lawnmower.yaml").read_text())
    # the exploration group is in the protocol's digest: its name stays (planner/lawnmower/__init__.py)
    assert cfg.pop("_target_") == "planner.lawnmower.plan_exploration"
    cfg.pop("name")
    assert set(cfg) <= set(lawnmower.DEFAULTS)
    assert {k: v for k, v in cfg.items()} == {k: lawnmower.DEFAULTS[k] for k in cfg}


@pytest.mark.parametrize("name", ["lawnmower", "smith", "yan", "ours"])
def test_budget_knobs_name_settings_and_move_them_one_way(name):
    """Each planner's budget knob names one of its settings, and its levels, taken in budget order
    (fewest images first), move that setting one way (the images they plan: bench_baselines --budgets)."""
    from planner.budget import LEVELS, apply_budget

    cfg = resolve_survey(yaml.safe_load((CONF / "planner" / f"{name}.yaml").read_text()))
    levels = [lv for lv in LEVELS if lv == "default" or lv in cfg["budget"]["levels"]]
    assert len(levels) >= 3  # a front needs three points
    values = [apply_budget(cfg, lv, name)[1]["budget_value"] for lv in levels]
    params, record = apply_budget(cfg, "default", name)
    assert "budget" not in params and record["budget_value"] == values[levels.index("default")]
    if name == "ours":  # an image budget; default, no limit: as many as the objective asks for
        assert values[levels.index("default")] is None
        values = [v for v in values if v is not None]
    # One direction all along (the knobs rise with the images).
    assert len(set(values)) == len(values) and values in (sorted(values), sorted(values, reverse=True))
