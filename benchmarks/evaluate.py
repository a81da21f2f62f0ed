"""Benchmark of the evaluation: 5 million points against a 1-million-triangle ground truth.

    uavplan-bench evaluate [--points 5000000] [--grid 708] [--from-file] [--vis]

The ground truth is a noisy terrain with a dome (a ``grid x grid`` vertex lattice: 708 gives
999,698 triangles) over 40 m x 40 m; the reconstruction samples it with 2 cm noise, 3 % outliers up
to 1 m, a missing quarter-disc (a hole, the slow case of the nearest-neighbour search) and 2 %
of the points outside the evaluation region. Prints the wall time of each step and the peak
resident memory of the process while scoring (sampled every 20 ms).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import trimesh

from evaluate.geometry import sample_surface
from evaluate.metrics import GroundTruth, score_details, score_file_details
from evaluate.settings import EvaluationSettings
from evaluate.visualise import write_error_visualisation
from scene.base import Box

SIZE_M = 40.0


def terrain_mesh(n: int, seed: int = 0) -> trimesh.Trimesh:
    """Noisy terrain with a 6 m dome: n x n vertices over SIZE_M x SIZE_M metres, 2 (n-1)^2 faces."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0.0, SIZE_M, n)
    gx, gy = np.meshgrid(xs, xs)
    r2 = (gx - 20.0) ** 2 + (gy - 20.0) ** 2
    gz = (
        6.0 * np.exp(-r2 / 60.0) + 0.3 * np.sin(gx / 3.0) * np.cos(gy / 4.0) + rng.normal(0.0, 0.01, gx.shape)
    )
    vertices = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    faces = np.concatenate([np.column_stack([a, a + 1, a + n + 1]), np.column_stack([a, a + n + 1, a + n])])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def reconstruction(mesh: trimesh.Trimesh, n_points: int, region: Box, seed: int = 1) -> np.ndarray:
    """n_points near the surface: noise, outliers, a hole, a few points outside the region."""
    rng = np.random.default_rng(seed)
    n_outside = int(0.02 * n_points)
    # Sample a bit more than needed, then cut the hole (a quarter disc of radius 12 m, ~22 % of the area).
    surface, _ = sample_surface(mesh, 1.35 * n_points / mesh.area, seed)
    surface = surface[(surface[:, 0] - SIZE_M) ** 2 + surface[:, 1] ** 2 > 12.0**2]
    surface = surface[: n_points - n_outside]
    points = surface + rng.normal(0.0, 0.02, surface.shape)
    outliers = rng.random(len(points)) < 0.03
    points[outliers] += rng.uniform(-1.0, 1.0, (int(outliers.sum()), 3))
    outside = rng.uniform(region.hi_array + 1.0, region.hi_array + 5.0, (n_outside, 3))
    return np.concatenate([points, outside])


class PeakMemory:
    """Peak resident set size (bytes) of this process while the context is open."""

    def __enter__(self):
        self.process = psutil.Process()
        self.peak = self.process.memory_info().rss
        self.running = True
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()
        return self

    def _poll(self):
        while self.running:
            self.peak = max(self.peak, self.process.memory_info().rss)
            time.sleep(0.02)

    def __exit__(self, *exc):
        self.running = False
        self.thread.join()
        self.peak = max(self.peak, self.process.memory_info().rss)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=5_000_000)
    parser.add_argument("--grid", type=int, default=708, help="vertices per side (708 -> ~1M triangles)")
    parser.add_argument("--from-file", action="store_true", help="also score from a binary PLY on disk")
    parser.add_argument("--vis", action="store_true", help="also time the error pictures")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    mesh = terrain_mesh(args.grid)
    region = Box((2.0, 2.0, -1.0), (38.0, 38.0, 8.0))
    points = reconstruction(mesh, args.points, region)
    print(
        f"setup: {len(mesh.faces):,} triangles, {len(points):,} points in {time.perf_counter() - start:.1f} s"
    )
    settings = EvaluationSettings()
    gb = 1024.0**3
    rss_before = psutil.Process().memory_info().rss

    with PeakMemory() as memory:
        start, cpu_start = time.perf_counter(), time.process_time()
        details = score_details(points, mesh, region, settings, progress=True)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    r = details.record
    load = ", ".join(f"{v:.1f}" for v in psutil.getloadavg())
    print(f"machine: {psutil.cpu_count()} CPUs, load average {load}")
    print(
        f"score_points: {wall:.1f} s wall, {cpu:.1f} s CPU  "
        f"(prepare: filter, sort, clip, sample {r['eval_prepare_time_s']:.1f} s, "
        f"accuracy {r['eval_accuracy_time_s']:.1f} s, "
        f"completeness {r['eval_completeness_time_s']:.1f} s)"
    )
    print(f"  {r['n_points_in_region']:,} points in region, {r['n_gt_samples']:,} ground-truth samples")
    print(f"  peak RSS {memory.peak / gb:.2f} GiB (before scoring {rss_before / gb:.2f} GiB)")
    print(
        f"  acc90 {r['acc90_m']:.4f} m, acc95 {r['acc95_m']:.4f} m, comp_050 {r['comp_050']:.2f} %, "
        f"comp_075 {r['comp_075']:.2f} %, chamfer {r['chamfer_m']:.4f} m"
    )

    if args.from_file:
        # heavy (open3d): imported on use
        import open3d as o3d

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "dense.ply"
            o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
            start = time.perf_counter()
            from_file = score_file_details(path, GroundTruth("bench", mesh, region), settings)
            seconds = time.perf_counter() - start
            print(f"score_file (binary PLY, {path.stat().st_size / 1e6:.0f} MB): {seconds:.1f} s")
            if from_file.record["acc90_m"] != r["acc90_m"]:
                raise RuntimeError("scoring from the PLY file disagrees with scoring the array")

    if args.vis:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            write_error_visualisation(
                tmp,
                details.points_in_region,
                details.accuracy_distances,
                details.gt_samples,
                details.completeness_distances,
                Box.from_points(details.gt_region_mesh.bounds),
                settings.visualise,
            )
            print(f"error pictures (2 PLYs, 10 PNGs): {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
