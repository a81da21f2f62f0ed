"""Flight order of a viewpoint set: a travelling-salesman path solved by LKH (``elkai``).

The path starts at a take-off point and is OPEN by default: it visits every viewpoint once and
ends at the last one (no return leg). ``return_home=True`` asks for the closed tour back to the
take-off point instead. Edge costs are Euclidean distances between positions, rounded to whole
millimetres for LKH.

Lengths: ``flight_length(ordered)`` is ``planner.base.polyline_length`` of the ordered positions,
the number ``Plan.flight_length_m`` reports; passing ``start`` adds the take-off leg (and, with
``return_home``, the leg back).
"""

from __future__ import annotations

import elkai
import numpy as np

from drone.model import legs_time_s
from scene.plan import PlanningError, polyline_length

_MM_PER_M = 1000.0


def _int_matrix(cost_m: np.ndarray) -> list[list[int]]:
    return np.rint(cost_m * _MM_PER_M).astype(np.int64).tolist()


def order_viewpoints(
    positions: np.ndarray, start=None, return_home: bool = False, runs: int = 3
) -> np.ndarray:
    """Visiting order (V,) of viewpoint positions (V, 3) in metres.

    Args:
        positions: (V, 3) viewpoint positions in metres.
        start: (3,) take-off point in metres; None: the path may start anywhere (open both ends).
        return_home: close the tour back to ``start`` (ignored without ``start``).
        runs: LKH restarts (elkai ``runs``); LKH is seeded internally, so the order is deterministic.

    Returns:
        a permutation of ``range(V)``: the first index is visited first.
    """
    pos = np.asarray(positions, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3 or not np.isfinite(pos).all():
        raise PlanningError(f"positions must be a finite (V, 3) array, got shape {pos.shape}")
    n = len(pos)
    if n == 0:
        raise PlanningError("cannot order an empty viewpoint set")
    if start is not None:
        start = np.asarray(start, dtype=float).reshape(3)
        if not np.isfinite(start).all():
            raise PlanningError(f"take-off point must be finite, got {start.tolist()}")
    if n == 1:
        return np.zeros(1, dtype=np.intp)
    if n == 2:
        if start is None or np.linalg.norm(pos[0] - start) <= np.linalg.norm(pos[1] - start):
            return np.array([0, 1], dtype=np.intp)
        return np.array([1, 0], dtype=np.intp)
    # Node 0 is the take-off point, or a dummy at zero cost from everything (free start and end).
    nodes = np.concatenate([start[None] if start is not None else np.zeros((1, 3)), pos])
    cost = np.linalg.norm(nodes[:, None] - nodes[None], axis=-1)
    if start is None:
        cost[0, :] = 0.0
        cost[:, 0] = 0.0
    elif not return_home:
        # Open path from the take-off point as a symmetric TSP (LKH solves those far faster than
        # the asymmetric form): a dummy node joined to take-off at cost 0 and to every viewpoint at
        # cost 0, while each take-off-viewpoint edge costs ``penalty`` more. A tour not passing
        # take-off -> dummy pays the penalty twice; a penalty above the largest pairwise distance
        # makes that never optimal, and the optimal tour is take-off -> path -> dummy -> take-off.
        penalty = float(cost.max()) + 1.0
        cost[0, 1:] += penalty
        cost[1:, 0] += penalty
        cost = np.pad(cost, ((0, 1), (0, 1)))
    tour = elkai.DistanceMatrix(_int_matrix(cost)).solve_tsp(runs=int(runs))
    tour = tour[:-1]  # elkai repeats the first node at the end
    k = tour.index(0)
    tour = tour[k:] + tour[:k]
    if start is not None and not return_home and tour[1] == n + 1:
        tour = [0, *tour[:0:-1]]  # the dummy came first: walk the tour the other way
    order = np.asarray([i for i in tour[1:] if i <= n], dtype=np.intp) - 1
    if start is None:
        # Both directions have the same cost; pick the one that starts at the smaller index.
        if order[-1] < order[0]:
            order = order[::-1].copy()
    if sorted(order.tolist()) != list(range(n)):
        raise PlanningError("TSP solver returned an invalid tour")
    return order


def flight_length(ordered_positions: np.ndarray, start=None, return_home: bool = False) -> float:
    """Length in metres of the flight through ``ordered_positions`` (N, 3).

    Without ``start`` this is ``polyline_length(ordered_positions)`` (the plan's flight length);
    with it the take-off leg is added, and with ``return_home`` also the leg back to ``start``.
    """
    pos = np.asarray(ordered_positions, dtype=float).reshape(-1, 3)
    if start is None:
        return polyline_length(pos)
    start = np.asarray(start, dtype=float).reshape(1, 3)
    legs = [start, pos, start] if return_home else [start, pos]
    return polyline_length(np.concatenate(legs))


def flight_time_costs(viewpoints: np.ndarray, takeoff: np.ndarray, drone) -> np.ndarray:
    """(V + 1, V + 1) seconds of each hop of a flight, node 0 the take-off point (on the ground):
    ``cost[i, j]`` is the leg from node i to node j (``drone.model.legs_time_s``: acceleration,
    cruise, climb and descent rates) plus, arriving at a waypoint from another, the yaw and gimbal
    turn between their attitudes; the photo time is the same for every order and left out."""
    vps = np.asarray(viewpoints, dtype=float).reshape(-1, 5)
    nodes = np.concatenate([np.asarray(takeoff, float).reshape(1, 3), vps[:, :3]])
    n = len(nodes)
    starts = np.repeat(nodes, n, axis=0)
    ends = np.tile(nodes, (n, 1))
    cost = legs_time_s(starts, ends, drone).reshape(n, n)
    turn = np.abs((vps[None, :, 3] - vps[:, None, 3] + 180.0) % 360.0 - 180.0) / drone.yaw_rate_deg_s
    tilt = np.abs(vps[None, :, 4] - vps[:, None, 4]) / drone.gimbal_rate_deg_s
    cost[1:, 1:] += np.maximum(turn, tilt)
    np.fill_diagonal(cost, 0.0)
    return cost


def order_by_flight_time(viewpoints: np.ndarray, takeoff: np.ndarray, drone, first=None, runs: int = 3):
    """Visiting order (V,) that minimises the flight time from take-off through every viewpoint and
    back (an asymmetric TSP on ``flight_time_costs``, solved by LKH: climbing and descending differ).

    Args:
        viewpoints: (V, 5) x, y, z (m), yaw, pitch (deg).
        takeoff: (3,) take-off point (m).
        drone: the drone (``drone.model.DroneSettings``).
        first: a viewpoint index the flight must visit first (the one the take-off point lies
            under, when the take-off point is defined by the first waypoint); None: any.
        runs: LKH restarts.
    """
    vps = np.asarray(viewpoints, dtype=float).reshape(-1, 5)
    n = len(vps)
    if n == 0:
        raise PlanningError("cannot order an empty viewpoint set")
    if not np.isfinite(vps).all():
        raise PlanningError("viewpoints must be finite to be ordered")
    if n == 1:
        return np.zeros(1, dtype=np.intp)
    cost = flight_time_costs(vps, takeoff, drone)
    if first is not None:
        # Take-off -> ``first`` is then a fixed cost: a closed tour over the viewpoints alone, whose
        # hop into ``first`` is the hop home from there (no penalty weights: LKH needs small ones).
        first = int(first)
        home = cost[1:, 0].copy()
        cost = cost[1:, 1:].copy()
        cost[:, first] = home
        cost[first, first] = 0.0
        start, offset = first, 0
    else:
        start, offset = 0, 1  # node 0 is the take-off point
    if len(cost) == 2:
        tour = [start, 1 - start]
    else:
        tour = elkai.DistanceMatrix(_int_matrix(cost)).solve_tsp(runs=int(runs))[:-1]
    k = tour.index(start)
    tour = tour[k:] + tour[:k]
    order = np.asarray(tour[offset:], dtype=np.intp) - offset
    if sorted(order.tolist()) != list(range(n)):
        raise PlanningError("TSP solver returned an invalid tour")
    return order
