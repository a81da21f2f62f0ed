"""One cell of the study, end to end, in simulation.

    python run.py scene=tomb planner=ours                 # one cell
    python run.py --cfg job                               # print the composed config
    python run.py -m scene=tomb,church,cathedral planner=ours,smith,yan   # a sweep

scene -> exploratory flight -> proxy (shared per scene, cached) -> plan -> render -> reconstruct
-> score -> metrics.json. The planner only ever sees the proxy; the reconstruction only sees
images and GNSS-like noisy camera positions.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from planner.budget import DEFAULT_LEVEL, apply_budget
from reconstruct.timing import cpu_seconds

log = logging.getLogger("run")


class CellFailed(RuntimeError):
    """The cell failed; metrics.json records the failure (a sweep reports it and goes on)."""


def obtain_proxy(scene, intrinsics, cfg: DictConfig, record: dict):
    """The proxy mesh the planners plan on, built once per scene and configuration (cached)."""
    source = cfg.reconstruct.proxy.source
    if source == "ground_truth_degraded":
        from reconstruct.proxy import degraded_ground_truth

        record["proxy_source"] = "ground_truth_degraded (NOT the paper's setting)"
        return degraded_ground_truth(scene, cfg.reconstruct, cfg.seed)
    if source != "reconstruction":
        raise ValueError(
            f"reconstruct.proxy.source must be 'reconstruction' or 'ground_truth_degraded', got {source!r}"
        )
    from experiments.exploration import build_exploration_proxy

    proxy, proxy_record = build_exploration_proxy(scene, intrinsics, cfg)
    record.update(
        {f"proxy_{k}": v for k, v in proxy_record.items() if isinstance(v, int | float | str | bool)}
    )
    record["proxy_source"] = "reconstruction"
    return proxy


def scene_label(cfg: DictConfig) -> str:
    """The scene's name in records: its config's name, or for ``scene=mesh`` the mesh file's stem
    (``scene.path=cache/meshes/hall.glb`` -> ``hall``), so two users' meshes are two scenes."""
    path = OmegaConf.select(cfg, "scene.path", default=None) if cfg.scene.name == "mesh" else None
    return Path(str(path)).stem if path else str(cfg.scene.name)


def planner_setup(cfg: DictConfig) -> tuple[DictConfig, dict]:
    """The planner's parameters, and the budget record (``budget``, ``budget_knob``, ``budget_value``).

    The experiment preset's overrides for this planner are merged in first: presets
    (conf/experiment/*.yaml) carry ``experiment.planner_overrides.<planner name>``, because each
    planner has parameters of its own. Then ``budget=<level>`` sets the planner's budget knob
    (``planner.budget``) and the ``budget`` block is dropped (``name`` and ``_target_`` stay).

    Raises:
        ValueError: a budget level the planner does not define.
    """
    overrides = OmegaConf.select(cfg, f"experiment.planner_overrides.{cfg.planner.name}")
    # Resolved first: planner settings interpolate run-level values (``${survey.target_gsd_m}``).
    params = OmegaConf.create(OmegaConf.to_container(cfg.planner, resolve=True))
    if overrides:
        params = OmegaConf.merge(params, overrides)
    params, budget = apply_budget(
        OmegaConf.to_container(params, resolve=True), str(cfg.get("budget", DEFAULT_LEVEL)), cfg.planner.name
    )
    return OmegaConf.create(params), budget


def planner_params(cfg: DictConfig) -> DictConfig:
    """The parameters ``plan`` receives (``planner_setup`` without the budget record)."""
    return planner_setup(cfg)[0]


def run_cell(cfg: DictConfig, run_dir: Path, record: dict) -> None:
    """Chain the stages for one (scene, planner, seed) cell; fill ``record`` as they complete."""
    from drone.model import DroneSettings, flight_summary
    from evaluate.run import evaluate_reconstruction
    from evaluate.settings import EvaluationSettings
    from experiments.observations import predicted_coverage
    from mission.validate import validate_plan
    from reconstruct.pipeline import reconstruct_flight
    from render import render_flight
    from scene.camera import Intrinsics
    from scene.plan import write_plan
    from scene.registry import load_scene

    record["stage"] = "config"
    params, budget = planner_setup(cfg)  # a bad budget level fails here, not after the proxy
    record.update(budget)

    record["stage"] = "scene"
    drone = DroneSettings.from_config(OmegaConf.to_container(cfg.drone, resolve=True))
    scene = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
    # Everything a camera could see, hashed: two records of one scene on two machines are comparable
    # image for image only when these agree.
    record["scene_fingerprint"] = scene.fingerprint
    intrinsics = Intrinsics(**cfg.camera)

    record["stage"] = "proxy"
    proxy = obtain_proxy(scene, intrinsics, cfg, record)

    record["stage"] = "plan"
    plan_fn = hydra.utils.get_method(cfg.planner._target_)
    start = time.perf_counter()
    plan = plan_fn(proxy, intrinsics, params, cfg.seed)
    record["plan_time_s"] = time.perf_counter() - start
    validate_plan(plan, proxy, drone)  # whoever made it: nothing unflyable is rendered
    settings = EvaluationSettings.from_config(cfg.evaluate)
    target_distance = float(cfg.survey.target_gsd_m) * intrinsics.focal_px
    forecast = predicted_coverage(proxy, plan.viewpoints, intrinsics, target_distance, settings)
    plan.info["predicted_coverage"] = {
        "criteria": ">= 3 planned views within 1.3 d_t and 60 deg of the normal (experiments.observations)",
        **forecast,
    }
    flight = flight_summary(plan.viewpoints, drone)
    plan.info.update(flight)
    record.update(forecast)
    write_plan(plan, run_dir / "plan")
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

    record["stage"] = "render"
    rendered = render_flight(
        scene, plan.viewpoints, intrinsics, run_dir / "images", cfg.render, kinds=plan.kinds
    )
    record.update(n_images=len(plan.viewpoints), render_time_s=rendered.render_time_s)

    record["stage"] = "reconstruct"
    recon = reconstruct_flight(run_dir / "images", run_dir / "recon", cfg.reconstruct, cfg.seed)
    record.update({k: v for k, v in recon.items() if isinstance(v, int | float | str | bool)})

    record["stage"] = "evaluate"
    record.update(evaluate_reconstruction(recon["dense_ply"], scene, cfg.evaluate, run_dir / "eval"))
    record["stage"] = "done"


@hydra.main(version_base=None, config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    record = {
        "scene": scene_label(cfg),
        "scene_config": cfg.scene.name,
        "planner": cfg.planner.name,
        "seed": int(cfg.seed),
        "budget": str(cfg.get("budget", DEFAULT_LEVEL)),
        "experiment": cfg.experiment.name,
        "status": "running",
    }
    log.info("run directory: %s", run_dir)
    from evaluate.record import code_revision, write_metrics

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
        if HydraConfig.get().mode == RunMode.MULTIRUN or os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise CellFailed(f"{failed_stage}: {exc}") from exc
        # One run: one line on stderr, the traceback on request.
        print(
            f"error: cell {record['scene']}/{record['planner']} failed in stage {failed_stage}: {exc} "
            "(traceback: HYDRA_FULL_ERROR=1)",
            file=sys.stderr,
        )
        sys.exit(1)
    record.pop("stage", None)
    record["status"] = "ok"
    record["cell_wall_time_s"] = time.perf_counter() - start  # proxy included unless it was cached
    record["cell_cpu_time_s"] = cpu_seconds() - cpu_start  # process and children, every thread
    write_metrics(run_dir, record, cfg=OmegaConf.to_container(cfg, resolve=True))
    log.info("metrics: %s", run_dir / "metrics.json")


if __name__ == "__main__":
    main()
