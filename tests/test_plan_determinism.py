"""Every planner, with a fixed seed on a fixed proxy, writes the same plan twice, byte for byte."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
from hydra import compose, initialize_config_dir

from pipeline.settings import planner_params
from scene.camera import Intrinsics
from scene.plan import write_plan
from tests.planner_scenes import box_building

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.mark.parametrize("planner", ["ours", "smith", "yan", "lawnmower"])
def test_same_seed_same_proxy_gives_a_byte_identical_plan(planner, tmp_path):
    with initialize_config_dir(str(CONF), version_base=None):
        cfg = compose("config", overrides=["experiment=smoke", f"planner={planner}", "seed=3"])
    proxy = box_building(size=(30.0, 20.0, 8.0), ground_half=35.0)
    plan_fn = hydra.utils.get_method(cfg.planner._target_)
    params = planner_params(cfg)
    files = []
    for attempt in range(2):
        plan = plan_fn(proxy, Intrinsics(**cfg.camera), params, cfg.seed)
        assert len(plan.viewpoints) >= 4
        files.append((write_plan(plan, tmp_path / f"plan{attempt}") / "viewpoints.csv").read_bytes())
    assert files[0] == files[1]
