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
    module = importlib.import_module(f"planner.{name}")
    assert cfg.pop("name") == name
    assert cfg.pop("_target_") == f"planner.{name}.plan"
    assert set(cfg) == set(module.DEFAULTS)
    for key, value in cfg.items():
        default = module.DEFAULTS[key]
        if isinstance(default, float):
            assert value == pytest.approx(default, rel=1e-9), key
        else:
            assert value == default, key


def test_exploration_config_is_a_lawnmower_config():
    from planner import lawnmower

    cfg = yaml.safe_load((CONF / "exploration" / "lawnmower.yaml").read_text())
    assert cfg.pop("_target_") == "planner.lawnmower.plan_exploration"
    cfg.pop("name")
    assert set(cfg) <= set(lawnmower.DEFAULTS)
    assert {k: v for k, v in cfg.items()} == {k: lawnmower.DEFAULTS[k] for k in cfg}
