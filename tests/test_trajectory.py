"""TSP ordering against brute force on small instances."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from planner.trajectory import flight_length, order_viewpoints
from scene.plan import PlanningError, polyline_length


def _best(points, start, return_home):
    return min(
        flight_length(points[list(q)], start, return_home) for q in itertools.permutations(range(len(points)))
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_open_path_from_takeoff_is_optimal(seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 60, (8, 3))
    start = np.array([-5.0, -5.0, 0.0])
    order = order_viewpoints(points, start)
    assert sorted(order.tolist()) == list(range(8))
    assert flight_length(points[order], start) == pytest.approx(_best(points, start, False), abs=0.01)


@pytest.mark.parametrize("seed", [3, 4])
def test_closed_tour_and_free_path_are_optimal(seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 60, (7, 3))
    start = np.array([30.0, -10.0, 0.0])
    order = order_viewpoints(points, start, return_home=True)
    assert flight_length(points[order], start, True) == pytest.approx(_best(points, start, True), abs=0.01)
    order = order_viewpoints(points)
    assert flight_length(points[order]) == pytest.approx(_best(points, None, False), abs=0.01)


def test_collinear_points_in_order_and_length_matches_polyline():
    points = np.array([[3.0, 0, 0], [1.0, 0, 0], [4.0, 0, 0], [2.0, 0, 0]])
    order = order_viewpoints(points, start=np.zeros(3))
    assert order.tolist() == [1, 3, 0, 2]
    assert flight_length(points[order]) == pytest.approx(3.0)
    assert flight_length(points[order]) == polyline_length(points[order])
    assert flight_length(points[order], np.zeros(3)) == pytest.approx(4.0)
    assert flight_length(points[order], np.zeros(3), return_home=True) == pytest.approx(8.0)


def test_tiny_and_empty_inputs():
    assert order_viewpoints(np.array([[1.0, 2, 3]]), np.zeros(3)).tolist() == [0]
    assert order_viewpoints(np.array([[5.0, 0, 0], [1.0, 0, 0]]), np.zeros(3)).tolist() == [1, 0]
    with pytest.raises(PlanningError, match="empty"):
        order_viewpoints(np.zeros((0, 3)), np.zeros(3))
