"""CUDA (``pycolmap.patch_match_stereo``) vs CPU (SGBM) dense back-end on one small tomb workspace.

Three steps; the middle one runs on a GPU machine (no network needed there):

1. here: ``python -m benchmarks.dense_cuda workspace SPARSE IMAGES /tmp/dc/ws`` cuts the
   ``--num-images`` registered views nearest (camera centre) to the ``--seed`` view out of the
   model (their 3-D points seen by >= 2 of them kept), undistorts them at ``--max-image-size`` and
   stores the images as JPEG (quality 95) so the workspace travels; ``workspace.tar`` beside it.
2. device (H100, Python 3.12, pycolmap-cuda12 4.0.4 and its libraries carried in ``.dense_cuda``,
   see the header of ``benchmarks/dense_cuda.sh`` for how to build it):
   ``bash benchmarks/dense_cuda.sh dense test`` runs ``dense /tmp/ws --backend cuda --out
   $OUT`` and the ``cuda``-marked test.
3. here: the same ``dense`` with ``--backend cpu`` on the same ``workspace.tar``, then
   ``python -m benchmarks.dense_cuda score dense_cuda.ply dense_cpu.ply --workspace WS``
   scores both with the evaluation stage in the scene's region and in the region the subset sees
   (the scene region cut in x, y to the 2-98 % range of the subset's sparse points).

``render VIEWPOINTS_CSV OUT`` (device: ``device_dense_cuda.sh render``) times MuJoCo EGL rendering
of the tomb's exploratory flight at 1024x768 with ``render.render_flight``.

As run on 2026-11-23 (tomb exploratory flight, 187 registered views; ``workspace ... --num-images 40
--seed 93 --max-image-size 640``; scored with ``score ... --voxel-m 0``): CUDA on an H100 408.7 s of
patch match (20 auto-selected sources a view, photometric + geometric pass) + 2.4 s fusion, 232,129
points, acc90/95 0.092/0.117 m, comp 5/7.5 cm 7.6/19.9 %; CPU SGBM on 2 shared cores 53.1 s + 10.0 s,
177,582 points, 0.050/0.066 m, 17.6/32.2 %. EGL rendering on the H100: 37.4 images/s (100 views).

``dense`` writes ``dense_<backend>.ply`` (x, y, z float32 only, voxel-averaged at ``--voxel-m``
when it would exceed ~15 MB, the same for both back-ends) and ``dense_<backend>.json`` (times).
It needs only numpy, OpenCV, PyYAML and pycolmap, so it runs where omegaconf is missing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tarfile
import time
from pathlib import Path

import numpy as np
import yaml

from evaluate.__main__ import load_scene_by_name
from evaluate.metrics import score_points
from reconstruct.align import merge_model
from reconstruct.dense import fuse
from reconstruct.dense_settings import DenseSettings
from reconstruct.stereo.depth_maps import compute_depth_maps_cpu, compute_depth_maps_cuda
from reconstruct.workspace import prepare_workspace
from render import RenderSettings, render_flight
from scene.base import Box
from scene.camera import Intrinsics
from scene.registry import load_scene

ROOT = Path(__file__).resolve().parents[1]

CONFIG = ROOT / "conf" / "reconstruct" / "default.yaml"
MAX_PLY_POINTS = 1_250_000  # 12 bytes each: the PLY stays under 16 MB, to copy back


def dense_settings() -> DenseSettings:
    """The default ``reconstruct.dense`` settings (plain YAML: no interpolation in that file)."""
    return DenseSettings.from_config(yaml.safe_load(CONFIG.read_text())["dense"])


def subset_model(rec, image_ids):
    """A new reconstruction of ``image_ids`` only: their cameras, poses, keypoints and the 3-D
    points observed by at least two of them (tracks cut to them)."""
    # heavy (pycolmap): imported on use
    import pycolmap

    out = pycolmap.Reconstruction()
    merge_model(out, rec, image_ids)
    return out


def build_workspace(sparse: Path, images: Path, out: Path, num_images: int, seed: int, max_size: int) -> Path:
    """Undistorted COLMAP workspace of the ``num_images`` views nearest the ``seed``-th (by name)."""
    # heavy (cv2): imported on use
    import cv2

    # heavy (pycolmap): imported on use
    import pycolmap

    rec = pycolmap.Reconstruction(sparse)
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.image(i).name)
    centers = np.array([rec.image(i).projection_center() for i in ids])
    order = np.argsort(np.linalg.norm(centers - centers[min(seed, len(ids) - 1)], axis=1))
    chosen = [ids[k] for k in order[:num_images]]
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    subset_model(rec, chosen).write(_mkdir(out / "subset_sparse"))
    settings = dataclasses.replace(dense_settings(), max_image_size=max_size)
    ws = prepare_workspace(out / "subset_sparse", images, out / "ws", settings)
    # JPEG (quality 95) instead of PNG: a third of the size, so the workspace fits the carry budget.
    und = pycolmap.Reconstruction(ws / "sparse")
    for image in und.images.values():
        png = ws / "images" / image.name
        jpg = png.with_suffix(".jpg")
        cv2.imwrite(str(jpg), cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 95])
        png.unlink()
        image.name = jpg.name
    und.write(ws / "sparse")
    cfg_lines = (ws / "stereo" / "patch-match.cfg").read_text().splitlines()
    (ws / "stereo" / "patch-match.cfg").write_text(
        "".join(f"{Path(n).with_suffix('.jpg').name if k % 2 == 0 else n}\n" for k, n in enumerate(cfg_lines))
    )
    (ws / "stereo" / "fusion.cfg").unlink(missing_ok=True)
    with tarfile.open(out / "workspace.tar", "w") as tar:
        tar.add(ws, arcname=".")
    print(f"{len(chosen)} views, {und.num_points3D()} sparse points -> {ws}, {out / 'workspace.tar'}")
    return ws


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def read_ply_xyz(path: Path) -> np.ndarray:
    """Vertex positions (N, 3) float64 of a binary little-endian PLY with scalar vertex properties."""
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "uint8": "u1", "int": "<i4", "float32": "<f4"}
    with open(path, "rb") as f:
        fields, count = [], 0
        while (line := f.readline().decode().strip()) != "end_header":
            parts = line.split()
            if parts[:2] == ["element", "vertex"]:
                count = int(parts[2])
            elif parts[0] == "property":
                fields.append((parts[2], types[parts[1]]))
        data = np.frombuffer(f.read(), dtype=np.dtype(fields), count=count)
    return np.column_stack([data["x"], data["y"], data["z"]]).astype(np.float64)


def write_ply_xyz(path: Path, points: np.ndarray) -> None:
    """Binary PLY of positions only (float32)."""
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(np.ascontiguousarray(points, dtype="<f4").tobytes())


def voxel_mean(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean of the points in each occupied voxel of edge ``voxel`` metres."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), points)
    return sums / counts[:, None]


def run_dense(workspace: Path, backend: str, out: Path, voxel: float) -> dict:
    """Depth maps with one back-end, then fusion; write the PLY and a JSON of counts and times."""
    # heavy (pycolmap): imported on use
    import pycolmap

    settings = dense_settings()
    shutil.rmtree(workspace / "stereo" / "depth_maps", ignore_errors=True)
    shutil.rmtree(workspace / "stereo" / "normal_maps", ignore_errors=True)
    (workspace / "stereo" / "depth_maps").mkdir(parents=True)
    (workspace / "stereo" / "normal_maps").mkdir(parents=True)
    start = time.perf_counter()
    compute = compute_depth_maps_cuda if backend == "cuda" else compute_depth_maps_cpu
    valid = compute(workspace, settings)
    depth_time = time.perf_counter() - start
    names = [n for n, count in valid.items() if count > 0]
    start = time.perf_counter()
    fused_ply = workspace / f"fused_{backend}.ply"
    n_fused = fuse(workspace, fused_ply, settings, names)
    fusion_time = time.perf_counter() - start
    points = read_ply_xyz(fused_ply)
    written = points if len(points) <= MAX_PLY_POINTS else voxel_mean(points, voxel)
    out.mkdir(parents=True, exist_ok=True)
    write_ply_xyz(out / f"dense_{backend}.ply", written)
    record = {
        "backend": backend,
        "pycolmap": pycolmap.__version__,
        "has_cuda": bool(pycolmap.has_cuda),
        "n_views": len(valid),
        "n_depth_maps": len(names),
        "depth_time_s": round(depth_time, 2),
        "fusion_time_s": round(fusion_time, 2),
        "n_fused_points": n_fused,
        "n_written_points": len(written),
        "voxel_m": voxel if len(written) < len(points) else None,
    }
    (out / f"dense_{backend}.json").write_text(json.dumps(record, indent=2))
    print(json.dumps(record))
    return record


def score(plys: list[Path], workspace: Path, scene_name: str, voxel: float) -> None:
    """Evaluation-stage metrics of each PLY in the scene region and in the subset's x, y range."""
    # heavy (pycolmap): imported on use
    import pycolmap

    scene = load_scene_by_name(scene_name)
    region = scene.evaluation_region
    sparse = np.array([p.xyz for p in pycolmap.Reconstruction(workspace / "sparse").points3D.values()])
    lo, hi = np.percentile(sparse[:, :2], [2.0, 98.0], axis=0)
    seen = Box(
        tuple(np.r_[np.maximum(lo, region.lo_array[:2]), region.lo_array[2]]),
        tuple(np.r_[np.minimum(hi, region.hi_array[:2]), region.hi_array[2]]),
    )
    for path in plys:
        points = read_ply_xyz(path)
        if voxel > 0:  # the same resolution for every cloud: a fair completeness
            points = voxel_mean(points, voxel)
        for label, box in (("scene region", region), ("subset region", seen)):
            r = score_points(points, scene.ground_truth_mesh, box)
            keys = [k for k in r if k.startswith(("acc", "comp", "n_", "fraction"))]
            print(path.name, label, json.dumps({k: r[k] for k in keys}))


def time_render(viewpoints_csv: Path, out: Path, n_views: int, cache_dir: Path) -> dict:
    """Build the tomb (textures generated into ``cache_dir``) and render the first ``n_views`` of a
    flight's ``viewpoints.csv`` with EGL; print and return the timings (s) and images/s."""
    scene_cfg = {**yaml.safe_load((ROOT / "conf" / "scene" / "tomb.yaml").read_text()), "seed": 0}
    start = time.perf_counter()
    scene = load_scene(scene_cfg, cache_dir=cache_dir)
    scene_build_s = time.perf_counter() - start
    cfg = {**yaml.safe_load((ROOT / "conf" / "render" / "default.yaml").read_text()), "backend": "egl"}
    camera = yaml.safe_load((ROOT / "conf" / "config.yaml").read_text())["camera"]
    intrinsics = Intrinsics(int(camera["width"]), int(camera["height"]), float(camera["hfov_deg"]))
    viewpoints = np.loadtxt(viewpoints_csv, delimiter=",", skiprows=1, usecols=(1, 2, 3, 4, 5))[:n_views]
    result = render_flight(scene, viewpoints, intrinsics, out / "images", RenderSettings.from_config(cfg))
    record = {
        "backend": result.backend,
        "n_views": len(viewpoints),
        "scene_build_s": round(scene_build_s, 2),
        "renderer_build_s": round(result.build_time_s, 2),
        "render_s": round(result.render_time_s, 2),
        "images_per_s": round(result.images_per_s, 2),
        "cpu_s_per_image": round(result.render_cpu_s / len(viewpoints), 3),
    }
    print(json.dumps(record))
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="step", required=True)
    w = sub.add_parser("workspace", help="cut, undistort and pack a workspace (here)")
    w.add_argument("sparse", type=Path)
    w.add_argument("images", type=Path)
    w.add_argument("out", type=Path)
    w.add_argument("--num-images", type=int, default=40)
    w.add_argument("--seed", type=int, default=100, help="index (by name) of the centre view")
    w.add_argument("--max-image-size", type=int, default=640)
    d = sub.add_parser("dense", help="depth maps + fusion with one back-end")
    d.add_argument("workspace", type=Path)
    d.add_argument("--backend", choices=("cpu", "cuda"), required=True)
    d.add_argument("--out", type=Path, required=True)
    d.add_argument("--voxel-m", type=float, default=0.01, help="voxel (m) when the PLY would be too big")
    s = sub.add_parser("score", help="score PLYs with the evaluation stage (here)")
    s.add_argument("plys", type=Path, nargs="+")
    s.add_argument("--workspace", type=Path, required=True)
    s.add_argument("--scene", default="tomb")
    s.add_argument("--voxel-m", type=float, default=0.01, help="voxel (m) applied to every cloud (0: none)")
    r = sub.add_parser("render", help="time MuJoCo EGL rendering of the tomb's flight (device)")
    r.add_argument("viewpoints_csv", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--views", type=int, default=100)
    r.add_argument("--cache-dir", type=Path, default=Path("/tmp/cache"))
    args = parser.parse_args(argv)
    if args.step == "workspace":
        build_workspace(args.sparse, args.images, args.out, args.num_images, args.seed, args.max_image_size)
    elif args.step == "dense":
        run_dense(args.workspace, args.backend, args.out, args.voxel_m)
    elif args.step == "render":
        time_render(args.viewpoints_csv, args.out, args.views, args.cache_dir)
    else:
        score(args.plys, args.workspace, args.scene, args.voxel_m)
    return 0


if __name__ == "__main__":
    sys.exit(main())
