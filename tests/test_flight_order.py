"""The flight order that minimises flight time (an asymmetric TSP on the drone model's leg times)."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from drone.model import DroneSettings, flight_summary
from planner.trajectory import flight_time_costs, order_by_flight_time

DRONE = replace(
    DroneSettings.default(),
    cruise_speed_m_s=5.0,
    acceleration_m_s2=2.0,
    climb_rate_m_s=3.0,
    descent_rate_m_s=2.0,
    takeoff_xy=None,
)
# A 20 m square at 10 m whose corner B stands 30 m higher: climbing is faster than descending, so
# the flight climbs to B straight after A and comes down over the square, not straight home.
SQUARE = np.array(
    [[0, 0, 10, 0, -45], [20, 0, 40, 0, -45], [20, 20, 10, 0, -45], [0, 20, 10, 0, -45]], float
)  # A, B, C, D
TAKEOFF = np.zeros(3)


def tour_time_s(viewpoints: np.ndarray, order, takeoff: np.ndarray, drone) -> float:
    """Seconds of the closed flight take-off -> ``order`` -> take-off on ``flight_time_costs``."""
    cost = flight_time_costs(viewpoints, takeoff, drone)
    path = [0, *(np.asarray(order, int) + 1), 0]
    return float(sum(cost[a, b] for a, b in zip(path[:-1], path[1:], strict=True)))


def test_leg_times_are_the_hand_values():
    cost = flight_time_costs(SQUARE, TAKEOFF, DRONE)
    # A 20 m leg: 20 / 5 + 5 / 2 = 6.5 s; climbing 30 m: 30 / 3 + 3 / 2 = 11.5 s; descending 30 m:
    # 30 / 2 + 2 / 2 = 16 s; take-off to A, 10 m up: 10 / 3 + 1.5 s; B home: 40 m down, 21 s.
    assert cost[1, 2] == pytest.approx(11.5)
    assert cost[2, 3] == pytest.approx(16.0)
    assert cost[3, 4] == pytest.approx(6.5)
    assert cost[0, 1] == pytest.approx(10 / 3 + 1.5)
    assert cost[2, 0] == pytest.approx(21.0)


def test_the_order_is_the_hand_optimum_and_its_time_the_models():
    order = order_by_flight_time(SQUARE, TAKEOFF, DRONE, first=0)
    assert order.tolist() == [0, 1, 2, 3]  # A B C D
    hand = (10 / 3 + 1.5) + 11.5 + 16.0 + 6.5 + 6.5  # home A, A B, B C, C D, D home (6.5 > 6 down)
    assert tour_time_s(SQUARE, order, TAKEOFF, DRONE) == pytest.approx(hand)
    # Every other order from A is slower (brute force over the 6).
    times = {p: tour_time_s(SQUARE, [0, *p], TAKEOFF, DRONE) for p in itertools.permutations([1, 2, 3])}
    assert min(times, key=times.get) == (1, 2, 3)
    # The drone model's flight time of that order: the tour, a photo at each waypoint, take-off, landing.
    summary = flight_summary(SQUARE[order], DRONE)
    assert summary["flight_time_s"] == pytest.approx(
        hand + 4 * DRONE.photo_time_s + DRONE.takeoff_s + DRONE.landing_s
    )


def test_turns_count_between_waypoints():
    turned = SQUARE.copy()
    turned[:, 3] = [0.0, 180.0, 0.0, 180.0]
    cost = flight_time_costs(turned, TAKEOFF, DRONE)
    plain = flight_time_costs(SQUARE, TAKEOFF, DRONE)
    assert cost[1, 2] - plain[1, 2] == pytest.approx(180.0 / DRONE.yaw_rate_deg_s)
    assert cost[0, 1] == plain[0, 1]  # the first waypoint turns from its own attitude
