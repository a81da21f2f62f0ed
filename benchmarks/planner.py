"""Benchmark of the planner ``ours`` on each scene's degraded ground truth (the stand-in proxy).

    uavplan-bench planner                       # tomb, church, cathedral
    uavplan-bench planner --scenes tomb --set cmaes.max_generations=4

Prints, per scene: the time of every stage (wall and process CPU), objective evaluations per
second and rays cast per second during CMA-ES, and the cost of re-scoring the viewpoint set after
moving one cluster (visibility of its rows + incremental scoring) as a fraction of a full
evaluation (visibility of every row + scoring from scratch), measured on the planned set.
The machine is shared: compare ratios within one run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from omegaconf import OmegaConf
from threadpoolctl import threadpool_limits

from planner.objective import ObjectiveState
from planner.ours.cmaes_refine import spatial_clusters
from planner.ours.ours import plan, resolve_params
from planner.ours.ours_settings import detail_params
from planner.sampling import sample_surface
from planner.visibility import VisibilityLimits, VisibilityModel
from reconstruct.proxy import degraded_ground_truth
from reconstruct.settings import ReconstructSettings
from scene.camera import Intrinsics
from scene.io import write_json_atomic
from scene.registry import load_scene

ROOT = Path(__file__).resolve().parents[1]


def _load_yaml(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


def _proxy(scene_name: str, seed: int, cache_dir: str):

    raw = OmegaConf.load(ROOT / "conf" / "scene" / f"{scene_name}.yaml")
    scene_cfg = OmegaConf.create({"seed": seed, "scene": raw})  # resolves ${seed}
    scene = load_scene(OmegaConf.to_container(scene_cfg, resolve=True)["scene"], cache_dir=cache_dir)
    recon_cfg = _load_yaml(ROOT / "conf" / "reconstruct" / "default.yaml")
    return degraded_ground_truth(scene, ReconstructSettings.from_config(recon_cfg).proxy, seed)


def _set(params: dict, assignment: str) -> None:
    key, _, value = assignment.partition("=")
    node = params
    *path, last = key.split(".")
    for p in path:
        node = node.setdefault(p, {})
    node[last] = yaml.safe_load(value)


def rescore_ratio(
    proxy, intrinsics: Intrinsics, params: dict, viewpoints: np.ndarray, seed: int, repeats: int = 5
):
    """(full evaluation s, one-cluster re-score s, ratio) in wall and CPU time on ``viewpoints``."""
    cfg = resolve_params(params)
    d_t = intrinsics.distance_for_gsd(cfg["target_gsd_m"])
    hp = detail_params(cfg["heuristics"], d_t)
    margin = hp.d_margin_m
    points, normals = sample_surface(proxy, cfg["n_points"], seed)
    vis = cfg["visibility"]
    model = VisibilityModel(
        proxy,
        points,
        normals,
        intrinsics,
        VisibilityLimits(vis["min_distance_m"], hp.target_hi_m + margin, vis["max_incidence_deg"]),
        vis["ray_offset_m"],
        vis["image_margin_px"],
    )
    state = ObjectiveState(hp, len(points), points=points)
    clusters = spatial_clusters(viewpoints[:, :3], cfg["cmaes"]["cluster_size"])
    rng = np.random.default_rng(seed)
    full_w = full_c = inc_w = inc_c = 0.0
    for r in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        state.reset(model.observe(viewpoints))
        full_w += time.perf_counter() - w
        full_c += time.process_time() - c
        cluster = clusters[r % len(clusters)]
        moved = viewpoints[cluster].copy()
        moved[:, :3] += rng.normal(0.0, 0.5, (len(cluster), 3))
        w, c = time.perf_counter(), time.process_time()
        state.evaluate(cluster, model.observe(moved), 1)
        inc_w += time.perf_counter() - w
        inc_c += time.process_time() - c
    return {
        "full_eval_wall_s": full_w / repeats,
        "rescore_wall_s": inc_w / repeats,
        "ratio_wall": inc_w / full_w,
        "full_eval_cpu_s": full_c / repeats,
        "rescore_cpu_s": inc_c / repeats,
        "ratio_cpu": inc_c / full_c,
        "n_viewpoints": len(viewpoints),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scenes", nargs="+", default=["tomb", "church", "cathedral"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache-dir", default="cache")
    parser.add_argument("--set", action="append", default=[], help="planner override key=value (dotted)")
    parser.add_argument("--json", default=None, help="also write the records to this JSON file")
    args = parser.parse_args(argv)
    cam = _load_yaml(ROOT / "conf" / "config.yaml")["camera"]
    intrinsics = Intrinsics(int(cam["width"]), int(cam["height"]), float(cam["hfov_deg"]))
    params: dict = {}
    for a in args.set:
        _set(params, a)
    records = []
    for name in args.scenes:
        t = time.perf_counter()
        proxy = _proxy(name, args.seed, args.cache_dir)
        print(
            f"\n=== {name}: degraded ground truth {len(proxy.faces)} faces ({time.perf_counter() - t:.1f} s)"
        )
        w, c = time.perf_counter(), time.process_time()
        result = plan(proxy, intrinsics, params, args.seed)
        wall, cpu = time.perf_counter() - w, time.process_time() - c
        info = result.info
        print(
            f"{'stage':22s} {'round':>5s} {'wall s':>8s} {'views':>6s} {'R':>9s} {'R_point':>9s} "
            f"{'vis':>6s} {'ovl':>6s} {'conn':>6s} {'evals':>7s} {'rays':>9s}"
        )
        for s in info["stages"]:
            rnd = "" if s["round"] is None else str(s["round"] + 1)
            print(
                f"{s['stage']:22s} {rnd:>5s} {s['time_s']:8.2f} {s['n_detail'] + s['n_coverage']:6d} "
                f"{s['R']:9.1f} {s['R_point_sum']:9.1f} {s['visibility']:6.3f} {s['overlap']:6.3f} "
                f"{s['connectivity']:6.3f} {s.get('evaluations', 0):7d} {s['rays_cast']:9d}"
            )
        cma = [s for s in info["stages"] if s["stage"].endswith("cmaes")]
        cma_time = sum(s["time_s"] for s in cma)
        cma_evals = sum(s["evaluations"] for s in cma)
        cma_rays = sum(s["rays_cast"] for s in cma)
        kinds = result.kinds
        print(
            f"total plan: {wall:.1f} s wall, {cpu:.1f} s CPU (this process); "
            f"TSP {info['timings_s']['tsp']:.1f} s"
        )
        print(
            f"viewpoints: {kinds.count('detail')} detail + {kinds.count('coverage')} coverage; "
            f"flight {result.flight_length_m:.0f} m; final R {info['final']['R']:.1f} "
            f"(R_point {info['final']['R_point_sum']:.1f}, R_viewpoint {info['final']['R_viewpoint']:.3f})"
        )
        print(
            f"CMA-ES: {cma_evals} objective evaluations in {cma_time:.1f} s = "
            f"{cma_evals / cma_time:.0f} evals/s; "
            f"{cma_rays} rays = {cma_rays / cma_time:.0f} rays/s (wall)"
        )
        detail = result.viewpoints[np.asarray(kinds) == "detail"]
        with threadpool_limits(limits=1):
            rs = rescore_ratio(proxy, intrinsics, params, detail, args.seed)
        print(
            f"re-score after moving one cluster: {rs['rescore_wall_s'] * 1e3:.1f} ms vs full evaluation "
            f"{rs['full_eval_wall_s'] * 1e3:.1f} ms: {100 * rs['ratio_wall']:.1f} % wall, "
            f"{100 * rs['ratio_cpu']:.1f} % CPU ({rs['n_viewpoints']} detail viewpoints)"
        )
        records.append(
            {
                "scene": name,
                "plan_wall_s": wall,
                "plan_cpu_s": cpu,
                "cma_evals_per_s": cma_evals / cma_time,
                "cma_rays_per_s": cma_rays / cma_time,
                **rs,
                "n_viewpoints": len(kinds),
                "stages": info["stages"],
                "timings_s": info["timings_s"],
            }
        )
    if args.json:
        write_json_atomic(args.json, records)
    return 0


if __name__ == "__main__":
    sys.exit(main())
