"""One cell of the study, end to end, in simulation.

    python run.py scene=tomb planner=ours                 # one cell
    python run.py --cfg job                               # print the composed config
    python run.py -m scene=tomb,church,cathedral planner=ours,smith,yan   # a sweep

scene -> exploratory flight -> proxy (shared per scene, cached) -> plan -> render -> reconstruct
-> score -> metrics.json. The planner only ever sees the proxy; the reconstruction only sees
images and GNSS-like noisy camera positions.
"""

from __future__ import annotations

import importlib
import logging
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("run")


class StageUnavailable(RuntimeError):
    """A pipeline stage has no implementation yet: the run stops there instead of faking it."""


class CellFailed(RuntimeError):
    """The cell failed; metrics.json records the failure (Hydra reports it and exits non-zero)."""


def stage(module: str, name: str):
    """Import stage function ``module.name``, or raise StageUnavailable naming the missing stage."""
    try:
        return getattr(importlib.import_module(module), name)
    except (ModuleNotFoundError, AttributeError) as exc:
        raise StageUnavailable(f"stage {module}.{name} is not available: {exc}") from exc


def obtain_proxy(scene, intrinsics, cfg: DictConfig, record: dict):
    """The proxy mesh the planners plan on, built once per scene and configuration (cached)."""
    source = cfg.reconstruct.proxy.source
    if source == "ground_truth_degraded":
        degraded_ground_truth = stage("reconstruct.proxy", "degraded_ground_truth")
        record["proxy_source"] = "ground_truth_degraded (NOT the paper's setting)"
        return degraded_ground_truth(scene, cfg.reconstruct, cfg.seed)
    if source != "reconstruction":
        raise ValueError(
            f"reconstruct.proxy.source must be 'reconstruction' or 'ground_truth_degraded', got {source!r}"
        )
    build_exploration_proxy = stage("experiments.exploration", "build_exploration_proxy")
    proxy, proxy_record = build_exploration_proxy(scene, intrinsics, cfg)
    record.update(
        {f"proxy_{k}": v for k, v in proxy_record.items() if isinstance(v, int | float | str | bool)}
    )
    record["proxy_source"] = "reconstruction"
    return proxy


def planner_params(cfg: DictConfig) -> DictConfig:
    """The planner's parameters with the experiment preset's overrides for this planner merged in.

    Presets (conf/experiment/*.yaml) carry ``experiment.planner_overrides.<planner name>``, because
    each planner has parameters of its own.
    """
    overrides = OmegaConf.select(cfg, f"experiment.planner_overrides.{cfg.planner.name}")
    # Resolved first: planner settings interpolate run-level values (``${survey.target_gsd_m}``).
    params = OmegaConf.create(OmegaConf.to_container(cfg.planner, resolve=True))
    return OmegaConf.merge(params, overrides) if overrides else params


def run_cell(cfg: DictConfig, run_dir: Path, record: dict) -> None:
    """Chain the stages for one (scene, planner, seed) cell; fill ``record`` as they complete."""
    from scene.camera import Intrinsics

    record["stage"] = "scene"
    scene = stage("scene.registry", "load_scene")(cfg.scene, cache_dir=cfg.cache_dir)
    intrinsics = Intrinsics(**cfg.camera)

    record["stage"] = "proxy"
    proxy = obtain_proxy(scene, intrinsics, cfg, record)

    record["stage"] = "plan"
    plan_fn = hydra.utils.get_method(cfg.planner._target_)
    write_plan = stage("planner.base", "write_plan")
    start = time.perf_counter()
    plan = plan_fn(proxy, intrinsics, planner_params(cfg), cfg.seed)
    record["plan_time_s"] = time.perf_counter() - start
    predicted_coverage = stage("experiments.observations", "predicted_coverage")
    settings = stage("evaluate.settings", "EvaluationSettings").from_config(cfg.evaluate)
    target_distance = float(cfg.survey.target_gsd_m) * intrinsics.focal_px
    forecast = predicted_coverage(proxy, plan.viewpoints, intrinsics, target_distance, settings)
    plan.info["predicted_coverage"] = {
        "criteria": ">= 3 planned views within 1.3 d_t and 60 deg of the normal (experiments.observations)",
        **forecast,
    }
    record.update(forecast)
    write_plan(plan, run_dir / "plan")
    record.update(n_viewpoints=len(plan.viewpoints), flight_length_m=plan.flight_length_m)
    log.info(
        "plan: %d viewpoints, %.0f m flight in %.1f s",
        len(plan.viewpoints),
        plan.flight_length_m,
        record["plan_time_s"],
    )

    record["stage"] = "render"
    render_flight = stage("render", "render_flight")
    rendered = render_flight(
        scene, plan.viewpoints, intrinsics, run_dir / "images", cfg.render, kinds=plan.kinds
    )
    record.update(n_images=len(plan.viewpoints), render_time_s=rendered.render_time_s)

    record["stage"] = "reconstruct"
    reconstruct_flight = stage("reconstruct.pipeline", "reconstruct_flight")
    recon = reconstruct_flight(run_dir / "images", run_dir / "recon", cfg.reconstruct, cfg.seed)
    record.update({k: v for k, v in recon.items() if isinstance(v, int | float | str | bool)})

    record["stage"] = "evaluate"
    evaluate_run = stage("evaluate.run", "evaluate_reconstruction")
    record.update(evaluate_run(recon["dense_ply"], scene, cfg.evaluate, run_dir / "eval"))
    record["stage"] = "done"


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    record = {
        "scene": cfg.scene.name,
        "planner": cfg.planner.name,
        "seed": int(cfg.seed),
        "experiment": cfg.experiment.name,
        "status": "running",
    }
    log.info("run directory: %s", run_dir)
    write_metrics = stage("evaluate.record", "write_metrics")
    stage("evaluate.record", "code_revision")()  # before the stages import their code
    start = time.perf_counter()
    try:
        run_cell(cfg, run_dir, record)
    except Exception as exc:
        record["cell_wall_time_s"] = time.perf_counter() - start
        failed_stage = record.pop("stage", "?")
        record.update(status="failed", failed_stage=failed_stage, error=f"{type(exc).__name__}: {exc}")
        record.update(getattr(exc, "record", {}) or {})
        write_metrics(run_dir, record, cfg=OmegaConf.to_container(cfg, resolve=True))
        log.error("cell %s/%s failed in stage %s: %s", record["scene"], record["planner"], failed_stage, exc)
        raise CellFailed(f"{failed_stage}: {exc}") from exc
    record.pop("stage", None)
    record["status"] = "ok"
    record["cell_wall_time_s"] = time.perf_counter() - start  # proxy included unless it was cached
    write_metrics(run_dir, record, cfg=OmegaConf.to_container(cfg, resolve=True))
    log.info("metrics: %s", run_dir / "metrics.json")


if __name__ == "__main__":
    main()
