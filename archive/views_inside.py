"""Does a planner put views inside the true building? Plan on a cell's exploration proxy, then test
every view against the ground truth's closed volumes (the 26-ray test of ``scene.enclosure``).

    python -m archive.views_inside scene=mesh scene.path=plant.dae \\
        exploration=lawnmower_orbit planner=ours

Takes ``run.py``'s overrides; the exploration proxy comes from the cache (built if missing).
Prints the plan's size and time and the views the ground truth closes in; exit status 1 when any.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    import hydra
    from hydra import compose, initialize_config_dir

    from drone.model import DroneSettings
    from mission.validate import validate_plan
    from pipeline.proxy import ProxyInputs, proxy_stage
    from pipeline.settings import planner_setup
    from scene.camera import Intrinsics
    from scene.enclosure import enclosed_positions, raycasting_scene
    from scene.registry import load_scene

    overrides = list(sys.argv[1:] if argv is None else argv)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose(config_name="config", overrides=overrides)
    params, _ = planner_setup(cfg)
    scene = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
    intrinsics = Intrinsics(**cfg.camera)
    proxy, _ = proxy_stage(scene, intrinsics, ProxyInputs.of(cfg))
    start = time.perf_counter()
    plan = hydra.utils.get_method(cfg.planner._target_)(proxy, intrinsics, params, cfg.seed)
    plan_s = time.perf_counter() - start
    validate_plan(plan, proxy, DroneSettings.from_config(dict(cfg.drone)))
    positions = np.asarray(plan.viewpoints)[:, :3]
    inside = np.flatnonzero(enclosed_positions(raycasting_scene(scene.ground_truth_mesh), positions))
    print(f"{cfg.planner.name}: {len(positions)} views planned in {plan_s:.0f} s; passes mission.validate")
    print(f"views inside a closed volume of the ground truth: {len(inside)}")
    for i in inside:
        print(f"  view {i} at {np.round(positions[i], 2).tolist()}")
    return 1 if len(inside) else 0


if __name__ == "__main__":
    sys.exit(main())
