"""Score any point cloud or mesh file against a scene's ground truth.

    uavplan-evaluate recon/dense.ply --scene tomb [--out DIR]
    uavplan-evaluate cloud.ply --gt-mesh gt_region.ply --region x0,y0,z0,x1,y1,z1
    uavplan-evaluate cloud.ply --scene church --config full --set visualise.vmax_m=0.1

Prints the metrics record (JSON) and writes ``metrics.json``, ``gt_region.ply`` and the error
pictures into ``--out`` (default: ``<file>_eval`` beside the file). Exit status 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import trimesh
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from evaluate.loading import ReconstructionFileError
from evaluate.metrics import GroundTruth
from evaluate.record import write_metrics
from evaluate.run import evaluate_reconstruction, parse_region
from evaluate.settings import EvaluationSettings
from scene.base import Box

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavplan-evaluate",
        description="Score a reconstruction (point cloud or mesh, world metres) against a ground truth.",
    )
    parser.add_argument("file", type=Path, help="reconstruction: PLY/OBJ/OFF/STL/GLB/PCD/XYZ/PTS/NPY")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help="scene name of conf/scene/ (ground truth and evaluation region)")
    source.add_argument("--gt-mesh", type=Path, help="ground-truth mesh file instead of a scene")
    parser.add_argument(
        "--region",
        help="evaluation region x0,y0,z0,x1,y1,z1 in metres (with --gt-mesh; default: the mesh's bounds)",
    )
    parser.add_argument(
        "--scene-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene setting, e.g. --scene mesh --scene-set path=model.obj (repeatable)",
    )
    parser.add_argument("--out", type=Path, help="output folder (default: <file>_eval beside the file)")
    parser.add_argument(
        "--config", default="default", help="evaluation config name in conf/evaluate/ (default: default)"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an evaluate setting (repeatable)",
    )
    parser.add_argument("--no-vis", action="store_true", help="skip the coloured PLYs and PNG views")
    return parser


def load_settings(name: str, overrides: list[str], no_vis: bool):
    """The evaluate settings of ``conf/evaluate/<name>.yaml`` with dot-list overrides applied."""
    cfg = _load_group_config(name)
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise ValueError(f"--set expects KEY=VALUE, got {bad}")
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    if no_vis:
        cfg = OmegaConf.merge(cfg, {"visualise": {"enabled": False}})
    return EvaluationSettings.from_config(cfg)


def _load_group_config(name: str):
    """``conf/evaluate/<name>.yaml`` with its ``defaults`` list (names in the same group) merged in."""
    path = CONF_DIR / "evaluate" / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"evaluation config not found: {path}")
    own = OmegaConf.load(path)
    defaults = own.pop("defaults", [])
    merged = OmegaConf.create({})
    for entry in defaults:
        merged = OmegaConf.merge(merged, own if entry == "_self_" else _load_group_config(str(entry)))
    return merged if "_self_" in defaults else OmegaConf.merge(merged, own)


def load_ground_truth(args):
    """A ``Scene`` (``--scene``) or ``GroundTruth`` (``--gt-mesh``) to score against."""
    if args.scene is not None:
        if args.region is not None:
            raise ValueError("--region goes with --gt-mesh; a scene brings its own evaluation region")
        return load_scene_by_name(args.scene, args.scene_set)
    if not args.gt_mesh.is_file():
        raise FileNotFoundError(f"ground-truth mesh not found: {args.gt_mesh}")
    try:
        mesh = trimesh.load(args.gt_mesh, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"{args.gt_mesh}: not a mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{args.gt_mesh}: not a triangle mesh with faces")
    region = parse_region(args.region) if args.region else Box.from_points(mesh.vertices)
    return GroundTruth(args.gt_mesh.stem, mesh, region)


def load_scene_by_name(name: str, overrides: list[str] = ()):
    """``scene.registry.load_scene`` on ``conf/scene/<name>.yaml`` composed like ``run.py`` does,
    with ``KEY=VALUE`` overrides of the scene settings."""
    try:
        # optional dependency: imported on use
        from scene.registry import load_scene
    except ImportError as exc:
        raise ValueError(f"no scene registry available ({exc}); use --gt-mesh FILE --region ...") from exc

    if not (CONF_DIR / "scene" / f"{name}.yaml").is_file():
        known = sorted(p.stem for p in (CONF_DIR / "scene").glob("*.yaml"))
        raise ValueError(f"unknown scene {name!r}; known scenes: {known}")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(config_name="config", overrides=[f"scene={name}", *(f"scene.{o}" for o in overrides)])
    return load_scene(cfg.scene, cache_dir=cfg.get("cache_dir"))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)

    try:
        settings = load_settings(args.config, args.set, args.no_vis)
        if not args.file.is_file():
            raise FileNotFoundError(f"reconstruction file not found: {args.file}")
        ground_truth = load_ground_truth(args)
        out_dir = args.out if args.out is not None else args.file.parent / f"{args.file.stem}_eval"
        record = {"scene": ground_truth.name}
        record.update(evaluate_reconstruction(args.file, ground_truth, settings, out_dir))
        record["status"] = "ok"
        path = write_metrics(out_dir, record)
    except (FileNotFoundError, ReconstructionFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(json.loads(path.read_text()), indent=2))
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
