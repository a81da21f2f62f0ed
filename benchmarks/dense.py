"""Dense stage before and after: one flight's aligned sparse model through variants of the dense
settings, each timed (wall and CPU: process + children) and scored against the scene's ground truth.

    uavplan-bench dense study/default_v3/tomb/ours/seed0 --scene tomb \\
        --variant default= --variant partners3=num_partners=3 \\
        --variant small=max_image_size=768,num_partners=3 \\
        --variant chunked=fusion.max_memory_gb=2

A variant is ``NAME=KEY=VALUE,KEY=VALUE`` over ``conf/reconstruct/default.yaml``'s ``dense`` section
(``NAME=`` alone: the defaults). Every variant starts from the same ``recon/sparse`` and
``images/`` of the run directory and writes ``--out/<name>/dense.ply``; run it on an idle machine
(one variant at a time, all cores) and quote the table it prints.

``--cover K [K ...]`` only counts, for each K, the views
``reconstruct.stereo.depth_maps.reference_views`` keeps
when every sparse point needs K reference views (``reference_views_per_point=K``; no dense
matching): whether a flight is redundant enough for the cover to save depth maps at all.

``--true-poses`` replaces the aligned model's camera poses with the simulation's true ones
(``images/cameras.json``) before dense matching: the difference to a run without it is the part of
the cloud's error that the SfM cameras cause, the rest is the dense stage's own.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from benchmarks import write_records
from evaluate.__main__ import load_scene_by_name, load_settings
from evaluate.run import evaluate_reconstruction
from reconstruct.dense import dense_reconstruct, fuse_report
from reconstruct.dense_settings import DenseSettings
from reconstruct.flight import read_flight
from reconstruct.stereo.depth_maps import reference_views, sparse_incidence
from reconstruct.timing import stage_time
from reconstruct.workspace import DEPTH_SUFFIX

ROOT = Path(__file__).resolve().parents[1]
REPORTED = ("acc90_m", "acc95_m", "comp_050", "comp_050_walls", "comp_050_roofs", "comp_050_ground")


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME=K=V,K=V`` -> (NAME, ["K=V", ...]); raises ValueError naming the bad part."""
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise ValueError(f"--variant {text!r}: expected NAME=KEY=VALUE,... (NAME= for the defaults)")
    overrides = [item for item in rest.split(",") if item]
    bad = [item for item in overrides if "=" not in item]
    if bad:
        raise ValueError(f"--variant {name}: expected KEY=VALUE, got {bad}")
    return name, overrides


def true_pose_model(sparse_dir: Path, image_dir: Path, out_dir: Path) -> Path:
    """A copy of the sparse model in ``out_dir`` whose registered cameras sit at their true poses
    (``image_dir/cameras.json``); points and tracks stay as SfM left them. Returns ``out_dir``."""
    # heavy (pycolmap): imported on use
    import pycolmap

    flight = read_flight(image_dir)
    truth = {name: (flight.rotations[i], flight.translations[i]) for i, name in enumerate(flight.names)}
    rec = pycolmap.Reconstruction(sparse_dir)
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        if image.name not in truth:
            raise ValueError(f"{image_dir}: no true pose for {image.name}")
        rotation, translation = truth[image.name]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(rotation)), np.asarray(translation))
        rec.frame(image.frame_id).set_cam_from_world(image.camera_id, pose)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec.write(out_dir)
    return out_dir


def cover_sizes(run_dir: Path, per_point: list[int], min_new_points: int) -> dict:
    """How many of ``run_dir``'s registered views the reference-view cover keeps for each K of
    ``per_point``; with the views, sparse points and their mean track length (views per point)."""
    # heavy (pycolmap): imported on use
    import pycolmap

    model = pycolmap.Reconstruction(run_dir / "recon" / "sparse")
    names = sorted(model.image(i).name for i in model.reg_image_ids())
    incidence = sparse_incidence(model, names)
    kept = {int(k): int(reference_views(incidence, int(k), min_new_points).sum()) for k in per_point}
    return {
        "n_views": len(names),
        "n_points": int(incidence.shape[1]),
        "mean_track": incidence.nnz / max(incidence.shape[1], 1),
        "kept": kept,
    }


def run_variant(
    run_dir: Path,
    out_dir: Path,
    overrides: list[str],
    scene,
    eval_settings,
    true_poses: bool = False,
    depth_from: Path | None = None,
) -> dict:
    """Dense reconstruction of ``run_dir``'s sparse model with ``overrides``; timings and metrics.
    ``depth_from``: an earlier variant's folder whose depth maps these settings share: fuse only."""
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense
    absent = object()  # a setting whose default is null (fusion.max_memory_gb) is known
    unknown = [
        o.split("=")[0] for o in overrides if OmegaConf.select(cfg, o.split("=")[0], default=absent) is absent
    ]
    if unknown:
        raise ValueError(f"unknown dense settings {unknown}")
    settings = DenseSettings.from_config(OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides)))
    out_dir.mkdir(parents=True, exist_ok=True)
    sparse = run_dir / "recon" / "sparse"
    if true_poses:
        sparse = true_pose_model(sparse, run_dir / "images", out_dir / "sparse_true_poses")
    with stage_time() as clock:
        if depth_from is not None:
            workspace = depth_from / "dense"
            maps = sorted(
                p.name[: -len(DEPTH_SUFFIX)] for p in (workspace / "stereo" / "depth_maps").iterdir()
            )
            fused = fuse_report(workspace, out_dir / "dense.ply", settings, maps)
            dense = {
                "n_depth_maps": len(maps),
                "n_dense_points": fused.n_points,
                "dense_path": out_dir / "dense.ply",
            }
        else:
            dense = dense_reconstruct(
                sparse, run_dir / "images", out_dir, settings, ground_truth=scene.ground_truth_mesh
            )
    record = {
        "dense_time_s": clock.wall_s,
        "dense_cpu_s": clock.cpu_s,
        "n_depth_maps": dense["n_depth_maps"],
        "n_dense_points": dense["n_dense_points"],
    }
    metrics = evaluate_reconstruction(dense["dense_path"], scene, eval_settings, out_dir / "eval")
    return record | {key: metrics.get(key) for key in REPORTED}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run directory with recon/sparse and images/")
    parser.add_argument("--scene", help="its scene (conf/scene/<name>.yaml); needed by --variant")
    parser.add_argument("--variant", action="append", default=[], help="NAME=KEY=VALUE,... (repeatable)")
    parser.add_argument(
        "--reuse-depth",
        action="store_true",
        help="a variant that changes only fusion.* settings fuses an earlier variant's depth maps (marked *)",
    )
    parser.add_argument(
        "--cover", type=int, nargs="+", metavar="K", help="only count the views the cover keeps for each K"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench_dense")
    parser.add_argument(
        "--true-poses", action="store_true", help="dense-match from the true camera poses, not SfM's"
    )
    args = parser.parse_args(argv)
    try:
        if not args.variant and not args.cover:
            raise ValueError("give --variant NAME=... (dense runs) or --cover K ... (view counts)")
        if args.variant and not args.scene:
            raise ValueError("--variant needs --scene (the ground truth to score against)")
        if args.cover and min(args.cover) < 1:
            raise ValueError(f"--cover: K must be >= 1, got {min(args.cover)}")
        variants = [parse_variant(v) for v in args.variant]
        for needed in ("recon/sparse", "images") if args.variant else ("recon/sparse",):
            if not (args.run_dir / needed).is_dir():
                raise ValueError(f"{args.run_dir}: no {needed}/ (not a finished run directory)")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.cover:
        min_new = int(
            OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense.reference_min_new_points
        )
        cover = cover_sizes(args.run_dir, args.cover, min_new)
        print(
            f"{args.run_dir}: {cover['n_views']} views, {cover['n_points']} sparse points, "
            f"{cover['mean_track']:.1f} views per point; a view kept adds >= {min_new} under-covered points"
        )
        for k, kept in cover["kept"].items():
            print(f"  K={k}: {kept} of {cover['n_views']} views get a depth map")
        return 0

    scene = load_scene_by_name(args.scene)
    settings = load_settings("default", [], no_vis=True)
    header = f"{'variant':>14} {'wall s':>7} {'cpu s':>7} {'maps':>5} {'points':>9} " + " ".join(
        f"{k:>15}" for k in REPORTED
    )
    print(f"{args.run_dir} ({args.scene}), {os.cpu_count()} cores\n{header}", flush=True)
    rows = {}
    depth_of: dict[str, Path] = {}  # depth settings (all but fusion) -> the variant that computed them
    for name, overrides in variants:
        depth_key = json.dumps(sorted(o for o in overrides if not o.startswith("fusion.")))
        reuse = depth_of.get(depth_key) if args.reuse_depth else None
        try:
            record = run_variant(
                args.run_dir, args.out / name, overrides, scene, settings, args.true_poses, depth_from=reuse
            )
            depth_of.setdefault(depth_key, args.out / name)
        except ValueError as exc:
            print(f"error: variant {name}: {exc}", file=sys.stderr)
            return 2
        rows[name] = record | {"overrides": overrides}
        name = f"{name}*" if reuse is not None else name
        print(
            f"{name:>14} {record['dense_time_s']:>7.1f} {record['dense_cpu_s']:>7.1f} "
            f"{record['n_depth_maps']:>5d} {record['n_dense_points']:>9d} "
            + " ".join(f"{record[k] if record[k] is not None else float('nan'):>15.4g}" for k in REPORTED),
            flush=True,
        )
    write_records(args.out, "bench_dense", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
