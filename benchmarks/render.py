"""Rendering benchmark: 100 views of each scene at 1024 x 768, per OpenGL back-end.

Prints, per scene and back-end: scene build time, renderer build time, images/s including PNG
writing, CPU seconds per image (all threads of the process: a figure that the other jobs on a shared
machine disturb less than wall time) and the peak resident memory. Each (scene, back-end) cell runs
in its own process: the back-end is fixed per process and the peak memory is then per cell.

    uavplan-bench render                       # tomb church cathedral, egl osmesa
    uavplan-bench render --scenes tomb --backends egl --views 100
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from render import RenderSettings, render_flight
from scene.camera import Intrinsics

REPO = Path(__file__).resolve().parents[1]


def survey_viewpoints(structure_lo, structure_hi, n_views: int, intrinsics) -> np.ndarray:
    """A lawnmower-like survey of a structure's bounding box: (n_views, 5) viewpoints.

    Half the views are a nadir lawnmower over the box (grown by 10 m) at 20 m above its top, the
    other half an orbit at 45 degrees pitch aimed at the box centre from 1.2 box diagonals away.
    """
    lo, hi = np.asarray(structure_lo, float), np.asarray(structure_hi, float)
    n_grid = n_views // 2
    cols = max(1, int(round(math.sqrt(n_grid * (hi[0] - lo[0] + 20) / (hi[1] - lo[1] + 20)))))
    rows = int(math.ceil(n_grid / cols))
    xs = np.linspace(lo[0] - 10, hi[0] + 10, cols)
    ys = np.linspace(lo[1] - 10, hi[1] + 10, rows)
    grid = []
    for r, y in enumerate(ys):
        for x in xs if r % 2 == 0 else xs[::-1]:
            grid.append([x, y, hi[2] + 20.0, 90.0 if r % 2 == 0 else -90.0, -90.0])
    grid = np.array(grid[:n_grid])
    n_orbit = n_views - len(grid)
    center = 0.5 * (lo + hi)
    radius = 1.2 * float(np.linalg.norm(hi - lo)) / math.sqrt(2.0)
    az = np.linspace(0.0, 2.0 * math.pi, n_orbit, endpoint=False)
    orbit = np.stack(
        [
            center[0] + radius * np.cos(az),
            center[1] + radius * np.sin(az),
            np.full(n_orbit, center[2] + radius),
            np.degrees(az) + 180.0,
            np.full(n_orbit, -45.0),
        ],
        axis=1,
    )
    orbit[:, 3] = (orbit[:, 3] + 180.0) % 360.0 - 180.0
    return np.concatenate([grid, orbit])


def run_cell(scene_name: str, backend: str, n_views: int, out_dir: Path) -> dict:
    """Build one scene and render ``n_views`` with one back-end in this process; return the figures."""
    try:
        # optional dependency: imported on use
        from scene.registry import load_scene
    except ImportError as err:
        raise SystemExit(f"scene.registry.load_scene is not available yet: {err}") from err

    # Scene configs interpolate the run's ${seed}; seed 0 as in conf/config.yaml.
    scene_cfg = OmegaConf.merge(
        {"seed": 0}, {"scene": OmegaConf.load(REPO / "conf" / "scene" / f"{scene_name}.yaml")}
    )
    scene_cfg = scene_cfg.scene
    start = time.perf_counter()
    scene = load_scene(scene_cfg)
    scene_build_s = time.perf_counter() - start
    intrinsics = Intrinsics(1024, 768, 60.0)
    cfg = OmegaConf.load(REPO / "conf" / "render" / "default.yaml")
    cfg.backend = backend
    viewpoints = survey_viewpoints(scene.structure_bounds.lo, scene.structure_bounds.hi, n_views, intrinsics)
    result = render_flight(scene, viewpoints, intrinsics, out_dir, RenderSettings.from_config(cfg))
    png_bytes = sum(p.stat().st_size for p in out_dir.glob("*.png"))
    return {
        "scene": scene_name,
        "backend": result.backend,
        "n_faces": scene.n_faces,
        "texture_mb": sum(t.nbytes for t in scene.textures.values()) / 1e6,
        "scene_build_s": scene_build_s,
        "renderer_build_s": result.build_time_s,
        "render_s": result.render_time_s,
        "images_per_s": result.images_per_s,
        "cpu_s_per_image": result.render_cpu_s / n_views,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "mean_png_kb": png_bytes / n_views / 1024.0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scenes", nargs="+", default=["tomb", "church", "cathedral"])
    parser.add_argument("--backends", nargs="+", default=["egl", "osmesa"], choices=["egl", "osmesa"])
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--keep", type=Path, default=None, help="keep the images under this folder")
    parser.add_argument("--cell", nargs=3, metavar=("SCENE", "BACKEND", "OUT_DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.views < 1:
        parser.error(f"--views must be positive, got {args.views}")

    if args.cell:
        scene_name, backend, out_dir = args.cell
        print("RESULT " + json.dumps(run_cell(scene_name, backend, args.views, Path(out_dir))), flush=True)
        return 0

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_render_") as tmp:
        for scene_name in args.scenes:
            for backend in args.backends:
                out_dir = (args.keep or Path(tmp)) / f"{scene_name}_{backend}"
                env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
                env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
                cmd = [
                    sys.executable,
                    __file__,
                    "--views",
                    str(args.views),
                    "--cell",
                    scene_name,
                    backend,
                    str(out_dir),
                ]
                proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if proc.returncode != 0 or not lines:
                    print(f"{scene_name}/{backend}: FAILED (exit {proc.returncode})", file=sys.stderr)
                    return 1
                rows.append(json.loads(lines[-1][len("RESULT ") :]))

    header = (
        f"{'scene':<10} {'backend':<7} {'faces':>8} {'tex MB':>7} {'scene s':>8} {'build s':>8} "
        f"{'img/s':>6} {'CPU s/img':>9} {'peak MB':>8} {'PNG kB':>7}"
    )
    print(
        f"{args.views} views per scene at 1024x768, PNG writing included; {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print(header)
    for r in rows:
        print(
            f"{r['scene']:<10} {r['backend']:<7} {r['n_faces']:>8} {r['texture_mb']:>7.0f} "
            f"{r['scene_build_s']:>8.1f} {r['renderer_build_s']:>8.1f} {r['images_per_s']:>6.2f} "
            f"{r['cpu_s_per_image']:>9.3f} "
            f"{r['peak_rss_mb']:>8.0f} {r['mean_png_kb']:>7.0f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
