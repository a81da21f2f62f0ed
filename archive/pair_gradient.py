"""Does a stereo pair hold less of a surface where its two views stand at different distances from it?

    python -m archive.pair_gradient WORKSPACE RUN/eval/gt_region.ply STEP

WORKSPACE is a dense workspace (``sparse/`` and ``images/``; a run directory's ``recon/sparse`` and
``images`` linked side by side will do). For every STEP-th view with stereo partners
(``reconstruct.workspace.select_partners``, the defaults of ``conf/reconstruct/default.yaml``) and
at least 2000 ground-truth wall pixels (normal within 45 deg of horizontal), every partner's depth
map (``reconstruct.dense.pair_depth``) is compared with the ground truth's depth. Each pixel is
binned by the pair's along-row disparity gradient there, ``|n.(C_src - C_ref)| / |n.(X - C_ref)|``
(how much the two views' distances from the surface's tangent plane differ, as a share of the
reference's: 0 where both see the surface with the same foreshortening). Prints, per bin, the
share of the pixels and the share held within 5 cm, for walls and for the rest. The answer is in
results/planner_ours.md.
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import trimesh
from omegaconf import OmegaConf

from experiments.depth_errors import WALL_MAX_NORMAL_Z, ground_truth_depth
from reconstruct.stereo.matching import pair_depth
from reconstruct.workspace import read_views, select_partners, sparse_points_by_image
from scene.enclosure import raycasting_scene

ROOT = Path(__file__).resolve().parents[1]
HELD_M = 0.05
MIN_WALL_PIXELS = 2000
EDGES = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, np.inf])


def main() -> None:
    workspace, gt_path, step = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    scene = raycasting_scene(trimesh.load(gt_path, process=False, force="mesh"))
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense
    views = read_views(workspace)
    partners = select_partners(workspace, views, OmegaConf.to_container(cfg))
    points = sparse_points_by_image(workspace)

    def gray(name: str) -> np.ndarray:
        return cv2.imread(str(workspace / "images" / name), cv2.IMREAD_GRAYSCALE)

    bins = len(EDGES) - 1
    pixels = np.zeros((2, bins))  # walls, the rest
    held = np.zeros((2, bins))
    for name in sorted(n for n in views if partners.get(n))[::step]:
        ref = views[name]
        truth, hits, normals = ground_truth_depth(scene, ref)
        wall = np.isfinite(truth) & (np.abs(normals[..., 2]) < WALL_MAX_NORMAL_Z)
        if wall.sum() < MIN_WALL_PIXELS:
            continue
        classes = (wall, np.isfinite(truth) & ~wall)
        for other in partners[name]:
            depth = pair_depth(ref, views[other], gray(name), gray(other), points[name], cfg)
            if depth is None:
                continue
            ok = np.abs(depth - truth) <= HELD_M
            for k, mask in enumerate(classes):
                n, x = normals[mask], hits[mask]
                across = np.abs(n @ (views[other].center - ref.center))
                away = np.maximum(np.abs(np.einsum("ij,ij->i", n, x - ref.center)), 1e-9)
                b = np.clip(np.digitize(across / away, EDGES) - 1, 0, bins - 1)
                pixels[k] += np.bincount(b, minlength=bins)
                held[k] += np.bincount(b, weights=ok[mask].astype(float), minlength=bins)
    for k, label in enumerate(("walls", "ground and roofs")):
        print(label)
        for i in range(bins):
            share = 100 * pixels[k, i] / max(pixels[k].sum(), 1)
            rate = 100 * held[k, i] / max(pixels[k, i], 1)
            span = f"{EDGES[i]:.2f}-{EDGES[i + 1]:.2f}"
            print(f"  gradient {span}: {share:5.1f} % of the pixels, {rate:5.1f} % held")


if __name__ == "__main__":
    main()
