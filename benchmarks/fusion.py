"""Fusion's memory on a finished dense workspace: fuse within ``fusion.max_memory_gb`` (in chunks
of views when the flight needs more) and print wall time, CPU time and peak resident memory.

    uavplan-bench fusion RUN/recon/dense --out study/fusion/dense.ply [--max-memory-gb 14]

Quote the line it prints; score the cloud with ``uavplan-evaluate``.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from reconstruct.dense import _fuse_atomic
from reconstruct.dense_settings import DenseSettings
from reconstruct.workspace import DEPTH_SUFFIX

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path, help="dense workspace (images/, sparse/, stereo/)")
    parser.add_argument("--out", type=Path, required=True, help="fused cloud (PLY)")
    parser.add_argument("--max-memory-gb", type=float, help="override reconstruct.dense.fusion.max_memory_gb")
    args = parser.parse_args(argv)

    maps = args.workspace / "stereo" / "depth_maps"
    names = sorted(p.name[: -len(DEPTH_SUFFIX)] for p in maps.glob(f"*{DEPTH_SUFFIX}"))
    if not names:
        print(f"error: {maps}: no geometric depth maps (not a dense workspace)", file=sys.stderr)
        return 2
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense
    if args.max_memory_gb is not None:
        cfg.fusion.max_memory_gb = args.max_memory_gb
    settings = DenseSettings.from_config(cfg)
    wall, cpu = time.perf_counter(), time.process_time()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    n_points = _fuse_atomic(args.workspace, args.out, settings, names, deterministic=False).n_points
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(
        f"fusion: {n_points} points from {len(names)} views in {time.perf_counter() - wall:.1f} s wall, "
        f"{time.process_time() - cpu:.1f} s CPU; peak resident {peak_gb:.2f} GB",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
