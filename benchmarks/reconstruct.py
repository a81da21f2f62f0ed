"""Benchmark the reconstruction stage: per-stage wall times and peak memory for growing flights.

    uavplan-bench reconstruct                      # 50, 100, 200 images of the tomb
    uavplan-bench reconstruct --counts 50 100 --images DIR --out bench_out
    uavplan-bench reconstruct --counts 100 --modes default deterministic   # its cost
    uavplan-bench reconstruct --settings scored --counts 200 400 780 \
        --images study/default_v4/church/yan/default/seed0/images   # a scored flight's settings

The base flight is the tomb's exploratory lawnmower at 1024x768 (rendered once into
``OUT/base``, overlap raised until it has at least max(counts) images, or taken from ``--images``).
Each count runs on the first N images of that flight (same density, growing area), in a fresh
process so its peak memory is its own; the proxy stage (Poisson) is included. The machine is
shared: the load average is printed with every row, compare ratios within one run. ``--modes``
runs each count in the default mode and/or with ``reconstruct.deterministic=true``, one after the
other; the CPU time (all threads of the process) is printed beside the wall time.

``--settings proxy`` (default) reconstructs as the exploratory flight does (``build_proxy``: the
proxy's smaller depth maps, then Poisson); ``--settings scored`` as a planned flight is scored
(``reconstruct_flight`` with the full ``dense`` settings and no proxy), which is what a cell's
alignment and dense time measure. The first N images of a planned flight follow its tour, so a
count is a contiguous stretch of the survey.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from planner.lawnmower.lawnmower import plan_exploration
from reconstruct.pipeline import build_proxy, reconstruct_flight
from reconstruct.settings import ReconstructSettings
from render.flight import render_flight
from render.settings import RenderSettings
from scene.camera import Intrinsics
from scene.cameras_file import CAMERAS_FILE, read_cameras, write_cameras
from scene.procedural.tomb import build_tomb

ROOT = Path(__file__).resolve().parents[1]
STAGES = (
    "extraction_time_s",
    "matching_time_s",
    "mapping_time_s",
    "align_time_s",
    "dense_time_s",
    "proxy_time_s",
)


def render_base_flight(out_dir: Path, n_images: int) -> Path:
    """Render the tomb's exploratory flight with at least ``n_images`` views into ``out_dir``."""
    if (out_dir / CAMERAS_FILE).is_file() and len(read_cameras(out_dir)) >= n_images:
        return out_dir
    base = OmegaConf.load(ROOT / "conf" / "config.yaml")
    intrinsics = Intrinsics(**base.camera)
    scene = build_tomb({}, cache_dir=ROOT / "cache" / "scenes")
    exploration = OmegaConf.load(ROOT / "conf" / "exploration" / "lawnmower.yaml")
    plan = plan_exploration(scene.structure_bounds, intrinsics, exploration, 0)
    while len(plan.viewpoints) < n_images:
        if exploration.front_overlap >= 0.95:
            raise SystemExit(
                f"cannot reach {n_images} images with the lawnmower (got {len(plan.viewpoints)})"
            )
        exploration.front_overlap = round(float(exploration.front_overlap) + 0.01, 3)
        exploration.side_overlap = round(float(exploration.side_overlap) + 0.01, 3)
        plan = plan_exploration(scene.structure_bounds, intrinsics, exploration, 0)
    render = OmegaConf.load(ROOT / "conf" / "render" / "default.yaml")
    print(f"rendering the base flight: {len(plan.viewpoints)} images (overlap {exploration.front_overlap})")
    render_flight(
        scene, plan.viewpoints, intrinsics, out_dir, RenderSettings.from_config(render), kinds=plan.kinds
    )
    return out_dir


def subset_flight(base: Path, out_dir: Path, n_images: int) -> Path:
    """A flight of the first ``n_images`` images of ``base`` (symbolic links + a cut cameras.json)."""
    cameras = read_cameras(base)
    if len(cameras) < n_images:
        raise SystemExit(f"{base} has {len(cameras)} images, fewer than {n_images}")
    out_dir.mkdir(parents=True, exist_ok=True)
    names = cameras.names[:n_images]
    for name in names:
        link = out_dir / name
        if not link.exists():
            link.symlink_to((base / name).resolve())
    write_cameras(
        out_dir,
        names,
        cameras.viewpoints[:n_images],
        cameras.intrinsics,
        cameras.kinds[:n_images],
        cameras.extra,
    )
    return out_dir


def run_one(image_dir: Path, out_dir: Path, mode: str = "default", settings: str = "proxy") -> dict:
    """Reconstruct one flight in this process (with its proxy for ``settings`` ``proxy``, as a scored
    flight for ``scored``); return the record with the wall and CPU time (s) and peak memory (GB).
    ``mode`` ``deterministic`` sets ``reconstruct.deterministic``."""
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml")
    cfg.deterministic = mode == "deterministic"
    cfg.keep_dense_workspace = False  # a cell's setting in the study; the bench keeps only records
    start, cpu_start = time.perf_counter(), time.process_time()
    if settings == "scored":
        record = reconstruct_flight(image_dir, out_dir, ReconstructSettings.from_config(cfg), seed=0)
        record["proxy_time_s"] = 0.0
    else:
        _, record = build_proxy(image_dir, out_dir, ReconstructSettings.from_config(cfg), seed=0)
    record["total_time_s"] = time.perf_counter() - start
    record["cpu_time_s"] = time.process_time() - cpu_start
    record["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[50, 100, 200])
    parser.add_argument("--images", type=Path, default=None, help="an existing rendered flight to cut")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench_reconstruct")
    parser.add_argument(
        "--modes", nargs="+", choices=("default", "deterministic"), default=["default"], help="modes to time"
    )
    parser.add_argument(
        "--settings",
        choices=("proxy", "scored"),
        default="proxy",
        help="reconstruct as the exploratory flight (with its proxy) or as a scored flight",
    )
    parser.add_argument(
        "--one", nargs=4, metavar=("IMAGE_DIR", "OUT_DIR", "MODE", "SETTINGS"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.one:
        image_dir, out_dir, mode, settings = args.one
        record = run_one(Path(image_dir), Path(out_dir), mode, settings)
        print("RESULT " + json.dumps(record, default=str))
        return
    if any(n < 3 for n in args.counts):
        parser.error("--counts must all be at least 3")
    base = args.images or render_base_flight(args.out / "base", max(args.counts))
    rows = []
    header = f"{'images':>6} {'mode':>13} {'registered':>10} " + " ".join(f"{s[:-7]:>10}" for s in STAGES)
    header += f" {'align cpu':>9} {'dense cpu':>9} {'total':>8} {'cpu':>8} {'peak GB':>8}"
    header += f" {'pos med m':>9} {'points':>9} {'load':>10}"
    print(header, flush=True)
    for n, mode in ((n, mode) for n in args.counts for mode in args.modes):
        flight = subset_flight(base, args.out / f"flight_{n}", n)
        out_dir = args.out / f"recon_{n}_{mode}_{args.settings}"
        for stale in (out_dir / "recon.json", out_dir / "proxy.json", out_dir / "sfm.json"):
            stale.unlink(missing_ok=True)  # measure, never reuse
        load_before = os.getloadavg()[0]
        done = subprocess.run(
            [sys.executable, __file__, "--one", str(flight), str(out_dir), mode, args.settings],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        result = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
        if done.returncode != 0 or not result:
            print(f"{n} images: failed\n{done.stderr[-3000:]}")
            continue
        record = json.loads(result[0][len("RESULT ") :])
        record["load"] = (load_before, os.getloadavg()[0])
        rows.append((f"{n}_{mode}", record))
        print(
            f"{n:>6} {mode:>13} {record['n_registered']:>10} "
            + " ".join(f"{record.get(s, float('nan')):>10.1f}" for s in STAGES)
            + "".join(f" {record.get(k, float('nan')):>9.1f}" for k in ("align_cpu_s", "dense_cpu_s"))
            + f" {record['total_time_s']:>8.1f} {record['cpu_time_s']:>8.1f} {record['peak_rss_gb']:>8.2f}"
            + f" {record['position_error_median_m']:>9.3f} {record['n_dense_points']:>9d}"
            + f" {record['load'][0]:>4.1f}->{record['load'][1]:<4.1f}",
            flush=True,
        )
    (args.out / "bench.json").parent.mkdir(parents=True, exist_ok=True)
    (args.out / "bench.json").write_text(json.dumps(dict(rows), indent=1, default=str))
    print(f"cpu cores: {os.cpu_count()}; records: {args.out / 'bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
