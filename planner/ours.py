"""The paper's planner (Sec. III): iterative hybrid discrete-continuous viewpoint planning.

    sample 2048 points on the proxy
    detail pass, ``detail_rounds`` times:   add (k_count views per point, then weak-region repair)
                                            -> clustered CMA-ES -> cull
    coverage pass, ``coverage_rounds`` times: the same with model-coverage views (farther, scored
                                            by ``coverage_point_scores``; detail views stay fixed)
    order all views by an open TSP path from the take-off point

Every stage is recorded in ``Plan.info["stages"]`` (time, viewpoint counts, R and its parts,
objective evaluations, rays cast). ``info["final"]`` is Eq. 10 over every final view (coverage
visibility range); ``info["final_detail_pass"]`` is Eq. 10 of the detail views after the detail pass.
Parameters: ``conf/planner/ours.yaml`` (``DEFAULTS`` below mirrors it).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from planner.base import plain_params
from planner.budget import CONFIG_KEYS
from planner.candidates import (
    CandidateSettings,
    FlightLimits,
    detail_group,
    select_spread,
    side_pool,
    valid_candidates,
)
from planner.cmaes_refine import CmaSettings, refine_clusters
from planner.culling import cull
from planner.heuristics import HeuristicParams, global_score
from planner.objective import ObjectiveState
from planner.sampling import sample_surface, validate_proxy
from planner.trajectory import flight_length, order_viewpoints
from planner.visibility import VisibilityLimits, VisibilityModel
from scene.camera import Intrinsics
from scene.plan import Plan, PlanningError


def _yaml_defaults() -> dict:
    """``conf/planner/ours.yaml`` (the one place ours' settings and their reasons live), with the
    shared target GSD taken from ``conf/config.yaml``; the config-only keys
    (``planner.budget.CONFIG_KEYS``) dropped."""
    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[1] / "conf"
    survey = OmegaConf.load(conf / "config.yaml").survey
    merged = OmegaConf.create({"survey": survey, "ours": OmegaConf.load(conf / "planner" / "ours.yaml")})
    out = OmegaConf.to_container(merged.ours, resolve=True)
    return {k: v for k, v in out.items() if k not in CONFIG_KEYS}


DEFAULTS: dict = _yaml_defaults()


def resolve_params(params: Mapping | None) -> dict:
    """``DEFAULTS`` overridden by ``params`` (a Mapping or DictConfig); unknown keys are an error."""
    params = plain_params(params)
    out = copy.deepcopy(DEFAULTS)

    def merge(dst: dict, src: Mapping, prefix: str) -> None:
        for key, value in src.items():
            if key in CONFIG_KEYS and not prefix:
                continue
            if key not in dst:
                raise PlanningError(f"planner ours: unknown setting {prefix}{key}")
            if isinstance(dst[key], dict):
                if not isinstance(value, Mapping):
                    raise PlanningError(
                        f"planner ours: setting {prefix}{key} must be a mapping, got {value!r}"
                    )
                merge(dst[key], value, f"{prefix}{key}.")
            else:
                dst[key] = value

    merge(out, params, "")
    return out


def _positive(cfg: dict, *path: str) -> float:
    value = cfg
    for p in path:
        value = value[p]
    if value is None or not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise PlanningError(f"planner ours: {'.'.join(path)} must be a positive number, got {value!r}")
    return float(value)


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


class _Recorder:
    """Stage records: time, counts, R parts, evaluations and rays since the previous record."""

    def __init__(self, models: list[VisibilityModel]) -> None:
        self.models = models
        self.stages: list[dict] = []
        self.t = time.perf_counter()
        self.rays = 0

    def record(
        self, stage: str, round_index: int | None, state: ObjectiveState, kinds: list[str], **extra
    ) -> None:
        now = time.perf_counter()
        rays = sum(m.rays_cast for m in self.models)
        self.stages.append(
            {
                "stage": stage,
                "round": round_index,
                "time_s": now - self.t,
                "n_detail": kinds.count("detail"),
                "n_coverage": kinds.count("coverage"),
                "objective": state.mode,
                **state.parts(),
                "rays_cast": rays - self.rays,
                **extra,
            }
        )
        self.t, self.rays = now, rays


def _add_viewpoints(
    state: ObjectiveState,
    viewpoints: list[np.ndarray],
    kinds: list[str],
    kind: str,
    model: VisibilityModel,
    make_group,
    k_count: int,
    excluded: np.ndarray,
    repair_threshold: float,
    repair_max_groups: int,
    point_rows: bool,
    desc: str,
) -> dict:
    """Viewpoint addition: groups until every point has ``k_count`` views or is excluded, then
    weak-region repair (groups accepted only when R improves). ``viewpoints``/``kinds`` grow."""
    n_pts = state.n_points
    selected = np.zeros(n_pts, bool)
    added = 0
    need = (state.count < k_count) & ~excluded
    bar = tqdm(total=int(need.sum()), desc=f"{desc}: add", leave=False, disable=None)
    while True:
        need = (state.count < k_count) & ~excluded & ~selected
        if not need.any():
            break
        cand = np.flatnonzero(need)
        keys = (cand, state.count[cand], state.point_score[cand])
        if state.point_weights is not None:  # ours_plus: the most unsure samples first
            keys += (-state.point_weights[cand],)
        pick = int(cand[np.lexsort(keys)[0]])
        selected[pick] = True
        group = make_group(pick)
        if group is not None:
            obs = model.observe(group)
            state.commit([], obs, new_point_rows=np.full(len(group), point_rows))
            viewpoints.extend(group)
            kinds.extend([kind] * len(group))
            added += len(group)
        if group is None or state.count[pick] < k_count:
            excluded[pick] = True
        bar.update(1)
    bar.close()

    tried = accepted = 0
    selected[:] = False
    for _ in tqdm(range(int(repair_max_groups)), desc=f"{desc}: repair", leave=False, disable=None):
        weak = (state.point_score < repair_threshold) & ~excluded & ~selected
        if not weak.any():
            break
        cand = np.flatnonzero(weak)
        urgency = state.point_score[cand]  # the weakest first ...
        if state.point_weights is not None:  # ... ours_plus: the largest weighted deficit first
            urgency = (urgency - repair_threshold) * state.point_weights[cand]
        pick = int(cand[np.lexsort((cand, urgency))[0]])
        selected[pick] = True
        group = make_group(pick)
        if group is None:
            excluded[pick] = True
            continue
        obs = model.observe(group)
        npr = np.full(len(group), point_rows)
        tried += 1
        if state.evaluate([], obs, 1, new_point_rows=npr).R[0] > state.R + 1e-9:
            state.commit([], obs, new_point_rows=npr)
            viewpoints.extend(group)
            kinds.extend([kind] * len(group))
            added += len(group)
            accepted += 1
    return {
        "added": added,
        "repair_groups_tried": tried,
        "repair_groups_accepted": accepted,
        "excluded_points": int(excluded.sum()),
    }


def _coverage_group(point_index, state, model, limits, settings: CandidateSettings):
    """A model-coverage group: the frontal candidate with the best coverage objective, then
    angularly spread side candidates."""
    vps, dirs, frontal, parent = valid_candidates(point_index, model, limits, settings)
    if len(vps) == 0:
        return None
    pool = np.flatnonzero(frontal) if frontal.any() else np.arange(len(vps))
    obs = model.observe(vps[pool])
    gains = state.evaluate([], obs, len(pool), new_point_rows=np.ones(1, bool)).R
    first = int(pool[int(np.argmax(gains))])
    return vps[select_spread(dirs, first, settings.group_size, allowed=side_pool(frontal, parent, first))]


@dataclass(frozen=True)
class PlanExtensions:
    """What ``ours_plus`` adds to the paper's planner (``planner/ours_plus.py``); None: the paper's.

    Attributes:
        weigh_samples: (points, normals) (P, 3) each -> (weights (P,), record for ``Plan.info``).
        time_term: take-off point (3,) -> a ``planner.flight_time_term.FlightTimeTerm`` without its
            reference flight, which the views of the first addition set.
        planner: the name the plan carries.
    """

    weigh_samples: Callable | None = None
    time_term: Callable | None = None
    planner: str = "ours"


def plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan:
    """Plan detail and model-coverage viewpoints on ``proxy`` and order them into a flight.

    Args:
        proxy: proxy mesh in world metres (Z up, ground at z = 0).
        intrinsics: the survey camera.
        params: settings (``conf/planner/ours.yaml``); missing ones take ``DEFAULTS``.
        seed: seeds the surface sampling and every CMA-ES run (same seed, same plan).

    Returns:
        the ordered ``Plan`` (kinds ``detail`` / ``coverage``); ``info`` holds the parameters,
        per-stage records, the final R and its parts, timings and the flight length.

    Raises:
        PlanningError: empty or degenerate proxy, impossible limits, no valid viewpoint.
    """
    # One BLAS thread: the hot path is many small products and CMA-ES's 60 x 60 eigendecompositions,
    # which a multi-threaded OpenBLAS slows down by an order of magnitude on a shared 2-core machine.
    with threadpool_limits(limits=1):
        return plan_with(proxy, intrinsics, resolve_params(params), seed, PlanExtensions())


def plan_with(
    proxy: trimesh.Trimesh, intrinsics: Intrinsics, cfg: dict, seed: int, ext: PlanExtensions
) -> Plan:
    """``plan`` with resolved parameters ``cfg`` and the ``ext`` additions (call under one BLAS thread)."""
    t_start = time.perf_counter()
    validate_proxy(proxy)
    h, c, cv = cfg["heuristics"], cfg["candidates"], cfg["coverage"]
    gsd = _positive(cfg, "target_gsd_m")
    d_t = intrinsics.distance_for_gsd(gsd)
    limits = FlightLimits(**cfg["limits"])
    for key in ("k_count", "top_k"):
        if int(h[key]) < 1:
            raise PlanningError(f"planner ours: heuristics.{key} must be >= 1, got {h[key]}")
    tol = float(h["distance_tolerance"])
    if not 0.0 <= tol < 1.0:
        raise PlanningError(f"planner ours: heuristics.distance_tolerance must lie in [0, 1), got {tol}")
    d_margin = _positive(cfg, "heuristics", "d_margin_factor") * d_t
    if limits.min_clearance_m >= d_t * (1.0 + tol):
        raise PlanningError(
            f"impossible limits: limits.min_clearance_m = {limits.min_clearance_m} m is not below the "
            f"target distance range (d_t = {d_t:.2f} m from target_gsd_m = {gsd})"
        )
    det_params = detail_params(h, d_t)
    d_c = _positive(cfg, "coverage", "distance_factor") * d_t
    ctol = float(cv["distance_tolerance"])
    if not 0.0 <= ctol < 1.0:
        raise PlanningError(f"planner ours: coverage.distance_tolerance must lie in [0, 1), got {ctol}")
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
    n_points = int(cfg["n_points"])
    for key in ("detail_rounds", "coverage_rounds"):
        if int(cfg[key]) < 0:
            raise PlanningError(f"planner ours: {key} must be >= 0, got {cfg[key]}")
    if int(cfg["detail_rounds"]) < 1:
        raise PlanningError("planner ours: detail_rounds must be >= 1")
    cm = cfg["cmaes"]
    if int(cm["cluster_size"]) < 1 or int(cm["max_generations"]) < 0:
        raise PlanningError(
            f"planner ours: cmaes.cluster_size >= 1 and max_generations >= 0 needed, got {cm}"
        )

    takeoff = cfg["takeoff"]
    if takeoff is None:
        lo = proxy.bounds[0]
        takeoff = [float(lo[0]), float(lo[1]), 0.0]
    takeoff = np.asarray(takeoff, dtype=float).reshape(-1)
    if takeoff.shape != (3,) or not np.isfinite(takeoff).all():
        raise PlanningError(f"planner ours: takeoff must be [x, y, z] in metres, got {cfg['takeoff']}")
    time_term = None if ext.time_term is None else ext.time_term(takeoff)

    t0 = time.perf_counter()
    points, normals = sample_surface(proxy, n_points, seed)
    weights, evidence = (None, None) if ext.weigh_samples is None else ext.weigh_samples(points, normals)
    det_model = VisibilityModel(
        proxy, points, normals, intrinsics, det_limits, vis["ray_offset_m"], vis["image_margin_px"]
    )
    cov_model = det_model.with_limits(cov_limits)
    rec = _Recorder([det_model, cov_model])
    state = ObjectiveState(det_params, n_points, mode="detail", points=points, point_weights=weights)
    rec.record("sample", None, state, [], sample_time_s=time.perf_counter() - t0)

    fallbacks = tuple(float(f) for f in c["fallback_distance_factors"])
    tilts = tuple(float(t) for t in c["fallback_tilt_deg"])
    if not all(0.0 < f < 1.0 for f in fallbacks):
        raise PlanningError(
            f"planner ours: candidates.fallback_distance_factors must lie in (0, 1), got {list(fallbacks)}"
        )
    if not all(0.0 < t < 90.0 for t in tilts):
        raise PlanningError(
            f"planner ours: candidates.fallback_tilt_deg must lie in (0, 90), got {list(tilts)}"
        )
    det_settings = CandidateSettings(
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
    cov_settings = replace(det_settings, distance_m=d_c, group_size=int(cv["group_size"]))
    for s in (det_settings, cov_settings):
        if s.group_size < 1 or s.n_frontal < 1 or s.n_side < 0:
            raise PlanningError(f"planner ours: need group_size >= 1, n_frontal >= 1, n_side >= 0, got {s}")
    cma_det = CmaSettings(
        cluster_size=int(cm["cluster_size"]),
        max_generations=int(cm["max_generations"]),
        popsize=cm["popsize"],
        sigma0=float(cm["sigma0"]),
        position_box_m=float(cm["position_box_factor"]) * d_t,
        pitch_box_deg=float(cm["pitch_box_deg"]),
        yaw_box_deg=float(cm["yaw_box_deg"]),
    )
    cma_cov = CmaSettings(**{**cma_det.__dict__, "position_box_m": float(cm["position_box_factor"]) * d_c})
    cul = cfg["culling"]
    cull_tol = float(cul["tolerance"]) * n_points

    def cull_unless_off(objective: ObjectiveState, cullable: np.ndarray, vps: list, desc: str):
        if not bool(cul["enabled"]):  # the ablation without culling
            return np.ones(len(cullable), bool), {"removed_empty": 0, "removed_redundant": 0}
        return cull(
            objective,
            cullable,
            float(cul["overlap_threshold"]),
            cull_tol,
            desc=desc,
            time_term=time_term,
            viewpoints=np.asarray(vps),
        )

    # ------------------------------------------------------------------ detail viewpoints
    viewpoints: list[np.ndarray] = []
    kinds: list[str] = []
    excluded = np.zeros(n_points, bool)
    add = cfg["addition"]
    for r in range(int(cfg["detail_rounds"])):
        stats = _add_viewpoints(
            state,
            viewpoints,
            kinds,
            "detail",
            det_model,
            lambda i: detail_group(i, det_model, limits, det_settings),
            det_params.k_count,
            excluded,
            float(add["repair_threshold"]),
            int(add["repair_max_groups"]),
            True,
            f"detail round {r + 1}",
        )
        if time_term is not None and time_term.reference_s is None and viewpoints:
            time_term = time_term.referenced(np.asarray(viewpoints))
        if not viewpoints:
            raise PlanningError(
                "no valid viewpoint anywhere: every candidate breaks the altitude, clearance or gimbal "
                f"limits or cannot see its point (limits={cfg['limits']}, d_t={d_t:.2f} m)"
            )
        rec.record("detail_addition", r, state, kinds, **stats)
        vps = np.asarray(viewpoints)
        stats = refine_clusters(
            state,
            vps,
            np.arange(len(vps)),
            det_model,
            limits,
            cma_det,
            seed,
            r,
            desc=f"detail round {r + 1}: CMA-ES",
            time_term=time_term,
        )
        viewpoints = list(vps)
        rec.record("detail_cmaes", r, state, kinds, **_drop_time(stats))
        kept, stats = cull_unless_off(
            state, np.ones(len(viewpoints), bool), viewpoints, f"detail round {r + 1}: cull"
        )
        viewpoints = [v for v, k in zip(viewpoints, kept, strict=True) if k]
        kinds = [s for s, k in zip(kinds, kept, strict=True) if k]
        rec.record("detail_culling", r, state, kinds, **_drop_time(stats))
    if not viewpoints:
        raise PlanningError("culling removed every viewpoint: none sees a sampled point")

    detail_parts = state.parts()  # Eq. 10 over the detail views, detail range

    # ------------------------------------------------------------------ model-coverage viewpoints
    cstate = ObjectiveState(cov_params, n_points, mode="coverage", points=points, point_weights=weights)
    cstate.reset(cov_model.observe(np.asarray(viewpoints)), point_rows=np.zeros(len(viewpoints), bool))
    rec.record("coverage_start", None, cstate, kinds)
    cov_excluded = np.zeros(n_points, bool)
    for r in range(int(cfg["coverage_rounds"])):
        stats = _add_viewpoints(
            cstate,
            viewpoints,
            kinds,
            "coverage",
            cov_model,
            lambda i: _coverage_group(i, cstate, cov_model, limits, cov_settings),
            cov_params.k_count,
            cov_excluded,
            float(cv["repair_threshold"]),
            int(cv["repair_max_groups"]),
            True,
            f"coverage round {r + 1}",
        )
        rec.record("coverage_addition", r, cstate, kinds, **stats)
        vps = np.asarray(viewpoints)
        cov_rows = np.flatnonzero(np.asarray(kinds) == "coverage")
        stats = refine_clusters(
            cstate,
            vps,
            cov_rows,
            cov_model,
            limits,
            cma_cov,
            seed,
            100 + r,
            point_rows=True,
            desc=f"coverage round {r + 1}: CMA-ES",
            time_term=time_term,
        )
        viewpoints = list(vps)
        rec.record("coverage_cmaes", r, cstate, kinds, **_drop_time(stats))
        kept, stats = cull_unless_off(
            cstate, np.asarray(kinds) == "coverage", viewpoints, f"coverage round {r + 1}: cull"
        )
        viewpoints = [v for v, k in zip(viewpoints, kept, strict=True) if k]
        kinds = [s for s, k in zip(kinds, kept, strict=True) if k]
        rec.record("coverage_culling", r, cstate, kinds, **_drop_time(stats))

    # ------------------------------------------------------------------ final score and order
    vps = np.asarray(viewpoints)
    # The final R: Eq. 10 with the detail heuristics over every view, seen within the coverage
    # range (the detail range would make every coverage view see nothing). Far coverage views widen
    # the angular spread of Eq. 4, so this is usually below ``final_detail_pass``.
    final_obs = cov_model.observe(vps)
    final = global_score(
        final_obs.visible,
        final_obs.distance,
        final_obs.direction,
        final_obs.cos_incidence,
        det_params,
        points,
    )
    t0 = time.perf_counter()
    order = order_viewpoints(vps[:, :3], takeoff, runs=int(cfg["tsp_runs"]))
    vps, kinds = vps[order], [kinds[i] for i in order]
    tsp_time = time.perf_counter() - t0
    rays = det_model.rays_cast + cov_model.rays_cast
    evaluations = state.evaluations + cstate.evaluations
    total = time.perf_counter() - t_start
    info = {
        "parameters": cfg,
        "seed": int(seed),
        "target_distance_m": d_t,
        "coverage_distance_m": d_c,
        "n_points": n_points,
        "excluded_points": int(excluded.sum()),
        "coverage_excluded_points": int(cov_excluded.sum()),
        "final": final,
        "final_detail_pass": detail_parts,
        "stages": rec.stages,
        "timings_s": {**_stage_times(rec.stages), "tsp": tsp_time, "total": total},
        "objective_evaluations": evaluations,
        "rays_cast": rays,
        "takeoff": takeoff.tolist(),
        "flight_length_from_takeoff_m": flight_length(vps[:, :3], takeoff),
        "plan_time_s": total,
    }
    if evidence is not None:
        info["evidence"] = evidence
    if time_term is not None:
        info["time_weight_per_pct"] = time_term.weight_per_pct
        info["time_reference_s"] = time_term.reference_s
    return Plan(viewpoints=vps, kinds=kinds, planner=ext.planner, info=info)


def _drop_time(stats: dict) -> dict:
    return {k: v for k, v in stats.items() if k != "time_s"}


def _stage_times(stages: list[dict]) -> dict:
    out: dict[str, float] = {}
    for s in stages:
        name = s["stage"]
        out[name] = out.get(name, 0.0) + float(s["time_s"])
    return out
