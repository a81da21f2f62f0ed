"""Quality-per-image fronts on constructed metrics whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from experiments.front_core import cost_to_reach, front_points, front_table, value_at
from experiments.fronts import plot_fronts

IMAGES = [100, 200, 400]
COMP = [40.0, 60.0, 80.0]


@pytest.mark.parametrize(
    ("level", "cost", "at_most"),
    [
        (50.0, 150.0, False),
        (80.0, 400.0, False),
        (70.0, 300.0, False),
        (30.0, 100.0, True),
        (40.0, 100.0, True),
    ],
)
def test_images_to_reach_interpolate_between_the_bracketing_budgets(level, cost, at_most):
    reach = cost_to_reach(IMAGES, COMP, level)
    assert reach.cost == pytest.approx(cost) and reach.at_most is at_most


def test_a_level_above_the_front_is_not_reached_and_a_dip_is_not_a_crossing():
    assert not cost_to_reach(IMAGES, COMP, 90.0).reached
    assert cost_to_reach(IMAGES, COMP, 90.0).text() == "not reached"
    # 70 is first reached on the way to 200 images; the dip to 65 at 400 images does not count again
    dip = ([100, 200, 400, 800], [40.0, 70.0, 65.0, 90.0])
    assert cost_to_reach(*dip, 68.0).cost == pytest.approx(100 + 28 / 30 * 100)
    assert cost_to_reach(*dip, 80.0).cost == pytest.approx(400 + 15 / 25 * 400)
    assert cost_to_reach(IMAGES, COMP, 30.0).text() == "≤ 100"


def test_values_at_equal_images_are_interpolated_inside_the_front_only():
    assert value_at(IMAGES, COMP, 300) == pytest.approx(70.0)
    assert value_at(IMAGES, COMP, 400) == pytest.approx(80.0)
    assert value_at(IMAGES, COMP, 125) == pytest.approx(45.0)
    assert math.isnan(value_at(IMAGES, COMP, 50)) and math.isnan(value_at(IMAGES, COMP, 800))
    assert value_at([200], [55.0], 200) == 55.0
    with pytest.raises(ValueError, match="as many costs as values"):
        value_at([1, 2], [1.0], 1)


def _runs() -> pd.DataFrame:
    rows = []

    def add(planner, budget, seed, images, comp, acc, minutes, status="ok"):
        rows.append(
            dict(
                scene="tomb",
                planner=planner,
                budget=budget,
                seed=seed,
                status=status,
                n_images=images,
                comp_050=comp,
                acc90_m=acc,
                flight_time_s=minutes * 60.0,
            )
        )

    # given out of order: the front must come back fewest images first
    add("ours", "high", 0, 400, 80.0, 0.03, 40.0)
    add("ours", "default", 0, 200, 58.0, 0.03, 20.0)
    add("ours", "default", 1, 220, 62.0, 0.05, 22.0)
    add("ours", "default", 2, 999, 99.0, 0.01, 99.0, status="failed")  # a failed seed counts for nothing
    add("ours", "low", 0, 100, 40.0, 0.04, 10.0)
    add("yan", "default", 0, 1000, 75.0, 0.05, 100.0)
    add("yan", "low", 0, 300, 50.0, 0.06, 30.0)
    return pd.DataFrame(rows)


def test_front_points_average_seeds_per_budget_in_budget_order():
    points = front_points(_runs())
    ours = points[points["planner"] == "yan"].index.max() < points[points["planner"] == "ours"].index.min()
    assert ours  # baselines before ours, as in the tables
    mine = points[points["planner"] == "ours"]
    assert list(mine["budget"]) == ["low", "default", "high"]
    assert list(mine["n_images"]) == [100.0, 210.0, 400.0]
    assert list(mine["comp_050"]) == [40.0, 60.0, 80.0]
    assert mine["comp_050_std"].iloc[1] == pytest.approx(np.std([58.0, 62.0], ddof=1))
    assert list(mine["n"]) == [1, 2, 1]


def test_front_table_answers_the_study_questions():
    table = front_table(front_points(_runs()), targets_pct=(50.0, 70.0, 80.0), at_images=(300, 800))
    ours = table[table["planner"] == "ours"].iloc[0]
    yan = table[table["planner"] == "yan"].iloc[0]
    assert ours["images_to_50"] == pytest.approx(155.0)  # 100 + (50 - 40) / 20 * 110
    assert ours["minutes_to_50"] == pytest.approx(15.5)
    assert ours["images_to_80"] == pytest.approx(400.0)
    assert yan["images_to_50"] == pytest.approx(300.0) and bool(yan["images_to_50_at_most"])
    assert yan["images_to_70"] == pytest.approx(300 + 20 / 25 * 700)
    assert math.isnan(yan["images_to_80"])
    assert ours["comp_at_300"] == pytest.approx(60.0 + 90 / 190 * 20.0)
    assert yan["comp_at_300"] == pytest.approx(50.0)
    assert math.isnan(ours["comp_at_800"]) and yan["comp_at_800"] == pytest.approx(50 + 500 / 700 * 25)
    assert ours["acc90_cm_at_300"] == pytest.approx(4.0 + 90 / 190 * (3.0 - 4.0))


def _front_lines(ax) -> dict:
    """Label -> the data line of each planner's error-bar plot on ``ax``."""
    return {c.get_label(): c.lines[0] for c in ax.containers}


def test_the_front_figure_joins_each_planner_in_budget_order():
    points = front_points(_runs())
    lines = _front_lines(plot_fronts(points, "n_images").axes[0])
    assert list(lines["Ours"].get_xdata()) == [100.0, 210.0, 400.0]
    assert list(lines["Ours"].get_ydata()) == [40.0, 60.0, 80.0]
    assert list(lines["Yan et al."].get_xdata()) == [300.0, 1000.0]
    accuracy = _front_lines(plot_fronts(points, "n_images").axes[1])  # second row, same scene
    assert list(accuracy["Ours"].get_ydata()) == pytest.approx([4.0, 4.0, 3.0])
    minutes = _front_lines(plot_fronts(points, "flight_time_s").axes[0])
    assert list(minutes["Ours"].get_xdata()) == [10.0, 21.0, 40.0]


def test_a_cost_that_was_not_recorded_is_not_an_answer():
    """Records from before flight time was recorded: the minutes are unknown, not "not reached"."""
    reach = cost_to_reach([float("nan"), float("nan")], [40.0, 80.0], 50.0)
    assert reach.missing and reach.text() == "n/a"
    # Known where the answer lies: an unknown cost elsewhere on the front does not matter.
    assert cost_to_reach([10.0, 20.0, float("nan")], [40.0, 80.0, 90.0], 50.0).cost == pytest.approx(12.5)
    runs = _runs().drop(columns="flight_time_s")
    table = front_table(front_points(runs), targets_pct=(50.0,), at_images=(300,))
    assert bool(table.iloc[0]["minutes_to_50_missing"]) and math.isnan(table.iloc[0]["minutes_to_50"])


def _seed_runs() -> pd.DataFrame:
    """Smith's front the same on three seeds; ours' crosses it at 200 images on seeds 0 and 2 only."""
    comp = {
        ("smith", 0): [70.0, 75.0, 78.0],
        ("smith", 1): [70.0, 75.0, 78.0],
        ("smith", 2): [70.0, 75.0, 78.0],
        ("ours", 0): [60.0, 80.0, 88.0],
        ("ours", 1): [65.0, 74.0, 86.0],
        ("ours", 2): [62.0, 82.0, 90.0],
    }
    rows = []
    for (planner, seed), values in comp.items():
        for budget, images, c in zip(("low", "default", "high"), (100, 200, 300), values, strict=True):
            rows.append(
                dict(
                    scene="tomb",
                    planner=planner,
                    budget=budget,
                    seed=seed,
                    status="ok",
                    n_images=images,
                    comp_050=c,
                    acc90_m=0.02,
                    flight_time_s=images * 6.0,
                    target_gsd_m=0.03,
                )
            )
    return pd.DataFrame(rows)


def test_a_claim_holds_on_every_seed_or_is_a_tie():
    from experiments.front_core import Question
    from experiments.fronts import seed_claims

    questions = [Question("completeness", 200), Question("completeness", 100), Question("images", 85.0)]
    questions += [Question("images", 75.0), Question("completeness", 300)]
    claims = seed_claims(_seed_runs(), questions).set_index("question")
    # the crossing flips with the seed: ours ahead at 200 images on seeds 0 and 2, Smith on seed 1
    assert claims.loc["completeness at 200 images", "best"] == "tie: Smith et al., Ours"
    assert list(claims.loc["completeness at 200 images", ["seed_0", "seed_1", "seed_2"]]) == [
        "Ours",
        "Smith et al.",
        "Ours",
    ]
    assert claims.loc["completeness at 100 images", "best"] == "Smith et al."
    assert claims.loc["images to 85 %", "best"] == "Ours"  # Smith never reaches 85 %
    assert claims.loc["images to 75 %", "best"] == "tie: Smith et al., Ours"  # 175 / 208 / 165 vs 200
    assert claims.loc["completeness at 300 images", "best"] == "Ours"
    # within a 10-point noise floor Smith's 78 % ties ours' 88 and 86 % on seeds 0 and 1, not its 90 %
    floor = {"comp_050": 10.0, "acc90_m": 0.0}
    at_300 = seed_claims(_seed_runs(), [Question("completeness", 300)], floor).iloc[0]
    assert at_300["best"] == "tie: Smith et al., Ours"
    assert list(at_300[["seed_0", "seed_1", "seed_2"]]) == [
        "Smith et al. = Ours",
        "Smith et al. = Ours",
        "Ours",
    ]
    # a seed Smith has no cell of compares nothing: the claim stands on the seeds that compare
    runs = _seed_runs()
    runs = runs[~((runs["planner"] == "smith") & (runs["seed"] == 2))]
    partial = seed_claims(runs, [Question("completeness", 100)]).iloc[0]
    assert partial["best"] == "Smith et al. on 2 of 3 seeds" and partial["seed_2"] == "n/a"


def test_each_answer_is_a_range_over_the_seeds():
    from experiments.front_core import Question
    from experiments.fronts import seed_ranges

    questions = [Question("images", 85.0), Question("completeness", 200), Question("images", 95.0)]
    ranges = seed_ranges(_seed_runs(), questions).set_index("method")
    # 200 + (85 - 80) / 8 x 100 = 262.5; (85 - 74) / 12 -> 291.7; (85 - 82) / 8 -> 237.5
    assert ranges.loc["Ours", "images to 85 %"] == "238–292"
    assert ranges.loc["Smith et al.", "images to 85 %"] == "–"
    assert ranges.loc["Ours", "completeness at 200 images"] == "74.0–82.0"
    assert ranges.loc["Smith et al.", "completeness at 200 images"] == "75.0"
    assert ranges.loc["Ours", "images to 95 %"] == "–" and int(ranges.loc["Ours", "seeds"]) == 3


def test_the_gsd_axis_is_the_default_knob_at_each_gsd_coarsest_first():
    runs = _seed_runs()
    extra = runs[(runs["budget"] == "default") & (runs["seed"] == 0)].copy()
    extra["target_gsd_m"] = 0.045
    extra["n_images"] = 90
    runs = pd.concat([runs, extra], ignore_index=True)
    own = front_points(runs)  # the own-knob axis leaves the 4.5 cm cells out
    assert list(own[own["planner"] == "ours"]["n_images"]) == [100.0, 200.0, 300.0]
    gsd = front_points(runs, axis="gsd")
    ours = gsd[gsd["planner"] == "ours"]
    assert list(ours["budget"]) == ["gsd4.5cm", "gsd3cm"] and list(ours["n_images"]) == [90.0, 200.0]
    assert list(ours["n"]) == [1, 3]
