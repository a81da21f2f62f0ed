"""How accurate is a flight's fused cloud, point by point, against how well each point is conditioned?

    python -m archive.fusion_conditioning RUN/recon/dense church [KEY=VALUE ...]
    COND="0.05,2;0.1,2" python -m archive.fusion_conditioning WORKSPACE church

Fuses the workspace's depth maps along rays (``reconstruct.fusion_rays``, the ``reconstruct.dense``
defaults with the given overrides), scores every fused point against the scene's ground truth and
prints acc50 / acc90 per bin of the fused depth sigma (at one pixel of disparity noise) and of the
support; then the whole cloud, and the cloud through ``well_conditioned`` for each ``cell_m,ratio``
of ``COND`` (completeness per class too). The answer is in results/dense_stage.md.
"""

import os
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from evaluate.__main__ import load_scene_by_name, load_settings
from evaluate.geometry import SurfaceDistance, clip_mesh_to_box
from evaluate.metrics import score_points
from reconstruct.fusion_rays import fuse_along_rays, well_conditioned
from reconstruct.workspace import (
    DEPTH_SUFFIX,
    overlapping_views,
    read_views,
    select_partners,
    stereo_baselines,
)

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    workspace, scene_name, overrides = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
    defaults = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense
    cfg = OmegaConf.merge(defaults, OmegaConf.from_dotlist(overrides))
    views = read_views(workspace)
    partners = select_partners(workspace, views, cfg)
    baselines = stereo_baselines(views, partners, cfg.partner_weights)
    names = sorted(p.name[: -len(DEPTH_SUFFIX)] for p in (workspace / "stereo" / "depth_maps").iterdir())
    cloud = fuse_along_rays(workspace, names, views, overlapping_views(workspace), baselines, cfg.fusion)
    scene = load_scene_by_name(scene_name)
    region = scene.evaluation_region
    inside = region.contains(cloud["points"])
    error = SurfaceDistance(clip_mesh_to_box(scene.ground_truth_mesh, region), origin=region.center)(
        cloud["points"][inside]
    )
    sigma, support = cloud["depth_sigma"][inside], cloud["support"][inside]
    print(f"{len(names)} maps, {len(cloud['points'])} points, {inside.sum()} in the region")
    for label, key, bins in (
        ("depth sigma at 1 px (m)", sigma, [0, 0.02, 0.04, 0.08, 0.16, 0.32, np.inf]),
        ("support (views)", support, [0, 3, 4, 6, 9, 13, np.inf]),
    ):
        print(label)
        for lo, hi in zip(bins[:-1], bins[1:], strict=True):
            m = (key >= lo) & (key < hi)
            if m.any():
                acc50, acc90 = np.percentile(error[m], [50, 90]) * 100
                share = m.mean() * 100
                print(f"  [{lo}, {hi}) {share:5.1f} % of points  acc50 {acc50:5.2f}  acc90 {acc90:6.2f} cm")
    settings = load_settings("default", [], no_vis=True)

    def show(label, c):
        r = score_points(c["points"], scene.ground_truth_mesh, region, settings)
        print(
            f"{label:>14}: {len(c['points']):>9} points  acc90 {r['acc90_m'] * 100:.2f} cm  comp. 5 cm "
            f"{r['comp_050']:.2f} %  walls {r['comp_050_walls']:.2f}  roofs {r['comp_050_roofs']:.2f}  "
            f"ground {r['comp_050_ground']:.2f}",
            flush=True,
        )

    show("fused", well_conditioned(cloud, 0.05, 0.0))
    for spec in filter(None, os.environ.get("COND", "").split(";")):
        cell_m, ratio = map(float, spec.split(","))
        show(f"{cell_m} m, x{ratio}", well_conditioned(cloud, cell_m, ratio))


if __name__ == "__main__":
    main()
