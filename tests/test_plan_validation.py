"""Every plan is checked before it is rendered, whoever made it (mission.validate)."""

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh

from mission.export import default_settings
from mission.validate import PlanRejected, validate_plan
from scene.plan import Plan

ROOT = Path(__file__).resolve().parents[1]
DRONE = default_settings()[1]


def hall() -> trimesh.Trimesh:
    """A closed 20 x 20 x 10 m box on the ground, centred on the origin (outward normals)."""
    return trimesh.creation.box(
        extents=(20.0, 20.0, 10.0), transform=trimesh.transformations.translation_matrix((0, 0, 5))
    )


def good_views() -> np.ndarray:
    """Six views 15 m from the box's faces and above its roof, facing it, pitch in range."""
    return np.array(
        [
            [25.0, 0.0, 5.0, 180.0, 0.0],
            [-25.0, 0.0, 5.0, 0.0, 0.0],
            [0.0, 25.0, 5.0, -90.0, 0.0],
            [0.0, -25.0, 8.0, 90.0, -10.0],
            [0.0, 0.0, 25.0, 0.0, -90.0],
            [18.0, 18.0, 20.0, -135.0, -30.0],
        ]
    )


def test_a_flyable_plan_passes():
    validate_plan(Plan(good_views(), ["v"] * 6, "mine"), hall(), DRONE)


@pytest.mark.parametrize(
    ("position", "pitch", "rule"),
    [
        ((30.0, 0.0, 1.0), 0.0, "below the minimum height (drone.min_height_m = 2.0 m)"),
        ((3.0, 2.0, 5.0), 0.0, "inside a closed volume of the proxy"),
        ((30.0, 0.0, 5.0), 45.0, "pitch outside the gimbal range [-90.0, 30.0] deg"),
        ((11.0, 0.0, 5.0), 0.0, "closer to the proxy than drone.min_clearance_m = 2.0 m"),
    ],
)
def test_one_violating_view_is_named(position, pitch, rule):
    views = good_views()
    views[4] = [*position, 180.0, pitch]
    with pytest.raises(PlanRejected) as err:
        validate_plan(Plan(views, ["v"] * 6, "mine"), hall(), DRONE)
    assert str(err.value).startswith("planner 'mine': view 4 ") and str(err.value).endswith(rule)


def test_inside_is_told_apart_from_close_outside():
    # 5 m inside the box is enclosed, but more than min_clearance from every face: only the ray test
    # can refuse it; with no clearance rule at all it is still refused.
    views = good_views()
    views[2] = [0.0, 0.0, 5.0, 0.0, 0.0]
    no_clearance = dataclasses.replace(DRONE, min_clearance_m=0.0)
    with pytest.raises(PlanRejected, match="view 2 .*inside a closed volume"):
        validate_plan(Plan(views, ["v"] * 6, "mine"), hall(), no_clearance)


def test_a_nan_view_is_refused_with_its_index():
    views = good_views()
    views[3, 1] = np.nan
    with pytest.raises(ValueError, match="viewpoint 3 has a non-finite value"):
        Plan(views, ["v"] * 6, "mine")


BAD_PLANNER = """
    import numpy as np
    from scene.plan import Plan

    def plan(proxy, intrinsics, params, seed):
        lo, hi = proxy.bounds
        centre = 0.5 * (lo + hi)
        views = np.array([[centre[0] + 60.0, centre[1], 20.0, 180.0, -10.0]] * 3)
        views[1, 4] = params["bad_pitch_deg"]  # the gimbal cannot look up that far
        return Plan(views, ["bad"] * 3, params["name"])
"""


def test_a_cell_stops_before_rendering_a_plan_that_breaks_a_rule(tmp_path):
    (tmp_path / "conf" / "planner").mkdir(parents=True)
    (tmp_path / "badplanner.py").write_text(textwrap.dedent(BAD_PLANNER))
    (tmp_path / "conf" / "planner" / "bad.yaml").write_text(
        "name: bad\n_target_: badplanner.plan\nbad_pitch_deg: 45.0\n"
    )
    run_dir = tmp_path / "run"
    out = subprocess.run(
        [
            sys.executable,
            "run.py",
            "experiment=smoke",
            "scene=tomb",
            "planner=bad",
            "proxy=ground_truth_degraded",
            f"hydra.searchpath=[file://{tmp_path / 'conf'}]",
            f"hydra.run.dir={run_dir}",
            f"cache_dir={tmp_path / 'cache'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(tmp_path)},
    )
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    line = "failed in stage plan: planner 'bad': view 1 "
    assert line in out.stderr and "pitch outside the gimbal range [-90.0, 30.0] deg" in out.stderr
    assert not (run_dir / "images").exists() and not (run_dir / "plan").exists()
    assert '"failed_stage": "plan"' in (run_dir / "metrics.json").read_text()
