"""How accurate are a flight's depth maps, pair by pair, against the ground truth?

    uavplan-diagnose depth-errors study/default_v4/church/ours/default/seed0 \\
        study/default_v4/church/smith/default/seed0 --views 60 --out archive/pre_p1/depth_errors/church

For every run: its aligned sparse model and images are put in a fresh dense workspace, the CPU
back-end's stereo partners are chosen as a cell chooses them (``reconstruct.dense.select_partners``
with the run's own ``reconstruct.dense`` settings), and for ``--views`` reference views (evenly
spread over the flight, or all) every partner's SGBM depth map (``pair_depth``) and the combined
map (``consistent_depth``) are compared with the ground truth's depth along the same pixels
(``eval/gt_region.ply`` ray-cast from the registered camera). Per pair it records the
triangulation angle at the ground-truth points (median over the pixels), the median depth, the
share of ground-truth pixels with a depth, and the absolute depth error (median, p90, share over
5 cm), for all pixels and for wall pixels (ground-truth normal within 45 deg of horizontal).

A planner whose fused cloud is less accurate than another's at the same distance has either worse
pairs (angle, foreshortening) or worse partners for the same pairs; this tells which.

Writes ``pairs.csv`` (one row per run, view and partner; ``partner`` = ``combined`` for the
combined map) and ``summary.md`` (per run, per triangulation-angle bin).
"""

from __future__ import annotations

import logging
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import trimesh
from omegaconf import OmegaConf

from experiments.observations import GT_REGION_FILE, SPARSE_DIR
from experiments.runs import RunDirectoryError, read_run_config, tool_parser
from reconstruct.dense_settings import DenseSettings
from reconstruct.stereo.matching import consistent_depth, pair_depth, partner_weights
from reconstruct.workspace import View, prepare_workspace, read_views, select_partners, sparse_points_by_image
from scene.enclosure import raycasting_scene
from scene.io import write_text_atomic

log = logging.getLogger(__name__)

IMAGES_DIR = Path("images")
# A ground-truth normal within this many degrees of horizontal makes a wall pixel.
WALL_MAX_NORMAL_Z = float(np.sin(np.radians(45.0)))
ERROR_THRESHOLD_M = 0.05
ANGLE_BINS_DEG = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 90.0)


def ground_truth_depth(scene, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth (H, W) along the optical axis (NaN = no hit), hit points (H, W, 3), normals (H, W, 3)."""
    # heavy (open3d): imported on use
    import open3d as o3d

    u, v = np.meshgrid(np.arange(view.width, dtype=np.float64), np.arange(view.height, dtype=np.float64))
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view.K).T
    # Rays with unit z in the camera frame: the hit distance is the depth along the optical axis.
    directions = rays_cam @ view.rotation
    origins = np.broadcast_to(view.center, directions.shape)
    rays = np.concatenate([origins, directions], -1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().reshape(view.height, view.width).astype(np.float64)
    t[~np.isfinite(t)] = np.nan
    normals = hit["primitive_normals"].numpy().reshape(view.height, view.width, 3)
    points = origins + directions * t[..., None]
    return t, points, normals


def depth_error_row(depth: np.ndarray, gt: np.ndarray, walls: np.ndarray) -> dict:
    """Coverage and absolute error (m) of one depth map against the ground-truth depth."""
    has_gt = np.isfinite(gt)
    both = has_gt & np.isfinite(depth)
    err = np.abs(depth - gt)
    gt_walls = has_gt & walls
    row = {
        "gt_pixels": int(has_gt.sum()),
        "valid_share": float(both.sum() / max(has_gt.sum(), 1)),
        "valid_share_walls": float((both & walls).sum() / max(gt_walls.sum(), 1)),
    }
    for label, mask in (("all", both), ("walls", both & walls)):
        e = err[mask]
        row[f"n_{label}"] = int(len(e))
        row[f"err50_{label}_m"] = float(np.median(e)) if len(e) else np.nan
        row[f"err90_{label}_m"] = float(np.percentile(e, 90)) if len(e) else np.nan
        row[f"over5cm_{label}"] = float(np.mean(e > ERROR_THRESHOLD_M)) if len(e) else np.nan
    return row


def seen_by(points: np.ndarray, has_gt: np.ndarray, src: View, src_gt: np.ndarray, rel_tol: float = 0.01):
    """Reference pixels (H, W) bool whose ground-truth point ``points`` lies in ``src``'s image and
    is the surface ``src`` sees there (its ground-truth depth ``src_gt`` agrees within ``rel_tol``):
    the most a pair with ``src`` could measure."""
    cam = (points[has_gt] - src.center) @ src.rotation.T
    seen = np.zeros(has_gt.shape, bool)
    z = cam[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        pix = cam @ src.K.T
        col = np.rint(pix[:, 0] / pix[:, 2]).astype(np.int64, copy=False)
        row = np.rint(pix[:, 1] / pix[:, 2]).astype(np.int64, copy=False)
    inside = (z > 0) & (col >= 0) & (col < src.width) & (row >= 0) & (row < src.height)
    visible = np.zeros(len(z), bool)
    depth_there = src_gt[row[inside], col[inside]]
    visible[inside] = np.abs(depth_there - z[inside]) <= rel_tol * z[inside]
    seen[has_gt] = visible
    return seen


def triangulation_angle_deg(points: np.ndarray, ref: View, src: View, mask: np.ndarray) -> float:
    """Median angle (deg) at the ground-truth points ``points[mask]`` between the two camera rays."""
    p = points[mask]
    if len(p) == 0:
        return float("nan")
    a = p - ref.center
    b = p - src.center
    cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


def analyse_run(
    run_dir: Path, n_views: int | None, workdir: Path, dense_overrides: Sequence[str] = ()
) -> pd.DataFrame:
    """One row per (reference view, partner) and per reference view's combined map.

    ``dense_overrides``: ``key=value`` dotlist on the run's ``reconstruct.dense`` settings (the
    same flight and SfM under another matcher setting, for an ablation)."""
    cfg = read_run_config(run_dir)
    if cfg is None:
        raise RunDirectoryError(f"{run_dir}: no .hydra/config.yaml (not a run directory)")
    if dense_overrides:
        try:
            cfg.reconstruct.dense = OmegaConf.merge(
                cfg.reconstruct.dense, OmegaConf.from_dotlist(list(dense_overrides))
            )
        except Exception as exc:  # noqa: BLE001 - a malformed override is reported as such
            raise RunDirectoryError(f"--dense {' '.join(dense_overrides)}: {exc}") from exc
    for needed in (SPARSE_DIR, IMAGES_DIR, GT_REGION_FILE):
        if not (run_dir / needed).exists():
            raise RunDirectoryError(f"{run_dir}: missing {needed}")
    try:
        dense = DenseSettings.from_config(cfg.reconstruct.dense)
    except ValueError as exc:
        raise RunDirectoryError(f"{run_dir}: {exc}") from exc
    if dense.backend == "cuda":
        raise RunDirectoryError(f"{run_dir}: ran the CUDA back-end; this compares the CPU back-end's pairs")
    workspace = prepare_workspace(run_dir / SPARSE_DIR, run_dir / IMAGES_DIR, workdir / "dense", dense)
    views = read_views(workspace)
    partners = select_partners(workspace, views, dense)
    points_by_name = sparse_points_by_image(workspace)
    gt_mesh = trimesh.load(run_dir / GT_REGION_FILE, process=False, force="mesh")
    scene = raycasting_scene(gt_mesh)

    names = sorted(n for n in views if partners.get(n))
    if n_views is not None and n_views < len(names):
        names = [names[i] for i in np.linspace(0, len(names) - 1, n_views).round().astype(int)]
    rows = []
    for i, name in enumerate(names):
        ref = views[name]
        ref_points = points_by_name[name]
        ref_gray = cv2.imread(str(workspace / "images" / name), cv2.IMREAD_GRAYSCALE)
        gt, points, normals = ground_truth_depth(scene, ref)
        walls = np.abs(normals[..., 2]) < WALL_MAX_NORMAL_Z
        has_gt = np.isfinite(gt)
        base = {
            "run": str(run_dir),
            "view": name,
            "gt_depth50_m": float(np.nanmedian(gt)) if has_gt.any() else np.nan,
        }
        gt_walls = has_gt & walls
        depths, measured = [], []
        seen_any = np.zeros(has_gt.shape, bool)
        for src_name in partners[name]:
            src = views[src_name]
            seen = seen_by(points, has_gt, src, ground_truth_depth(scene, src)[0])
            seen_any |= seen
            src_gray = cv2.imread(str(workspace / "images" / src_name), cv2.IMREAD_GRAYSCALE)
            depth = pair_depth(ref, src, ref_gray, src_gray, ref_points, dense)
            row = base | {
                "partner": src_name,
                "baseline_m": float(np.linalg.norm(src.center - ref.center)),
                "angle_deg": triangulation_angle_deg(points, ref, src, has_gt),
                "axes_deg": float(np.degrees(np.arccos(np.clip(ref.forward @ src.forward, -1, 1)))),
                "seen_share": float(seen.sum() / max(has_gt.sum(), 1)),
                "seen_share_walls": float((seen & walls).sum() / max(gt_walls.sum(), 1)),
            }
            if depth is None:
                rows.append(row | {"valid_share": 0.0})
                continue
            depths.append(depth)
            measured.append(src)
            rows.append(row | depth_error_row(depth, gt, walls))
        if depths:
            combined = consistent_depth(
                np.stack(depths),
                dense.min_consistent_partners,
                dense.consistency_rel_tol,
                partner_weights(ref, measured, dense),
            )
            rows.append(
                base
                | {
                    "partner": "combined",
                    "n_partners": len(depths),
                    "seen_share": float(seen_any.sum() / max(has_gt.sum(), 1)),
                    "seen_share_walls": float((seen_any & walls).sum() / max(gt_walls.sum(), 1)),
                }
                | depth_error_row(combined, gt, walls)
            )
        log.info("%s: view %d / %d (%s)", run_dir, i + 1, len(names), name)
    return pd.DataFrame(rows)


def summarise(pairs: pd.DataFrame) -> str:
    """Markdown: per run, the pairs by triangulation-angle bin, and the combined maps."""
    lines = ["# Depth-map error against the ground truth, pair by pair", ""]
    single = pairs[pairs["partner"] != "combined"].dropna(subset=["angle_deg"]).copy()
    single["angle_bin"] = pd.cut(single["angle_deg"], ANGLE_BINS_DEG)
    for run, group in single.groupby("run"):
        lines += [
            f"## {run}",
            "",
            "| angle (deg) | pairs | median depth (m) | valid | walls seen | walls valid | err50 walls (cm) "
            "| err90 walls (cm) | > 5 cm walls | err90 all (cm) |",
            "| :-- | --: | --: | --: | --: | --: | --: | --: | --: | --: |",
        ]
        for interval, g in group.groupby("angle_bin", observed=True):
            lines.append(
                f"| {interval} | {len(g)} | {g['gt_depth50_m'].median():.1f} | {g['valid_share'].mean():.2f} "
                f"| {g['seen_share_walls'].mean():.2f} | {g['valid_share_walls'].mean():.2f} "
                f"| {100 * g['err50_walls_m'].median():.1f} | {100 * g['err90_walls_m'].median():.1f} "
                f"| {100 * g['over5cm_walls'].median():.1f} % | {100 * g['err90_all_m'].median():.1f} |"
            )
        lines.append("")
    combined = pairs[pairs["partner"] == "combined"]
    lines += [
        "## Combined maps (what fusion reads)",
        "",
        "| run | views | median depth (m) | valid | walls seen | walls valid | err50 walls (cm) "
        "| err90 walls (cm) | > 5 cm walls | err90 all (cm) | median pair angle (deg) |",
        "| :-- | --: | --: | --: | --: | --: | --: | --: | --: | --: | --: |",
    ]
    for run, g in combined.groupby("run"):
        angle = single.loc[single["run"] == run, "angle_deg"].median()
        lines.append(
            f"| {run} | {len(g)} | {g['gt_depth50_m'].median():.1f} | {g['valid_share'].mean():.2f} "
            f"| {g['seen_share_walls'].mean():.2f} | {g['valid_share_walls'].mean():.2f} "
            f"| {100 * g['err50_walls_m'].median():.1f} | {100 * g['err90_walls_m'].median():.1f} "
            f"| {100 * g['over5cm_walls'].median():.1f} % | {100 * g['err90_all_m'].median():.1f} "
            f"| {angle:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = tool_parser("uavplan-diagnose depth-errors", __doc__)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (a cell's output)")
    parser.add_argument(
        "--views", type=int, default=60, help="reference views per run, evenly spread (0: all)"
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for pairs.csv and summary.md")
    parser.add_argument(
        "--dense",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="reconstruct.dense settings to change for every run (e.g. max_num_disparities=512)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.views < 0:
        print("error: --views must be >= 0", file=sys.stderr)
        return 2
    frames = []
    try:
        for run in args.runs:
            workdir = Path(tempfile.mkdtemp(prefix="depth_errors_"))
            try:
                frames.append(analyse_run(run, args.views or None, workdir, args.dense))
            finally:
                shutil.rmtree(workdir, ignore_errors=True)
    except RunDirectoryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    pairs = pd.concat(frames, ignore_index=True)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "pairs.csv", pairs.to_csv(index=False))
    summary = summarise(pairs)
    write_text_atomic(args.out / "summary.md", summary)
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
