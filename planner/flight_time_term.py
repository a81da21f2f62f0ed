"""Flight time as a cost in the planner's objective (``ours_plus``).

The cost of a viewpoint set is ``weight_per_min`` objective units per minute of flight, the flight
timed by the missions' model (``mission.flight_time``: accelerate-cruise-decelerate legs, yaw and
gimbal at each stop, a photo) along a visiting order. The order used while optimising is a greedy
nearest-neighbour path from the take-off point, fixed for one CMA-ES or culling pass: the final
order (LKH) is shorter, but the cost only has to rank alternatives, and a fixed order makes the
cost of moving a cluster a change of its own legs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mission.flight_time import DroneSettings, legs_time_s, stops_time_s


def greedy_order(positions: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Nearest-neighbour visiting order (V,) of ``positions`` (V, 3) from ``start`` (3,), metres."""
    positions = np.asarray(positions, float)
    n = len(positions)
    order = np.empty(n, np.int64)
    left = np.ones(n, bool)
    here = np.asarray(start, float)
    for i in range(n):
        d = np.where(left, np.linalg.norm(positions - here, axis=1), np.inf)
        j = int(np.argmin(d))
        order[i], left[j], here = j, False, positions[j]
    return order


@dataclass(frozen=True)
class FlightTimeTerm:
    """``weight_per_min`` objective units per minute of flight, timed for ``drone`` from ``takeoff``."""

    drone: DroneSettings
    weight_per_min: float
    takeoff: np.ndarray

    def seconds(self, ordered: np.ndarray) -> np.ndarray:
        """Flight time (s) of ordered viewpoint sets (..., V, 5) from and back to the take-off point:
        legs plus stops (take-off and landing excluded: they do not depend on the set)."""
        ordered = np.asarray(ordered, float)
        lead = ordered.shape[:-2]
        home = np.broadcast_to(self.takeoff, lead + (1, 3))
        path = np.concatenate([home, ordered[..., :3], home], axis=-2)
        legs = legs_time_s(path[..., :-1, :].reshape(-1, 3), path[..., 1:, :].reshape(-1, 3), self.drone)
        stops = stops_time_s(ordered[..., 3], ordered[..., 4], self.drone) if ordered.shape[-2] else 0.0
        return legs.reshape(lead + (-1,)).sum(axis=-1) + np.sum(stops, axis=-1)

    def cost(self, ordered: np.ndarray) -> np.ndarray:
        """Objective units (...,) of ordered viewpoint sets (..., V, 5)."""
        return self.weight_per_min * self.seconds(ordered) / 60.0

    def order(self, viewpoints: np.ndarray) -> np.ndarray:
        """The order (V,) the cost uses for ``viewpoints`` (V, 5) during one pass."""
        return greedy_order(np.asarray(viewpoints)[:, :3], self.takeoff)
