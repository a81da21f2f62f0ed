"""Planning to a crew's budget: as many views as the budget allows, the objective close to the best
subset, no budget the plan of before, and budgets that cannot be planned refused by name."""

from __future__ import annotations

import itertools
from pathlib import Path

import hydra
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from drone.model import DroneSettings
from pipeline.settings import SettingsError, cell_settings, planner_params
from planner.heuristics import HeuristicParams
from planner.objective import ObjectiveState
from planner.ours.ours_budget import BudgetLimit, fit_budget
from planner.sampling import sample_surface
from planner.visibility import VisibilityLimits, VisibilityModel
from scene.camera import Intrinsics, look_at
from scene.plan import PlanningError, write_plan
from tests.planner_scenes import box_building

CONF = Path(__file__).resolve().parents[1] / "conf"
FIXTURE = Path(__file__).resolve().parent / "data" / "ours_box_plan" / "viewpoints.csv"
CAMERA = Intrinsics(640, 480, 60.0)


def smoke(*overrides: str):
    with initialize_config_dir(str(CONF), version_base=None):
        return compose("config", overrides=["experiment=smoke", "planner=ours", "seed=3", *overrides])


def box_plan(cfg):
    proxy = box_building(size=(30.0, 20.0, 8.0), ground_half=35.0)
    plan_fn = hydra.utils.get_method(cfg.planner._target_)
    return plan_fn(proxy, Intrinsics(**cfg.camera), planner_params(cfg), cfg.seed)


def test_no_budget_plans_the_views_of_before_byte_for_byte(tmp_path):
    """The fixture is the plan of the code before budgets (86 views, smoke settings, seed 3)."""
    plan = box_plan(smoke())
    assert (write_plan(plan, tmp_path) / "viewpoints.csv").read_bytes() == FIXTURE.read_bytes()
    assert "budget" not in plan.info


def test_an_image_budget_plans_that_many_views_and_records_what_it_gave_up():
    plan = box_plan(smoke("planner.budget_limit.max_images=50"))
    assert len(plan.viewpoints) == 50
    budget = plan.info["budget"]
    assert budget["asked"] == {"max_images": 50}
    assert budget["unconstrained"]["n_images"] == 86 == len(budget["unconstrained_viewpoints"])
    assert budget["spent"]["n_images"] == 50
    assert budget["R_after"] < budget["R_before"]
    partners = budget["stereo_partners"]
    assert sum(partners["unconstrained"]["views_by_partners"]) == 86
    assert sum(partners["spent"]["views_by_partners"]) == 50


def test_a_flight_time_budget_is_kept_on_the_drone_model():
    from drone.model import flight_summary

    plan = box_plan(smoke("planner.budget_limit.max_flight_min=8"))
    minutes = flight_summary(np.asarray(plan.viewpoints), DroneSettings.default())["flight_time_s"] / 60
    budget = plan.info["budget"]
    assert budget["unconstrained"]["flight_min"] > 8.0 >= budget["spent"]["flight_min"]
    # The plan's own order flies no faster than the flight-time order the budget was counted in.
    assert minutes >= budget["spent"]["flight_min"] - 1e-9


def ring_candidates() -> np.ndarray:
    """Eight views around a 10 x 8 x 6 m box, 20 m away, at two heights."""
    rows = []
    for k, a in enumerate(np.radians(np.arange(0, 360, 45))):
        height = 4.0 if k % 2 else 10.0
        rows.append(look_at([20 * np.cos(a), 20 * np.sin(a), height], [0.0, 0.0, 3.0]).as_array())
    return np.array(rows)


def test_the_budget_prune_is_close_to_the_best_subset():
    """Eight candidates, a budget of four: the greedy prune's R within 3 % of the best of all 70."""
    mesh = box_building(size=(10.0, 8.0, 6.0), ground_half=None)
    points, normals = sample_surface(mesh, 300, seed=0)
    model = VisibilityModel(mesh, points, normals, CAMERA, VisibilityLimits(1.0, 40.0, 80.0))
    params = HeuristicParams(k_count=3, target_lo_m=16.0, target_hi_m=24.0, d_margin_m=10.0)
    views = ring_candidates()
    obs = model.observe(views)

    def r_of(subset) -> float:
        state = ObjectiveState(params, len(points), points=points)
        state.reset(obs.take(list(subset)))
        return state.R

    best = max(r_of(s) for s in itertools.combinations(range(8), 4))
    state = ObjectiveState(params, len(points), points=points)
    state.reset(obs)
    kept, record = fit_budget(state, views, ["detail"] * 8, BudgetLimit(max_images=4), None, np.zeros(3))
    assert kept.sum() == 4
    assert record["R_after"] == pytest.approx(r_of(np.flatnonzero(kept)))
    assert record["R_after"] >= 0.97 * best


def test_a_budget_below_the_coverage_views_is_refused_with_the_smallest_one():
    cfg = smoke("planner.budget_limit.max_images=2")
    with pytest.raises(
        PlanningError, match=r"budget_limit.max_images=2 is below the \d+ model-coverage views"
    ):
        box_plan(cfg)


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("planner.budget_limit.max_images=0", "budget_limit.max_images must be >= 1, got 0"),
        ("planner.budget_limit.max_flight_min=-5", "budget_limit.max_flight_min must be > 0"),
        ("planner.budget_limit.max_flight_min=nan", "budget_limit.max_flight_min must be a finite number"),
        ("planner.budget_limit.max_batteries=1.5", "budget_limit.max_batteries must be an integer"),
        ("planner.budget_partners.weight=-0.5", "budget_partners.weight must be >= 0"),
    ],
)
def test_a_bad_budget_is_refused_before_any_work(override, named):
    with pytest.raises(SettingsError, match=named):
        cell_settings(smoke(override))
