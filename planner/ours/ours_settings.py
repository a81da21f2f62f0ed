"""The settings of the paper's planner, checked and turned into metres once, before any planning.

``OursSettings.build(cfg, intrinsics)`` takes the resolved ``conf/planner/ours.yaml`` block
(``planner.ours.ours.resolve_params``) and the survey camera and returns everything ``planner.ours.ours``
needs in physical units, or raises ``PlanningError`` naming the first bad setting. The pipeline
builds it before the scene loads (``pipeline.settings``), so a bad setting costs no exploration.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from drone.model import DroneError, DroneSettings
from planner.heuristics import HeuristicParams
from planner.ours.candidates import CandidateSettings, FlightLimits
from planner.ours.cmaes_refine import CmaSettings
from planner.ours.ours_budget import BudgetLimit
from planner.ours.stereo_partners import PartnerRule
from planner.visibility import VisibilityLimits
from scene.camera import Intrinsics
from scene.plan import PlanningError


def _drone(node):

    try:
        return DroneSettings.from_config(node) if node is not None else DroneSettings.default()
    except DroneError as exc:
        raise PlanningError(f"planner ours: {exc}") from exc


def _partner_rule(node) -> PartnerRule:
    try:
        return PartnerRule.from_config(node)
    except ValueError as exc:
        raise PlanningError(str(exc)) from exc


def _number(cfg: Mapping, *path: str):
    value = cfg
    for p in path:
        value = value[p]
    return value


def _positive(cfg: Mapping, *path: str) -> float:
    value = _number(cfg, *path)
    if value is None or not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise PlanningError(f"planner ours: {'.'.join(path)} must be a positive number, got {value!r}")
    return float(value)


def _fraction(cfg: Mapping, *path: str) -> float:
    value = float(_number(cfg, *path))
    if not 0.0 <= value < 1.0:
        raise PlanningError(f"planner ours: {'.'.join(path)} must lie in [0, 1), got {value}")
    return value


def _match_settings(h: Mapping) -> dict:
    return {
        "matchable_overlap": bool(h["matchable_overlap"]),
        "match_angle_full_deg": float(h["match_angle_full_deg"]),
        "match_angle_zero_deg": float(h["match_angle_zero_deg"]),
        "match_scale_full": float(h["match_scale_full"]),
        "match_scale_zero": float(h["match_scale_zero"]),
    }


def detail_params(h: Mapping, d_t: float) -> HeuristicParams:
    """The detail pass's ``HeuristicParams`` from the ``heuristics`` settings and the target
    distance ``d_t`` (m): the one place the YAML's factors become metres."""
    tol = float(h["distance_tolerance"])
    return HeuristicParams(
        k_count=int(h["k_count"]),
        target_lo_m=d_t * (1.0 - tol),
        target_hi_m=d_t * (1.0 + tol),
        d_margin_m=float(h["d_margin_factor"]) * d_t,
        r_min=float(h["r_min"]),
        r_max=float(h["r_max"]),
        top_k=int(h["top_k"]),
        tau_edge=float(h["tau_edge"]),
        eps=float(h["eps"]),
        point_score=str(h["point_score"]),
        frontal_full_deg=float(h["frontal_full_deg"]),
        frontal_cone_deg=float(h["frontal_cone_deg"]),
        **_match_settings(h),
    )


@dataclass(frozen=True)
class OursSettings:
    """``planner.ours.ours``' settings in physical units (metres, degrees).

    Attributes:
        cfg: the resolved settings as given (recorded in ``Plan.info["parameters"]``).
        d_t: target distance (m) of ``target_gsd_m``; ``d_c`` the coverage views' distance (m).
        limits: altitude, clearance and gimbal limits of every candidate.
        det_params, cov_params: the detail and coverage passes' heuristics (Eq. 4-10).
        det_limits, cov_limits: the visibility ranges of the two passes.
        det_candidates, cov_candidates: the candidate patterns of the two passes.
        cma_det, cma_cov: the CMA-ES settings of the two passes.
        n_points: surface samples.
        takeoff: [x, y, z] (m), or None for the proxy's lowest corner on the ground.
        budget: the crew's budget (``planner.ours.ours_budget``); ``drone`` the drone it is flown on.
        partners: the dense stage's stereo-partner test the budget prune keeps views for
            (``planner.ours.stereo_partners``).
    """

    cfg: dict
    d_t: float
    d_c: float
    limits: FlightLimits
    det_params: HeuristicParams
    cov_params: HeuristicParams
    det_limits: VisibilityLimits
    cov_limits: VisibilityLimits
    det_candidates: CandidateSettings
    cov_candidates: CandidateSettings
    cma_det: CmaSettings
    cma_cov: CmaSettings
    n_points: int
    takeoff: tuple[float, float, float] | None
    budget: BudgetLimit
    drone: object
    partners: PartnerRule

    @classmethod
    def build(cls, cfg: dict, intrinsics: Intrinsics) -> OursSettings:
        """Check ``cfg`` (resolved ``conf/planner/ours.yaml``) and derive the settings; raise
        ``PlanningError`` at the first bad setting, naming it."""
        h, c, cv, cm = cfg["heuristics"], cfg["candidates"], cfg["coverage"], cfg["cmaes"]
        gsd = _positive(cfg, "target_gsd_m")
        d_t = intrinsics.distance_for_gsd(gsd)
        limits = FlightLimits(**cfg["limits"])
        for key in ("k_count", "top_k"):
            if int(h[key]) < 1:
                raise PlanningError(f"planner ours: heuristics.{key} must be >= 1, got {h[key]}")
        tol = _fraction(cfg, "heuristics", "distance_tolerance")
        d_margin = _positive(cfg, "heuristics", "d_margin_factor") * d_t
        if limits.min_clearance_m >= d_t * (1.0 + tol):
            raise PlanningError(
                f"impossible limits: limits.min_clearance_m = {limits.min_clearance_m} m is not below the "
                f"target distance range (d_t = {d_t:.2f} m from target_gsd_m = {gsd})"
            )
        det_params = detail_params(h, d_t)
        d_c = _positive(cfg, "coverage", "distance_factor") * d_t
        ctol = _fraction(cfg, "coverage", "distance_tolerance")
        cov_params = HeuristicParams(
            k_count=int(cv["k_count"]),
            target_lo_m=d_c * (1.0 - ctol),
            target_hi_m=d_c * (1.0 + ctol),
            d_margin_m=_positive(cfg, "coverage", "d_margin_factor") * d_t,
            r_min=det_params.r_min,
            r_max=det_params.r_max,
            top_k=det_params.top_k,
            tau_edge=det_params.tau_edge,
            eps=det_params.eps,
            coverage_closeness_weight=float(cv["closeness_weight"]),
            **_match_settings(h),
        )
        vis = cfg["visibility"]
        det_limits = VisibilityLimits(
            vis["min_distance_m"], det_params.target_hi_m + d_margin, vis["max_incidence_deg"]
        )
        cov_limits = VisibilityLimits(
            vis["min_distance_m"], cov_params.target_hi_m + cov_params.d_margin_m, vis["max_incidence_deg"]
        )
        for key in ("detail_rounds", "coverage_rounds"):
            if int(cfg[key]) < 0:
                raise PlanningError(f"planner ours: {key} must be >= 0, got {cfg[key]}")
        if int(cfg["detail_rounds"]) < 1:
            raise PlanningError("planner ours: detail_rounds must be >= 1")
        if int(cm["cluster_size"]) < 1 or int(cm["max_generations"]) < 0:
            raise PlanningError(
                f"planner ours: cmaes.cluster_size >= 1 and max_generations >= 0 needed, got {cm}"
            )
        takeoff = cfg["takeoff"]
        if takeoff is not None:
            arr = np.asarray(takeoff, dtype=float).reshape(-1)
            if arr.shape != (3,) or not np.isfinite(arr).all():
                raise PlanningError(f"planner ours: takeoff must be [x, y, z] in metres, got {takeoff}")
            takeoff = (float(arr[0]), float(arr[1]), float(arr[2]))
        fallbacks = tuple(float(f) for f in c["fallback_distance_factors"])
        tilts = tuple(float(t) for t in c["fallback_tilt_deg"])
        if not all(0.0 < f < 1.0 for f in fallbacks):
            raise PlanningError(
                "planner ours: candidates.fallback_distance_factors must lie in (0, 1), "
                f"got {list(fallbacks)}"
            )
        if not all(0.0 < t < 90.0 for t in tilts):
            raise PlanningError(
                f"planner ours: candidates.fallback_tilt_deg must lie in (0, 90), got {list(tilts)}"
            )
        det_candidates = CandidateSettings(
            distance_m=d_t,
            group_size=int(c["group_size"]),
            n_frontal=int(c["n_frontal"]),
            frontal_jitter_deg=float(c["frontal_jitter_deg"]),
            n_side=int(c["n_side"]),
            side_angle_deg=float(c["side_angle_deg"]),
            fallback_distance_factors=fallbacks,
            fallback_tilt_deg=tilts,
        )
        # Coverage candidates: the detail candidates' pattern at the coverage distance and group size.
        cov_candidates = replace(det_candidates, distance_m=d_c, group_size=int(cv["group_size"]))
        for s in (det_candidates, cov_candidates):
            if s.group_size < 1 or s.n_frontal < 1 or s.n_side < 0:
                raise PlanningError(
                    f"planner ours: need group_size >= 1, n_frontal >= 1, n_side >= 0, got {s}"
                )
        cma_det = CmaSettings(
            cluster_size=int(cm["cluster_size"]),
            max_generations=int(cm["max_generations"]),
            popsize=cm["popsize"],
            sigma0=float(cm["sigma0"]),
            position_box_m=float(cm["position_box_factor"]) * d_t,
            pitch_box_deg=float(cm["pitch_box_deg"]),
            yaw_box_deg=float(cm["yaw_box_deg"]),
        )
        cma_cov = replace(cma_det, position_box_m=float(cm["position_box_factor"]) * d_c)
        return cls(
            cfg=cfg,
            d_t=d_t,
            d_c=d_c,
            limits=limits,
            det_params=det_params,
            cov_params=cov_params,
            det_limits=det_limits,
            cov_limits=cov_limits,
            det_candidates=det_candidates,
            cov_candidates=cov_candidates,
            cma_det=cma_det,
            cma_cov=cma_cov,
            n_points=int(cfg["n_points"]),
            takeoff=takeoff,
            budget=BudgetLimit.from_config(cfg.get("budget_limit")),
            partners=_partner_rule(cfg.get("budget_partners")),
            drone=_drone(cfg.get("drone")),
        )
