"""Golden records of protocol 1 (tests/golden_records.py): every planner's smoke plan on the committed
smoke tomb proxy, and the protocol's settings per study scene. The smoke cells' golden metrics are
checked in tests/test_pipeline_smoke.py, beside the sweep that makes them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from pipeline.protocol import PROTOCOL_DIGESTS, protocol_fields, study_digests
from tests.golden_records import (
    CELLS_FILE,
    PLANNERS,
    PLANS_FILE,
    cell_differences,
    plan_differences,
    smoke_plan_record,
)

ROOT = Path(__file__).resolve().parents[1]
BUMP = (
    "a bug, or a planner version bump (conf/planner/{p}.yaml) with the plans rewritten by "
    "`.venv/bin/python -m tests.golden_records --write` and a line in results/protocol.md; the golden "
    "values come from an AMD EPYC: on another processor, measure its spread first (results/protocol.md)"
)


@pytest.fixture(scope="module")
def smoke_cache(tmp_path_factory):
    """One stage cache for the module: the committed smoke proxy is installed once."""
    return tmp_path_factory.mktemp("golden_cache")


@pytest.fixture(scope="module")
def golden_plans():
    return json.loads(PLANS_FILE.read_text())


@pytest.mark.parametrize("planner", PLANNERS)
def test_smoke_plan_is_golden(planner, smoke_cache, golden_plans):
    record = smoke_plan_record(planner, smoke_cache)
    assert record["proxy_bundle"] == "proxies/smoke/tomb/seed0"  # the committed proxy, not a rebuild
    differences = plan_differences(record, golden_plans[planner])
    assert not differences, f"{planner}'s smoke plan moved ({BUMP.format(p=planner)}): {differences}"


def test_a_moved_planner_setting_fails_the_golden_plan(smoke_cache, golden_plans):
    """The guard bites: the lawnmower flown 1 m higher is not its golden plan."""
    record = smoke_plan_record("lawnmower", smoke_cache, ("planner.altitude_above_top_m=16.0",))
    differences = plan_differences(record, golden_plans["lawnmower"])
    assert any(d.startswith(("n_viewpoints", "viewpoints")) for d in differences), differences


def test_a_nudged_cell_metric_fails_the_golden_cell():
    golden = json.loads(CELLS_FILE.read_text())["ours"]
    assert cell_differences(dict(golden), golden) == []
    nudged = {**golden, "comp_050": golden["comp_050"] * (1 + 1e-6)}
    assert cell_differences(nudged, golden) == [
        f"comp_050: {nudged['comp_050']!r} != golden {golden['comp_050']!r}"
    ]


def test_protocol_settings_are_protocol_1():
    """The default preset's protocol settings of every study scene are the committed ones: an edited
    YAML of a covered group (results/protocol.md) is a protocol bump, not a silent change."""
    assert study_digests() == PROTOCOL_DIGESTS


def test_a_moved_protocol_setting_leaves_the_protocol():
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        study = compose("config", overrides=["scene=church", "planner=yan", "seed=2", "budget=low"])
        moved = compose("config", overrides=["scene=church", "reconstruct.dense.num_partners=3"])
        neutral = compose("config", overrides=["scene=church", "reconstruct.deterministic=false"])
    assert protocol_fields(study, "church") == {"protocol": 1, "protocol_digest": PROTOCOL_DIGESTS["church"]}
    assert protocol_fields(moved, "church")["protocol"] is None
    assert protocol_fields(neutral, "church")["protocol"] == 1
    assert protocol_fields(study, "tomb")["protocol"] is None  # another scene's settings
