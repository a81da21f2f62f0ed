"""Baseline planners benchmark: planning time and image count of lawnmower, smith and yan per scene.

Each planner plans on the scene's degraded ground truth (``reconstruct.proxy.degraded_ground_truth``:
the ground truth cropped to the evaluation region, decimated and noised; a stand-in for the proxy
that needs no exploratory reconstruction) with its ``conf/planner/<name>.yaml`` settings and the
run camera of ``conf/config.yaml``. Prints one row per (scene, planner): images, planning time, its
largest stages, the time of the flight-time order every cell flies (``order_s``), flight length,
the planner's own objective before and after optimisation (Smith) or coverage figures, and the
forecast every run records (``pipeline.forecast.predicted_coverage``: the share of the proxy's
wall / roof / ground samples with >= 3 planned views within 1.3 d_t and 60 deg of the normal). The
machine is shared, so compare times within one run.

    uavplan-bench baselines                          # tomb church cathedral x all
    uavplan-bench baselines --scenes tomb --planners smith yan --json out.json
    uavplan-bench baselines --scenes tomb --planners yan --proxy cache/exploration/<key>
    uavplan-bench baselines --scenes tomb --planners ours yan --budgets low default high

``--proxy`` plans on a reconstructed proxy instead: an exploration cache entry of a run of that
scene (``proxy_entry`` in its ``metrics.json``), with the exploratory cloud Yan's confidence reads.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.utils import get_method
from omegaconf import OmegaConf

from drone.model import DroneSettings, flight_summary
from evaluate.settings import EvaluationSettings
from pipeline.cell import ordered_by_flight_time
from pipeline.forecast import predicted_coverage
from pipeline.proxy import load_proxy
from pipeline.settings import planner_setup
from reconstruct.proxy import degraded_ground_truth
from reconstruct.settings import ReconstructSettings
from scene.camera import Intrinsics
from scene.io import write_json_atomic
from scene.registry import load_scene

REPO = Path(__file__).resolve().parents[1]

PLANNERS = ("lawnmower", "smith", "yan")
# Every planner config (conf/planner/<name>.yaml) can be given; PLANNERS are the default set.
KNOWN_PLANNERS = tuple(sorted(p.stem for p in (REPO / "conf" / "planner").glob("*.yaml")))
SCENES = ("tomb", "church", "cathedral")


def compose(scene: str, planner: str, budget: str = "default"):
    """The composed run config for ``scene=<scene> planner=<planner> budget=<budget>``."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        overrides = [f"scene={scene}", f"planner={planner}", f"budget={budget}"]
        return hydra_compose("config", overrides=overrides)


def plan_record(plan, seconds: float) -> dict:
    """The printed figures of one plan."""
    info = plan.info
    record = {
        "n_images": len(plan.viewpoints),
        "plan_time_s": seconds,
        "flight_length_m": plan.flight_length_m,
        "stages_s": {k: round(v, 2) for k, v in info.get("timings_s", {}).items() if k != "total"},
    }
    for key in ("objective_initial", "objective_final", "n_initial_views", "n_local", "n_global"):
        if key in info:
            record[key] = info[key]
    for key in ("fraction_coverable_covered", "n_before_key_images", "rays_cast", "time_reference_s"):
        if key in info:
            record[key] = info[key]
    if "optimisation" in info:
        record["nm_steps"] = info["optimisation"]["steps"]
        record["nm_rounds"] = info["optimisation"]["rounds"]
    return record


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--planners", nargs="+", default=list(PLANNERS), choices=KNOWN_PLANNERS)
    parser.add_argument(
        "--budgets", nargs="+", default=["default"], help="image budget levels (planner/budget.py)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="also write the records here")
    parser.add_argument(
        "--proxy", type=Path, default=None, help="exploration cache entry to plan on (one scene only)"
    )
    args = parser.parse_args(argv)
    if args.proxy is not None and len(args.scenes) != 1:
        parser.error("--proxy is the proxy of one scene: give exactly one --scenes")

    records = []
    for scene_name in args.scenes:
        base = compose(scene_name, args.planners[0])
        t0 = time.perf_counter()
        scene = load_scene(base.scene, cache_dir=base.cache_dir)
        if args.proxy is None:
            proxy = degraded_ground_truth(
                scene, ReconstructSettings.from_config(base.reconstruct).proxy, args.seed
            )
        else:
            try:
                proxy = load_proxy(args.proxy)
            except (FileNotFoundError, ValueError) as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
        print(
            f"\n{scene_name}: structure {scene.structure_bounds.extent.round(1).tolist()} m, proxy "
            f"{len(proxy.faces)} faces, {proxy.area:.0f} m^2 "
            f"(scene + proxy {time.perf_counter() - t0:.1f} s)",
            flush=True,
        )
        cells = [(p, b) for p in args.planners for b in args.budgets]
        for planner_name, budget in cells:
            cfg = compose(scene_name, planner_name, budget)
            intrinsics = Intrinsics(int(cfg.camera.width), int(cfg.camera.height), float(cfg.camera.hfov_deg))
            try:
                params, budget_record = planner_setup(cfg)
            except ValueError as exc:  # a level this planner does not define
                print(f"  {planner_name} {budget}: {exc}", flush=True)
                continue
            params = OmegaConf.to_container(params)
            if "progress" in params:
                params["progress"] = False
            plan_fn = get_method(cfg.planner._target_)
            t0, c0 = time.perf_counter(), time.process_time()
            plan = plan_fn(proxy, intrinsics, params, args.seed)
            seconds = time.perf_counter() - t0
            label = planner_name if budget == "default" else f"{planner_name}@{budget}"
            record = {"scene": scene_name, "planner": label, **budget_record, **plan_record(plan, seconds)}
            # CPU time of this process's threads: the machine is shared, wall time moves with it.
            record["plan_cpu_s"] = round(time.process_time() - c0, 1)
            drone = DroneSettings.from_config(cfg.drone)
            if str(cfg.survey.get("flight_order", "planner")) == "flight_time":
                # The order every cell flies (pipeline.cell.plan_stage): part of planning a flight.
                t0, c0 = time.perf_counter(), time.process_time()
                plan = ordered_by_flight_time(plan, drone)
                record["order_time_s"] = round(time.perf_counter() - t0, 2)
                record["order_cpu_s"] = round(time.process_time() - c0, 2)
            # The same forecast run.py records for every planner (issue "Planner ours"'s count).
            settings = EvaluationSettings.from_config(cfg.evaluate)
            target_distance = float(cfg.survey.target_gsd_m) * intrinsics.focal_px
            forecast = predicted_coverage(proxy, plan.viewpoints, intrinsics, target_distance, settings)
            record.update({k: round(v, 1) for k, v in forecast.items()})
            flight = flight_summary(plan.viewpoints, drone)
            record["flight_time_min"] = round(flight["flight_time_s"] / 60.0, 1)
            records.append(record)
            extras = {
                k: v
                for k, v in record.items()
                if k not in ("scene", "planner", "n_images", "plan_time_s", "budget", "budget_knob")
            }
            print(
                f"  {label:16s} images {record['n_images']:5d}  plan {seconds:7.1f} s  "
                + json.dumps(extras, default=float),
                flush=True,
            )
    print(
        "\nscene      planner           images  plan_s   cpu_s order_s  flight min"
        "  objective initial -> final   3 good views (%): walls roofs ground"
    )
    for r in records:
        objective = " " * 20
        if "objective_final" in r:
            objective = f"{r['objective_initial']:8.3f} -> {r['objective_final']:8.3f}"
        shares = "  ".join(
            f"{r.get(f'predicted_well_observed_{c}_pct', float('nan')):5.1f}"
            for c in ("walls", "roofs", "ground")
        )
        row = f"{r['scene']:10s} {r['planner']:16s} {r['n_images']:7d}"
        row += f" {r['plan_time_s']:7.1f} {r['plan_cpu_s']:7.1f} {r.get('order_time_s', float('nan')):7.1f}"
        row += f" {r['flight_time_min']:11.1f}"
        print(f"{row}  {objective}                   {shares}")
    if args.json:
        write_json_atomic(args.json, records)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
