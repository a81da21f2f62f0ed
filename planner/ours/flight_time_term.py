"""Flight time as a cost in the planner's objective (``ours_plus``).

The cost of a viewpoint set is ``weight_per_pct`` objective units per 1 % of a reference flight
time: the flight of the plan's first set of views (``FlightTimeTerm.referenced``), before the term
acted on it. A per-minute price is not scale-free: R counts well-observed samples of a fixed number
(2048) whatever the scene's size, so a view of a large scene adds less R than one of a small scene
while taking as long to fly, and one price per minute prunes the large scene harder (the cathedral
lost 22 % of its views and 5 points of completeness at the price that cost the tomb 5 %:
archive/pre_p1/ours_plus.md). Priced per share of the scene's own flight, 1 % of the flight buys the same
share of R on every scene. The flight is timed by the missions' model (``drone.model``:
accelerate-cruise-decelerate legs, yaw and gimbal at each stop, a photo) along a visiting order.
The order used while optimising is a greedy nearest-neighbour path from the take-off point, fixed
for one CMA-ES or culling pass: the final order (LKH) is shorter, but the cost only has to rank
alternatives, and a fixed order makes the cost of moving a cluster a change of its own legs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from drone.model import DroneSettings, legs_time_s, stops_time_s


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
    """``weight_per_pct`` objective units per 1 % of ``reference_s`` (seconds) of flight, timed for
    ``drone`` from ``takeoff``; ``reference_s`` is set by ``referenced`` before the first cost."""

    drone: DroneSettings
    weight_per_pct: float
    takeoff: np.ndarray
    reference_s: float | None = None

    def referenced(self, viewpoints: np.ndarray) -> FlightTimeTerm:
        """This term with the flight of ``viewpoints`` (V, 5), in its greedy order, as the reference."""
        viewpoints = np.asarray(viewpoints, float)
        reference = float(self.seconds(viewpoints[self.order(viewpoints)]))
        if not reference > 0:
            raise ValueError(f"flight-time term: the reference flight of {len(viewpoints)} views takes 0 s")
        return replace(self, reference_s=reference)

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
        if self.reference_s is None:
            raise ValueError("flight-time term: no reference flight yet (call referenced() first)")
        return self.weight_per_pct * 100.0 * self.seconds(ordered) / self.reference_s

    def order(self, viewpoints: np.ndarray) -> np.ndarray:
        """The order (V,) the cost uses for ``viewpoints`` (V, 5) during one pass."""
        return greedy_order(np.asarray(viewpoints)[:, :3], self.takeoff)
