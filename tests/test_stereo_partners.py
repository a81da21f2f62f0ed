"""Forecast stereo partners: the dense stage's partner test on constructed views, the shortfall a
removal adds, and the budget prune's pick with and without it, against hand computations."""

from __future__ import annotations

import numpy as np
import pytest

from planner.ours.ours_budget import PartnerTerm, _pick_victims
from planner.ours.stereo_partners import PartnerRule, added_shortfall, forecast, partner_matrix

RULE = PartnerRule(min_shared_samples=10, num_partners=4)


def nadir_views_of_a_square(centres: list[tuple[float, float, float]]):
    """Nadir views of an 11 x 11 grid of samples on z = 0 over [-5, 5]^2 m, every sample seen."""
    xs = np.linspace(-5.0, 5.0, 11)
    points = np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2)
    points = np.column_stack([points, np.zeros(len(points))])
    centres = np.asarray(centres, dtype=float)
    to_camera = centres[:, None, :] - points[None]
    direction = to_camera / np.linalg.norm(to_camera, axis=-1, keepdims=True)
    viewpoints = np.column_stack([centres, np.zeros(len(centres)), np.full(len(centres), -90.0)])
    return np.ones((len(centres), len(points)), bool), direction, viewpoints


def test_the_partner_test_on_nadir_views_matches_the_hand_geometry():
    # A and B: 4 m apart at 20 m, 11.3 deg at the centre -> partners. C above A: the baseline runs
    # along both axes. D 40 m off: 42-63 deg over the square, above 40. F 0.5 m from A: 1.4 deg,
    # below 3; F and B: 3.5 m apart, 9.9 deg -> partners.
    visible, direction, vps = nadir_views_of_a_square(
        [(0, 0, 20), (4, 0, 20), (0, 0, 30), (40, 0, 20), (0.5, 0, 20)]
    )
    eligible = partner_matrix(visible, direction, vps, RULE)
    expected = np.zeros((5, 5), bool)
    for a, b in ((0, 1), (1, 4)):
        expected[a, b] = expected[b, a] = True
    np.testing.assert_array_equal(eligible, expected)
    assert forecast(eligible, 4) == {"mean_partners": 0.8, "views_by_partners": [2, 2, 1, 0, 0]}
    # Fewer shared samples than asked for: no partner at all.
    few = visible.copy()
    few[:, 9:] = False
    assert not partner_matrix(few, direction, vps, RULE).any()


def test_a_removal_adds_the_partner_slots_it_takes_and_frees_its_own():
    # Path 0 - 1 - 2 and a lone view 3, one partner wanted: removing 1 leaves 0 and 2 without one
    # (+2); 0 or 2 leave 1 with a spare (0); the lone view takes its own shortfall with it (-1).
    eligible = np.zeros((4, 4), bool)
    for a, b in ((0, 1), (1, 2)):
        eligible[a, b] = eligible[b, a] = True
    np.testing.assert_array_equal(added_shortfall(eligible, np.ones(4, bool), 1), [0, 2, 0, -1])

    loss = np.array([1.0, 0.5, 2.0, 3.0])
    assert _pick_victims(loss, 2, None).tolist() == [1, 0]
    # Weight 1 (scale: the mean loss 1.625): costs 1, 3.75, 2, 1.375 -> view 0; then 1 and 2 are each
    # other's only partner: 2.125, 3.625, 1.375 -> view 3.
    assert _pick_victims(loss, 2, PartnerTerm(eligible, 1, 1.0)).tolist() == [0, 3]
    assert _pick_victims(loss, 2, PartnerTerm(eligible, 1, 0.0)).tolist() == [1, 0]


@pytest.mark.parametrize(
    ("node", "named"),
    [
        ({"weight": -1.0}, "budget_partners.weight must be >= 0"),
        ({"min_shared_samples": 0}, "budget_partners.min_shared_samples must be >= 1"),
        ({"min_triangulation_angle_deg": 50.0}, "min_triangulation_angle_deg=50 is above"),
    ],
)
def test_a_bad_partner_setting_is_refused_by_name(node, named):
    with pytest.raises(ValueError, match=named):
        PartnerRule.from_config(node)
