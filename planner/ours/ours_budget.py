"""A crew's budget for the paper's planner: at most so many images, minutes of flight or batteries.

The paper plans to a target GSD and takes as many views as its objective asks for; it leaves a
budget open. Chosen here: the paper's stages run as they are (addition, repair, CMA-ES, culling,
detail then coverage); then, while the plan exceeds the budget, the views whose removal costs the
objective least are removed: per image for an image budget, per second of flight saved for a time or
battery budget (a view's stop and the detour to it, in the flight-time order of
``planner.trajectory.order_by_flight_time``). The objective is the one the plan reports as its
final R (Eq. 10 with the detail heuristics, every view seen within the coverage range), so the
views kept are the ones the objective values most for what they cost. A removal also pays for the
stereo partners it takes from the views that stay (``PartnerTerm``, ``planner.ours.stereo_partners``):
the objective alone left a 100-image tomb plan with 30 views of two partners or fewer, and the dense stage
made less of their walls (archive/pre_p1/planner_ours.md). A budget the plan already
fits leaves it as it is; a budget below what the model-coverage views alone need is refused, naming
the smallest that can be planned.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from drone.model import flight_summary
from planner.objective import ObjectiveState
from planner.ours.stereo_partners import added_shortfall, forecast
from planner.trajectory import flight_time_costs, order_by_flight_time
from scene.config import setting, typed_settings
from scene.plan import PlanningError

# Views removed per re-scoring of every view: a tenth of what is still to go (one near the budget),
# so a 200 -> 100 prune re-scores about 30 times, not 100.
_BATCH_SHARE = 0.1


@dataclass(frozen=True)
class BudgetLimit:
    """``budget_limit`` of ``conf/planner/ours.yaml``: any of images, flight minutes, batteries."""

    max_images: int | None = setting(None, low=1)
    max_flight_min: float | None = setting(None, above=0)
    max_batteries: int | None = setting(None, low=1)

    @property
    def active(self) -> bool:
        return any(v is not None for v in (self.max_images, self.max_flight_min, self.max_batteries))

    @property
    def timed(self) -> bool:
        return self.max_flight_min is not None or self.max_batteries is not None

    @classmethod
    def from_config(cls, node: Mapping | None) -> BudgetLimit:
        """From the ``budget_limit`` mapping; a ``PlanningError`` names a bad setting."""
        try:
            return typed_settings(cls, node or {}, "planner ours: budget_limit")
        except ValueError as exc:
            raise PlanningError(str(exc)) from exc

    def asked(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


def flight_of(viewpoints: np.ndarray, drone, takeoff: np.ndarray, tsp_runs: int) -> tuple[np.ndarray, dict]:
    """The flight-time order of ``viewpoints`` and the drone model's summary of it."""
    order = order_by_flight_time(viewpoints, takeoff, drone, runs=tsp_runs)
    return order, flight_summary(viewpoints[order], drone)


def _over(limit: BudgetLimit, n_views: int, flight: dict | None) -> bool:
    if limit.max_images is not None and n_views > limit.max_images:
        return True
    if flight is None:
        return False
    if limit.max_flight_min is not None and flight["flight_time_s"] > 60.0 * limit.max_flight_min:
        return True
    return limit.max_batteries is not None and flight["n_batteries"] > limit.max_batteries


def seconds_saved(viewpoints: np.ndarray, order: np.ndarray, takeoff: np.ndarray, drone) -> np.ndarray:
    """(V,) seconds each view's removal saves in the flight ``order``: its photo, its turn and the
    detour to it (the legs to and from it, minus the direct leg that replaces them)."""
    cost = flight_time_costs(viewpoints, takeoff, drone)
    path = np.concatenate([[0], np.asarray(order) + 1, [0]])
    saved = np.zeros(len(viewpoints))
    prev, here, nxt = path[:-2], path[1:-1], path[2:]
    saved[here - 1] = cost[prev, here] + cost[here, nxt] - cost[prev, nxt] + drone.photo_time_s
    return np.maximum(saved, 1e-3)


def fit_budget(
    state: ObjectiveState,
    viewpoints: np.ndarray,
    kinds: list[str],
    limit: BudgetLimit,
    drone,
    takeoff: np.ndarray,
    tsp_runs: int = 1,
    partners: PartnerTerm | None = None,
) -> tuple[np.ndarray, dict]:
    """Remove views of ``state`` (whose rows are ``viewpoints``) until the plan fits ``limit``.

    Args:
        state: the final objective over the plan's views (updated as views go).
        viewpoints: (V, 5) the plan's views; ``kinds`` their labels.
        limit: the budget.
        drone: the drone, for a time or battery budget (``drone.model.DroneSettings``).
        takeoff: (3,) take-off point (m).
        partners: the stereo partners the views will find (``planner.ours.stereo_partners``) and what a
            lost one costs; None: the views go by the objective alone.

    Returns:
        (V,) bool: the views kept; the record ``plan.json`` keeps (asked, what the unconstrained
        plan needed and what the kept views spend, R before and after).

    Raises:
        PlanningError: the budget is below what the model-coverage views alone need (the message
            names the setting and the smallest budget that can be planned).
    """
    vps = np.asarray(viewpoints, dtype=float)
    kept = np.ones(len(vps), bool)
    flight = flight_of(vps, drone, takeoff, tsp_runs)[1] if limit.timed else None
    before = {"n_images": len(vps), **({} if flight is None else _spent(flight))}
    _refuse_below_coverage(vps, kinds, limit, drone, takeoff, tsp_runs)
    r_before = state.R
    while _over(limit, int(kept.sum()), flight):
        rows = np.flatnonzero(kept)  # state row k is viewpoint rows[k]
        removal = np.array([state.evaluate_removal(k) for k in range(len(rows))])
        loss = np.maximum(state.R - removal, 0.0)
        n_views = len(rows)
        if flight is not None and not (limit.max_images is not None and n_views > limit.max_images):
            order = flight_of(vps[rows], drone, takeoff, tsp_runs)[0]
            saved = seconds_saved(vps[rows], order, takeoff, drone)
            loss = loss / saved
            to_go = math.ceil(
                max(flight["flight_time_s"] - _target_s(limit, drone), 0.0) / float(saved.mean())
            )
        else:
            to_go = n_views - int(limit.max_images)
        batch = max(1, min(n_views - 1, int(_BATCH_SHARE * to_go) or 1))
        victims = _pick_victims(loss, batch, None if partners is None else partners.among(rows))
        state.commit(victims)
        kept[rows[victims]] = False
        if limit.timed:
            flight = flight_of(vps[kept], drone, takeoff, tsp_runs)[1]
    spent = {"n_images": int(kept.sum()), **({} if flight is None else _spent(flight))}
    record = {
        "asked": limit.asked(),
        "unconstrained": before,
        "spent": spent,
        "R_before": r_before,
        "R_after": state.R,
    }
    if partners is not None:
        record["stereo_partners"] = {
            "weight": partners.weight,
            "unconstrained": forecast(partners.eligible, partners.num_partners),
            "spent": forecast(partners.among(np.flatnonzero(kept)).eligible, partners.num_partners),
        }
    return kept, record


@dataclass(frozen=True)
class PartnerTerm:
    """The stereo partners' part of the prune: a view's removal costs ``weight`` times the batch's
    mean objective loss for every partner slot it takes from a kept view (``added_shortfall``)."""

    eligible: np.ndarray  # (V, V) bool over the views fit_budget is given
    num_partners: int
    weight: float

    def among(self, rows: np.ndarray) -> PartnerTerm:
        return PartnerTerm(self.eligible[np.ix_(rows, rows)], self.num_partners, self.weight)


def _pick_victims(loss: np.ndarray, batch: int, partners: PartnerTerm | None) -> np.ndarray:
    """The ``batch`` views to remove: the least ``loss`` (ties: the first), or with ``partners``
    one at a time by loss plus the partner shortfall each adds, counted after the ones picked."""
    order = np.lexsort((np.arange(len(loss)), loss))
    if partners is None or partners.weight == 0:
        return order[:batch]
    alive = np.ones(len(loss), bool)
    scale = partners.weight * float(loss.mean())
    victims = []
    for _ in range(batch):
        cost = loss + scale * added_shortfall(partners.eligible, alive, partners.num_partners)
        cost[~alive] = np.inf
        victim = int(np.lexsort((np.arange(len(cost)), cost))[0])
        alive[victim] = False
        victims.append(victim)
    return np.asarray(victims)


def _target_s(limit: BudgetLimit, drone) -> float:
    """The flight time (s) a time or battery budget allows, batteries at their usable time each."""
    minutes = 60.0 * limit.max_flight_min if limit.max_flight_min is not None else math.inf
    batteries = limit.max_batteries * drone.usable_flight_s if limit.max_batteries is not None else math.inf
    return min(minutes, batteries)


def _spent(flight: dict) -> dict:
    return {"flight_min": flight["flight_time_s"] / 60.0, "n_batteries": int(flight["n_batteries"])}


def _refuse_below_coverage(vps, kinds, limit: BudgetLimit, drone, takeoff, tsp_runs: int) -> None:
    coverage = np.asarray([k == "coverage" for k in kinds])
    n_cov = int(coverage.sum())
    if not n_cov:
        return
    if limit.max_images is not None and limit.max_images < n_cov:
        raise PlanningError(
            f"planner ours: budget_limit.max_images={limit.max_images} is below the {n_cov} model-coverage "
            f"views this proxy needs; the smallest budget that can be planned is {n_cov} images"
        )
    if limit.timed:
        flight = flight_of(vps[coverage], drone, takeoff, tsp_runs)[1]
        if limit.max_flight_min is not None and flight["flight_time_s"] > 60.0 * limit.max_flight_min:
            raise PlanningError(
                f"planner ours: budget_limit.max_flight_min={limit.max_flight_min:g} is below the "
                f"{flight['flight_time_s'] / 60:.1f} min the model-coverage views alone fly; the smallest "
                f"budget that can be planned is {math.ceil(flight['flight_time_s'] / 6.0) / 10:.1f} min"
            )
        if limit.max_batteries is not None and flight["n_batteries"] > limit.max_batteries:
            raise PlanningError(
                f"planner ours: budget_limit.max_batteries={limit.max_batteries} is below the "
                f"{flight['n_batteries']} batteries the model-coverage views alone need; the smallest "
                f"budget that can be planned is {flight['n_batteries']}"
            )
