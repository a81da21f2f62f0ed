"""Do a flight's stereo pairs match its walls worse, or does it have fewer of them?

    python -m archive.partner_maps WORKSPACE RUN/eval/gt_region.ply STEP

WORKSPACE is a dense workspace (``uavplan-bench dense ... --out OUT`` keeps ``OUT/<variant>/dense``).
Prints how many stereo partners its views get (``reconstruct.workspace.select_partners``, the
defaults of ``conf/reconstruct/default.yaml``), then, for every STEP-th view with partners and at
least 2000 ground-truth wall pixels (normal within 45 deg of horizontal), the share of those pixels
each partner's depth map (``reconstruct.dense.pair_depth``) holds within 5 cm of the ground truth's
depth, the best partner's, any partner's, and the combined map's (``consistent_depth``) before and
after the occlusion-edge margin. The answer is in results/planner_ours.md.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import trimesh
from omegaconf import OmegaConf

from experiments.depth_errors import WALL_MAX_NORMAL_Z, ground_truth_depth
from reconstruct.depth_filter import edge_pixels
from reconstruct.stereo.matching import consistent_depth, pair_depth
from reconstruct.workspace import read_views, select_partners, sparse_points_by_image
from scene.enclosure import raycasting_scene

ROOT = Path(__file__).resolve().parents[1]
HELD_M = 0.05
MIN_WALL_PIXELS = 2000


def main() -> None:
    workspace, gt_path, step = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    scene = raycasting_scene(trimesh.load(gt_path, process=False, force="mesh"))
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense
    views = read_views(workspace)
    partners = select_partners(workspace, views, OmegaConf.to_container(cfg))
    counts = np.array([len(partners.get(name, [])) for name in views])
    print(f"partners a view: mean {counts.mean():.2f}, views with 0-4: {np.bincount(counts, minlength=5)}")
    points = sparse_points_by_image(workspace)

    def gray(name: str) -> np.ndarray:
        return cv2.imread(str(workspace / "images" / name), cv2.IMREAD_GRAYSCALE)

    # wall pixels; held by: a partner on average, the best partner, any, combined, combined after edges
    totals = np.zeros(6)
    for name in sorted(n for n in views if partners.get(n))[::step]:
        ref = views[name]
        truth, _, normals = ground_truth_depth(scene, ref)
        wall = np.isfinite(truth) & (np.abs(normals[..., 2]) < WALL_MAX_NORMAL_Z)
        if wall.sum() < MIN_WALL_PIXELS:
            continue
        maps = [pair_depth(ref, views[o], gray(name), gray(o), points[name], cfg) for o in partners[name]]
        maps = [m for m in maps if m is not None]
        if not maps:
            continue
        stack = np.stack(maps)
        held = (np.abs(stack - truth[None]) <= HELD_M)[:, wall]
        combined = consistent_depth(stack, int(cfg.min_consistent_partners), float(cfg.consistency_rel_tol))
        edged = combined.copy()
        edged[edge_pixels(combined, int(cfg.edge_margin_px))] = np.nan
        n_wall = wall.sum()
        totals += [
            n_wall,
            held.mean(axis=1).mean() * n_wall,
            held.mean(axis=1).max() * n_wall,
            held.any(axis=0).sum(),
            (np.abs(combined - truth) <= HELD_M)[wall].sum(),
            (np.abs(edged - truth) <= HELD_M)[wall].sum(),
        ]
    shares = 100 * totals[1:] / totals[0]
    print(
        "wall pixels held within 5 cm: a partner on average {:.1f} %, the best partner {:.1f} %, any "
        "partner {:.1f} %, the combined map {:.1f} %, after the edge margin {:.1f} %".format(*shares)
    )


if __name__ == "__main__":
    main()
