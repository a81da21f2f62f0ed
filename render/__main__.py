"""Render a viewpoint file of a scene: ``uavplan-render SCENE viewpoints.csv OUT_DIR``.

SCENE is a scene config name (``conf/scene/SCENE.yaml``) or the path of a scene YAML file; the
camera comes from ``conf/config.yaml`` unless ``--width/--height/--hfov`` are given, the render
settings from ``conf/render/default.yaml`` (``--backend`` overrides the back-end).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from omegaconf import OmegaConf

from render import RenderSettings, render_flight
from scene.camera import Intrinsics
from scene.plan import read_viewpoints
from scene.registry import load_scene

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:

    parser = argparse.ArgumentParser(prog="uavplan-render", description=__doc__)
    parser.add_argument("scene", help="scene config name (conf/scene/NAME.yaml) or a scene YAML path")
    parser.add_argument("viewpoints", type=Path, help="viewpoints.csv (index,x,y,z,yaw_deg,pitch_deg[,kind])")
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--backend", choices=["auto", "egl", "osmesa"], default=None)
    parser.add_argument("--width", type=int, default=None)
    parser.add_argument("--height", type=int, default=None)
    parser.add_argument("--hfov", type=float, default=None, help="horizontal field of view in degrees")
    parser.add_argument("--seed", type=int, default=0, help="the scene seed (${seed} in scene configs)")
    args = parser.parse_args(argv)

    try:
        viewpoints, kinds = read_viewpoints(args.viewpoints)
    except (OSError, ValueError) as err:
        print(f"error: {args.viewpoints}: {err}", file=sys.stderr)
        return 2
    scene_path = Path(args.scene)
    if not scene_path.suffix:
        scene_path = REPO / "conf" / "scene" / f"{args.scene}.yaml"
    if not scene_path.is_file():
        known = sorted(p.stem for p in (REPO / "conf" / "scene").glob("*.yaml"))
        print(f"error: no scene config {scene_path} (known: {', '.join(known) or 'none'})", file=sys.stderr)
        return 2
    camera = OmegaConf.load(REPO / "conf" / "config.yaml").camera
    try:
        intrinsics = Intrinsics(
            args.width or int(camera.width),
            args.height or int(camera.height),
            args.hfov or float(camera.hfov_deg),
        )
    except ValueError as err:
        print(f"error: camera: {err}", file=sys.stderr)
        return 2
    cfg = OmegaConf.load(REPO / "conf" / "render" / "default.yaml")
    if args.backend:
        cfg.backend = args.backend

    # Scene configs interpolate the run's ${seed}.
    root = OmegaConf.merge({"seed": args.seed}, {"scene": OmegaConf.load(scene_path)})
    scene = load_scene(root.scene)
    result = render_flight(
        scene, viewpoints, intrinsics, args.out_dir, RenderSettings.from_config(cfg), kinds
    )
    print(
        f"{len(result.names)} images of {scene.name} in {result.image_dir} ({result.backend}, "
        f"{result.images_per_s:.2f} images/s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
