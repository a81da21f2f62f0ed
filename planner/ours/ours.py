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
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from omegaconf import OmegaConf
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from planner.base import plain_params
from planner.budget import CONFIG_KEYS
from planner.heuristics import global_score
from planner.objective import ObjectiveState
from planner.ours.candidates import (
    CandidateSettings,
    detail_group,
    select_spread,
    side_pool,
    valid_candidates,
)
from planner.ours.cmaes_refine import refine_clusters
from planner.ours.culling import cull
from planner.ours.ours_budget import PartnerTerm, fit_budget
from planner.ours.ours_settings import OursSettings
from planner.ours.stereo_partners import partner_matrix
from planner.sampling import sample_surface, validate_proxy
from planner.trajectory import flight_length, order_viewpoints
from planner.visibility import VisibilityModel
from scene.camera import Intrinsics
from scene.plan import Plan, PlanningError


def _yaml_defaults() -> dict:
    """``conf/planner/ours.yaml`` (the one place ours' settings and their reasons live), with the
    shared target GSD taken from ``conf/config.yaml``, the drone from ``conf/drone`` and the dense
    stage's partner test from ``conf/reconstruct``; the config-only keys
    (``planner.budget.CONFIG_KEYS``) dropped."""
    conf = Path(__file__).resolve().parents[2] / "conf"
    survey = OmegaConf.load(conf / "config.yaml").survey
    drone = OmegaConf.load(conf / "drone" / "default.yaml")
    reconstruct = OmegaConf.load(conf / "reconstruct" / "default.yaml")
    merged = OmegaConf.create(
        {
            "survey": survey,
            "drone": drone,
            "reconstruct": reconstruct,
            "ours": OmegaConf.load(conf / "planner" / "ours.yaml"),
        }
    )
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


# A budget above the plan's own size adds at most this many detail views per sampled point.
MAX_FILL_VIEWS = 4


def check_params(params: Mapping | None, intrinsics: Intrinsics) -> None:
    """Refuse a bad setting before any work (the planner contract, ``planner.base``)."""
    OursSettings.build(resolve_params(params), intrinsics)


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
    """What ``ours_plus`` adds to the paper's planner (``planner/ours/ours_plus.py``); None: the paper's.

    Attributes:
        weigh_samples: (points, normals) (P, 3) each -> (weights (P,), record for ``Plan.info``).
        time_term: take-off point (3,) -> a ``planner.ours.flight_time_term.FlightTimeTerm`` without its
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


@dataclass
class _Run:
    """What the passes of one ``plan_with`` share: its settings, models, objective and views so far."""

    cfg: dict
    settings: OursSettings
    seed: int
    takeoff: np.ndarray
    time_term: object
    points: np.ndarray
    weights: np.ndarray | None
    evidence: dict | None
    det_model: VisibilityModel
    cov_model: VisibilityModel
    rec: _Recorder
    state: ObjectiveState
    viewpoints: list
    kinds: list
    excluded: np.ndarray

    def cull_unless_off(self, objective: ObjectiveState, cullable: np.ndarray, desc: str):
        """Cull the ``cullable`` views (nothing where culling is off: the ablation without it)."""
        cul = self.cfg["culling"]
        if not bool(cul["enabled"]):  # the ablation without culling
            return np.ones(len(cullable), bool), {"removed_empty": 0, "removed_redundant": 0}
        return cull(
            objective,
            cullable,
            float(cul["overlap_threshold"]),
            float(cul["tolerance"]) * self.settings.n_points,
            desc=desc,
            time_term=self.time_term,
            viewpoints=np.asarray(self.viewpoints),
        )

    def keep(self, kept: np.ndarray) -> None:
        self.viewpoints = [v for v, k in zip(self.viewpoints, kept, strict=True) if k]
        self.kinds = [s for s, k in zip(self.kinds, kept, strict=True) if k]

    def add_detail(self, k_count: int, excluded_points: np.ndarray, repair_groups: int, desc: str) -> dict:
        settings = self.settings
        return _add_viewpoints(
            self.state,
            self.viewpoints,
            self.kinds,
            "detail",
            self.det_model,
            lambda i: detail_group(i, self.det_model, settings.limits, settings.det_candidates),
            k_count,
            excluded_points,
            float(self.cfg["addition"]["repair_threshold"]),
            repair_groups,
            True,
            desc,
        )


def _start(proxy: trimesh.Trimesh, intrinsics: Intrinsics, cfg: dict, seed: int, ext: PlanExtensions) -> _Run:
    """Settings, take-off, the proxy's samples (weighed by ``ext``), both visibility models and the
    detail objective, empty."""
    settings = OursSettings.build(cfg, intrinsics)
    validate_proxy(proxy)
    n_points = settings.n_points
    vis = cfg["visibility"]
    takeoff = settings.takeoff
    if takeoff is None:
        lo = proxy.bounds[0]
        takeoff = [float(lo[0]), float(lo[1]), 0.0]
    takeoff = np.asarray(takeoff, dtype=float).reshape(-1)
    time_term = None if ext.time_term is None else ext.time_term(takeoff)

    t0 = time.perf_counter()
    points, normals = sample_surface(proxy, n_points, seed)
    weights, evidence = (None, None) if ext.weigh_samples is None else ext.weigh_samples(points, normals)
    det_model = VisibilityModel(
        proxy, points, normals, intrinsics, settings.det_limits, vis["ray_offset_m"], vis["image_margin_px"]
    )
    cov_model = det_model.with_limits(settings.cov_limits)
    rec = _Recorder([det_model, cov_model])
    state = ObjectiveState(settings.det_params, n_points, mode="detail", points=points, point_weights=weights)
    rec.record("sample", None, state, [], sample_time_s=time.perf_counter() - t0)
    return _Run(
        cfg,
        settings,
        seed,
        takeoff,
        time_term,
        points,
        weights,
        evidence,
        det_model,
        cov_model,
        rec,
        state,
        [],
        [],
        np.zeros(n_points, bool),
    )


def _detail_pass(run: _Run) -> dict:
    """``detail_rounds`` of addition, CMA-ES and culling; Eq. 10 over the detail views after it."""
    cfg, settings, state, rec = run.cfg, run.settings, run.state, run.rec
    for r in range(int(cfg["detail_rounds"])):
        stats = run.add_detail(
            settings.det_params.k_count,
            run.excluded,
            int(cfg["addition"]["repair_max_groups"]),
            f"detail round {r + 1}",
        )
        if run.time_term is not None and run.time_term.reference_s is None and run.viewpoints:
            run.time_term = run.time_term.referenced(np.asarray(run.viewpoints))
        if not run.viewpoints:
            raise PlanningError(
                "no valid viewpoint anywhere: every candidate breaks the altitude, clearance or gimbal "
                f"limits or cannot see its point (limits={cfg['limits']}, d_t={settings.d_t:.2f} m)"
            )
        rec.record("detail_addition", r, state, run.kinds, **stats)
        vps = np.asarray(run.viewpoints)
        stats = refine_clusters(
            state,
            vps,
            np.arange(len(vps)),
            run.det_model,
            settings.limits,
            settings.cma_det,
            run.seed,
            r,
            desc=f"detail round {r + 1}: CMA-ES",
            time_term=run.time_term,
        )
        run.viewpoints = list(vps)
        rec.record("detail_cmaes", r, state, run.kinds, **_drop_time(stats))
        kept, stats = run.cull_unless_off(
            state, np.ones(len(run.viewpoints), bool), f"detail round {r + 1}: cull"
        )
        run.keep(kept)
        rec.record("detail_culling", r, state, run.kinds, **_drop_time(stats))
    if not run.viewpoints:
        raise PlanningError("culling removed every viewpoint: none sees a sampled point")
    return state.parts()  # Eq. 10 over the detail views, detail range


def _coverage_pass(run: _Run) -> tuple[ObjectiveState, np.ndarray]:
    """``coverage_rounds`` of model-coverage views (the detail views fixed); their objective and
    the samples excluded."""
    cfg, settings, rec = run.cfg, run.settings, run.rec
    cv, cov_model, n_points = cfg["coverage"], run.cov_model, settings.n_points
    cstate = ObjectiveState(
        settings.cov_params, n_points, mode="coverage", points=run.points, point_weights=run.weights
    )
    cstate.reset(
        cov_model.observe(np.asarray(run.viewpoints)), point_rows=np.zeros(len(run.viewpoints), bool)
    )
    rec.record("coverage_start", None, cstate, run.kinds)
    cov_excluded = np.zeros(n_points, bool)
    for r in range(int(cfg["coverage_rounds"])):
        stats = _add_viewpoints(
            cstate,
            run.viewpoints,
            run.kinds,
            "coverage",
            cov_model,
            lambda i: _coverage_group(i, cstate, cov_model, settings.limits, settings.cov_candidates),
            settings.cov_params.k_count,
            cov_excluded,
            float(cv["repair_threshold"]),
            int(cv["repair_max_groups"]),
            True,
            f"coverage round {r + 1}",
        )
        rec.record("coverage_addition", r, cstate, run.kinds, **stats)
        vps = np.asarray(run.viewpoints)
        cov_rows = np.flatnonzero(np.asarray(run.kinds) == "coverage")
        stats = refine_clusters(
            cstate,
            vps,
            cov_rows,
            cov_model,
            settings.limits,
            settings.cma_cov,
            run.seed,
            100 + r,
            point_rows=True,
            desc=f"coverage round {r + 1}: CMA-ES",
            time_term=run.time_term,
        )
        run.viewpoints = list(vps)
        rec.record("coverage_cmaes", r, cstate, run.kinds, **_drop_time(stats))
        kept, stats = run.cull_unless_off(
            cstate, np.asarray(run.kinds) == "coverage", f"coverage round {r + 1}: cull"
        )
        run.keep(kept)
        rec.record("coverage_culling", r, cstate, run.kinds, **_drop_time(stats))
    return cstate, cov_excluded


def _budget_pass(run: _Run) -> tuple[np.ndarray, list[str], dict | None]:
    """The crew's budget: fill up to its image cap (one more detail view per sample at a time),
    then prune to its limits keeping stereo partners; the views, their kinds and the record."""
    settings, det_params, n_points = run.settings, run.settings.det_params, run.settings.n_points
    cap = settings.budget.max_images
    k_fill = det_params.k_count
    n_paper = len(run.viewpoints)  # the paper's plan, before a fill
    while cap is not None and len(run.viewpoints) < cap and k_fill < det_params.k_count + MAX_FILL_VIEWS:
        # A budget above what the objective asks for: one more detail view per sampled point.
        k_fill += 1
        stats = run.add_detail(k_fill, np.zeros(n_points, bool), 0, f"budget fill (k {k_fill})")
        run.rec.record("budget_fill", k_fill, run.state, run.kinds, **stats)
        if not stats["added"]:
            break
    vps, kinds = np.asarray(run.viewpoints), run.kinds
    if not settings.budget.active:
        return vps, kinds, None
    t0 = time.perf_counter()
    final_state = ObjectiveState(
        det_params, n_points, mode="detail", points=run.points, point_weights=run.weights
    )
    unconstrained_obs = run.cov_model.observe(vps)
    final_state.reset(unconstrained_obs)
    rule = settings.partners
    eligible = partner_matrix(unconstrained_obs.visible, unconstrained_obs.direction, vps, rule)
    partners = PartnerTerm(eligible, rule.num_partners, rule.weight)
    kept, budget = fit_budget(
        final_state,
        vps,
        kinds,
        settings.budget,
        settings.drone,
        run.takeoff,
        int(run.cfg["tsp_runs"]),
        partners,
    )
    # "unconstrained": what the objective asked for (after a fill: the filled plan, before the prune).
    budget |= {
        "paper_plan_images": n_paper,
        "unconstrained_viewpoints": vps.tolist(),
        "time_s": time.perf_counter() - t0,
    }
    return vps[kept], [k for k, keep in zip(kinds, kept, strict=True) if keep], budget


def plan_with(
    proxy: trimesh.Trimesh, intrinsics: Intrinsics, cfg: dict, seed: int, ext: PlanExtensions
) -> Plan:
    """``plan`` with resolved parameters ``cfg`` and the ``ext`` additions (call under one BLAS thread)."""
    t_start = time.perf_counter()
    run = _start(proxy, intrinsics, cfg, seed, ext)
    detail_parts = _detail_pass(run)
    cstate, cov_excluded = _coverage_pass(run)
    vps, kinds, budget = _budget_pass(run)
    settings, takeoff, time_term = run.settings, run.takeoff, run.time_term

    # ------------------------------------------------------------------ final score and order
    # The final R: Eq. 10 with the detail heuristics over every view, seen within the coverage
    # range (the detail range would make every coverage view see nothing). Far coverage views widen
    # the angular spread of Eq. 4, so this is usually below ``final_detail_pass``.
    final_obs = run.cov_model.observe(vps)
    final = global_score(
        final_obs.visible,
        final_obs.distance,
        final_obs.direction,
        final_obs.cos_incidence,
        settings.det_params,
        run.points,
    )
    t0 = time.perf_counter()
    order = order_viewpoints(vps[:, :3], takeoff, runs=int(cfg["tsp_runs"]))
    vps, kinds = vps[order], [kinds[i] for i in order]
    tsp_time = time.perf_counter() - t0
    rays = run.det_model.rays_cast + run.cov_model.rays_cast
    evaluations = run.state.evaluations + cstate.evaluations
    total = time.perf_counter() - t_start
    info = {
        "parameters": cfg,
        "seed": int(seed),
        "target_distance_m": settings.d_t,
        "coverage_distance_m": settings.d_c,
        "n_points": settings.n_points,
        "excluded_points": int(run.excluded.sum()),
        "coverage_excluded_points": int(cov_excluded.sum()),
        "final": final,
        "final_detail_pass": detail_parts,
        "stages": run.rec.stages,
        "timings_s": {**_stage_times(run.rec.stages), "tsp": tsp_time, "total": total},
        "objective_evaluations": evaluations,
        "rays_cast": rays,
        "takeoff": takeoff.tolist(),
        "flight_length_from_takeoff_m": flight_length(vps[:, :3], takeoff),
        "plan_time_s": total,
    }
    if budget is not None:
        info["budget"] = budget
    if run.evidence is not None:
        info["evidence"] = run.evidence
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
