"""One cell of the study, end to end: the pipeline as a library.

    settings -> scene -> proxy -> plan (+ check, forecast, flight time) -> render -> reconstruct
    -> evaluate -> metrics.json

``run_cell(cfg, run_dir, record)`` chains the stages; each stage is a function that takes its own
config group and writes its artefact into the run directory (``plan/``, ``images/``, ``recon/``,
``eval/``). ``run_and_record`` is what ``run.py`` calls: it runs the cell and writes ``metrics.json``
whether the cell succeeded or failed. The planner only ever sees the proxy; the reconstruction only
sees images and GNSS-like noisy camera positions.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import hydra
import numpy as np
import trimesh
from omegaconf import DictConfig, OmegaConf

from drone.model import DroneSettings, default_takeoff, flight_summary
from evaluate.record import code_revision, write_metrics
from evaluate.run import evaluate_reconstruction
from evaluate.settings import EvaluationSettings
from mission.envelope import keep_within_heights
from mission.validate import validate_plan
from pipeline.forecast import predicted_coverage
from pipeline.proxy import proxy_stage
from pipeline.settings import CellSettings, cell_settings, scene_label
from planner.budget import DEFAULT_LEVEL
from planner.trajectory import order_by_flight_time
from reconstruct.pipeline import oracle_flight, reconstruct_flight
from reconstruct.settings import ReconstructSettings
from reconstruct.timing import cpu_seconds
from render import render_flight
from scene.camera import Intrinsics
from scene.plan import Plan, write_plan
from scene.registry import load_scene

log = logging.getLogger("run")

FORECAST_CRITERIA = ">= 3 planned views within 1.3 d_t and 60 deg of the normal (pipeline.forecast)"


class CellFailed(RuntimeError):
    """The cell failed; metrics.json records the failure (a sweep reports it and goes on)."""


def planned(proxy: trimesh.Trimesh, settings: CellSettings, out_dir: Path) -> tuple[Plan, dict]:
    """``plan_stage`` with a cell's settings (its planner, camera, drone, evaluation and GSD)."""
    planner = settings.planner
    return plan_stage(
        proxy,
        settings.intrinsics,
        planner.target,
        planner.params,
        settings.seed,
        settings.drone,
        settings.evaluation,
        settings.target_gsd_m,
        out_dir,
        planner.flight_order,
    )


def plan_stage(
    proxy: trimesh.Trimesh,
    intrinsics: Intrinsics,
    target: str,
    params: Mapping,
    seed: int,
    drone: DroneSettings,
    evaluation: EvaluationSettings,
    target_gsd_m: float,
    out_dir: Path,
    flight_order: str = "planner",
) -> tuple[Plan, dict]:
    """Plan on the proxy, check it against the drone, forecast it, time it; write ``out_dir``.

    Args:
        target: the planner's ``plan`` function (``planner._target_``).
        params: its parameters (``pipeline.settings.planner_setup``).
        evaluation: the surface classes the forecast reports (``evaluate``).
        target_gsd_m: the survey's GSD (m/px): the forecast's d_t.
        out_dir: the plan folder (``viewpoints.csv``, ``plan.json``).
        flight_order: ``flight_time``: every planner's views re-ordered by the same flight-time
            TSP (``ordered_by_flight_time``); ``planner``: each planner's own order.

    Returns:
        (the plan, the ``metrics.json`` fields: ``plan_time_s``, ``flight_order_time_s`` (s; with
        ``flight_order: flight_time``), the forecast, ``n_viewpoints``,
        ``flight_length_m``, ``flight_time_s``, ``n_batteries``).
    """
    plan_fn = hydra.utils.get_method(target)
    start = time.perf_counter()
    plan = plan_fn(proxy, intrinsics, params, seed)
    record: dict = {"plan_time_s": time.perf_counter() - start}
    # Within the drone's floor and ceiling by construction, whoever planned: views above or below
    # are moved to the limit or dropped (mission/envelope.py). The study's plans are left as they
    # are (none comes near 120 m): ``envelope`` is recorded only where a view moved.
    unbounded = plan
    if isinstance(plan, Plan):
        plan, envelope = keep_within_heights(plan, proxy, drone)
    else:
        envelope = None
    validate_plan(plan, proxy, drone)  # whoever made it: nothing unflyable is rendered
    if flight_order == "flight_time":
        start = time.perf_counter()
        plan = ordered_by_flight_time(plan, drone)
        # Apart from plan_time_s, which stays the planner's own (comparable with older records).
        record["flight_order_time_s"] = time.perf_counter() - start
    target_distance = float(target_gsd_m) * intrinsics.focal_px
    forecast = predicted_coverage(proxy, plan.viewpoints, intrinsics, target_distance, evaluation)
    plan.info["predicted_coverage"] = {"criteria": FORECAST_CRITERIA, **forecast}
    if envelope is not None:
        # What the heights cost: the forecast of the plan as the planner made it.
        envelope["forecast_before"] = predicted_coverage(
            proxy, unbounded.viewpoints, intrinsics, target_distance, evaluation
        )
        envelope["forecast_after"] = forecast
        record["envelope"] = envelope
        log.info(
            "within the drone's heights (%.0f-%.0f m): %d views moved down, %d up, %d dropped (of %d)",
            envelope["floor_m"],
            envelope["ceiling_m"],
            envelope["n_moved_down"],
            envelope["n_moved_up"],
            envelope["n_dropped"],
            envelope["n_before"],
        )
    budget = plan.info.get("budget")
    if isinstance(budget, dict) and budget.get("unconstrained_viewpoints"):
        # What the budget gave up: the forecast of the plan the objective asked for.
        unconstrained = np.asarray(budget["unconstrained_viewpoints"], dtype=float)
        budget["unconstrained_forecast"] = predicted_coverage(
            proxy, unconstrained, intrinsics, target_distance, evaluation
        )
    flight = flight_summary(plan.viewpoints, drone)
    plan.info.update(flight)
    record.update(forecast)
    write_plan(plan, out_dir)
    record.update(
        n_viewpoints=len(plan.viewpoints),
        flight_length_m=plan.flight_length_m,
        flight_time_s=flight["flight_time_s"],
        n_batteries=flight["n_batteries"],
    )
    log.info(
        "plan: %d viewpoints, %.0f m flight (%.1f min, %d batteries) in %.1f s",
        len(plan.viewpoints),
        plan.flight_length_m,
        flight["flight_time_s"] / 60.0,
        flight["n_batteries"],
        record["plan_time_s"],
    )
    return plan, record


ORACLE_DIR = Path("recon") / "oracle"


def oracle_stage(
    scene, run_dir: Path, reconstruct: ReconstructSettings, evaluation: EvaluationSettings, seed: int
) -> dict:
    """The matcher's ceiling of the cell's flight (``reconstruct.oracle_beside``): the oracle's cloud
    at the registered cameras of ``run_dir/recon`` in ``run_dir/recon/oracle/``, scored as the
    real one is; returns its ``oracle_*`` fields (numbers only; no error pictures)."""
    out = run_dir / ORACLE_DIR
    dense = oracle_flight(
        run_dir / "recon", run_dir / "images", out, reconstruct, seed, scene.ground_truth_mesh
    )
    quiet = replace(evaluation, visualise=replace(evaluation.visualise, enabled=False), export_gt_mesh=False)
    scores = evaluate_reconstruction(dense["dense_ply"], scene, quiet, out / "eval")
    fields = {**dense, **scores}
    return {
        f"oracle_{k}": v for k, v in fields.items() if isinstance(v, int | float | bool) and v is not None
    }


def ordered_by_flight_time(plan: Plan, drone: DroneSettings) -> Plan:
    """The plan's views in the order that flies them fastest (``planner.trajectory``), from the
    take-off point the missions use (``drone.takeoff_xy``, or the ground under the planner's first
    view, which then stays first); ``info`` keeps the planner's own order's flight time."""
    vps = np.asarray(plan.viewpoints, dtype=float)
    first = 0 if drone.takeoff_xy is None else None
    order = order_by_flight_time(vps, default_takeoff(vps, drone), drone, first=first)
    info = {
        **plan.info,
        "flight_order": "flight_time",
        "planner_order_flight_time_s": flight_summary(vps, drone)["flight_time_s"],
    }
    return Plan(vps[order], [plan.kinds[i] for i in order], plan.planner, info)


def run_cell(cfg: DictConfig, run_dir: Path, record: dict) -> None:
    """Chain the stages for one (scene, planner, seed) cell; fill ``record`` as they complete.

    The run config is read once, by ``cell_settings``; each stage gets its own part of the
    settings. ``record["stage"]`` names the stage running, so a failure is recorded where it happened.
    """
    record["stage"] = "config"
    settings = cell_settings(cfg)  # every bad setting fails here, before the scene loads
    record.update(settings.budget)
    record.update(settings.protocol)
    seed = settings.seed

    record["stage"] = "scene"
    scene = load_scene(settings.scene, cache_dir=settings.cache_dir)
    # Everything a camera could see, hashed: two records of one scene on two machines are comparable
    # image for image only when these agree.
    record["scene_fingerprint"] = scene.fingerprint

    record["stage"] = "proxy"
    proxy, proxy_record = proxy_stage(scene, settings.intrinsics, settings.proxy)
    record.update(proxy_record)

    record["stage"] = "plan"
    plan, plan_record = planned(proxy, settings, run_dir / "plan")
    record.update(plan_record)

    record["stage"] = "render"
    rendered = render_flight(
        scene, plan.viewpoints, settings.intrinsics, run_dir / "images", settings.render, kinds=plan.kinds
    )
    record.update(n_images=len(plan.viewpoints), render_time_s=rendered.render_time_s)

    record["stage"] = "reconstruct"
    recon = reconstruct_flight(
        run_dir / "images",
        run_dir / "recon",
        settings.reconstruct,
        seed,
        ground_truth=scene.ground_truth_mesh,
    )
    record.update({k: v for k, v in recon.items() if isinstance(v, int | float | str | bool)})

    record["stage"] = "evaluate"
    record.update(evaluate_reconstruction(recon["dense_ply"], scene, settings.evaluation, run_dir / "eval"))

    if settings.reconstruct.oracle_beside:
        record["stage"] = "oracle"
        record.update(oracle_stage(scene, run_dir, settings.reconstruct, settings.evaluation, seed))
    record["stage"] = "done"


def cell_record(cfg: DictConfig) -> dict:
    """The fields every ``metrics.json`` starts with: what the cell is."""
    return {
        "scene": scene_label(cfg),
        "scene_config": cfg.scene.name,
        "planner": cfg.planner.name,
        "seed": int(cfg.seed),
        "budget": str(cfg.get("budget", DEFAULT_LEVEL)),
        "target_gsd_m": float(cfg.survey.target_gsd_m),
        "experiment": cfg.experiment.name,
        "status": "running",
    }


def run_and_record(cfg: DictConfig, run_dir: Path) -> dict:
    """Run the cell into ``run_dir`` and write its ``metrics.json``, failed or not.

    Returns:
        the record written.

    Raises:
        CellFailed: the cell failed (its record, with ``status: failed``, the failed stage and the
            error, is written first).
    """
    record = cell_record(cfg)
    log.info("run directory: %s", run_dir)
    code_revision()  # before the stages import their code
    start, cpu_start = time.perf_counter(), cpu_seconds()
    try:
        run_cell(cfg, run_dir, record)
    except Exception as exc:
        record["cell_wall_time_s"] = time.perf_counter() - start
        record["cell_cpu_time_s"] = cpu_seconds() - cpu_start
        failed_stage = record.pop("stage", "?")
        record.update(status="failed", failed_stage=failed_stage, error=f"{type(exc).__name__}: {exc}")
        record.update(getattr(exc, "record", {}) or {})
        write_metrics(run_dir, record, cfg=OmegaConf.to_container(cfg, resolve=True))
        log.error("cell %s/%s failed in stage %s: %s", record["scene"], record["planner"], failed_stage, exc)
        raise CellFailed(f"{failed_stage}: {exc}") from exc
    record.pop("stage", None)
    record["status"] = "ok"
    record["cell_wall_time_s"] = time.perf_counter() - start  # proxy included unless it was cached
    record["cell_cpu_time_s"] = cpu_seconds() - cpu_start  # process and children, every thread
    write_metrics(run_dir, record, cfg=OmegaConf.to_container(cfg, resolve=True))
    log.info("metrics: %s", run_dir / "metrics.json")
    return record
