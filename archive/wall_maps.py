"""How many of a flight's depth maps see each ground-truth wall sample, and how many hold it?

    python -m archive.wall_maps WORKSPACE RUN/eval/gt_region.ply CLOUD.ply

WORKSPACE is a dense workspace with its depth maps kept (``uavplan-bench dense ... --out OUT`` keeps
``OUT/<variant>/dense``), CLOUD its fused cloud. The ground truth's walls (normal within 45 deg of
horizontal) are sampled (200,000 surface samples, seed 0). A map *sees* a sample when the sample lies
in its frame, no surface lies between them (ray cast) and the view is within 60 deg of the sample's
normal; it *holds* it when its depth at that pixel is within 5 cm of the sample's. A sample is
*reconstructed* when a fused point lies within 5 cm. Prints the samples and their reconstruction by
the number of maps that see them, then the share held over every (sample, map) pair that sees, by
distance, incidence, the triangulation angle with the map's partners and their axis angle. The
answer is in results/planner_ours.md.
"""

import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

from reconstruct.depth_filter import project
from reconstruct.workspace import DEPTH_SUFFIX, read_maps, read_views, select_partners
from scene.enclosure import raycasting_scene

ROOT = Path(__file__).resolve().parents[1]
WALL_MAX_NORMAL_Z = np.sin(np.radians(45.0))
MAX_INCIDENCE_DEG = 60.0
HELD_M = 0.05


def main() -> None:
    workspace, gt_path, cloud_path = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    mesh = trimesh.load(gt_path, process=False, force="mesh")
    samples, faces = trimesh.sample.sample_surface(mesh, 200000, seed=0)
    normals = mesh.face_normals[faces]
    wall = np.abs(normals[:, 2]) < WALL_MAX_NORMAL_Z
    samples, normals = samples[wall], normals[wall]
    scene = raycasting_scene(mesh)
    views = read_views(workspace)
    dense = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml").dense)
    partners = select_partners(workspace, views, dense)
    mapped = sorted(n for n in views if (workspace / "stereo" / "depth_maps" / (n + DEPTH_SUFFIX)).exists())
    seen_by = np.zeros(len(samples), int)
    pairs = []  # (incidence deg, distance m, held, triangulation deg, partner axis deg, has a depth)
    for name in mapped:
        view = views[name]
        u, v, z = project(samples, view.K, view.rotation, view.translation)
        to_view = view.center - samples
        distance = np.linalg.norm(to_view, axis=1)
        direction = to_view / distance[:, None]
        cos_incidence = np.einsum("ij,ij->i", direction, normals)
        inside = (z > 0) & (u >= 0) & (u <= view.width - 1) & (v >= 0) & (v <= view.height - 1)
        inside &= cos_incidence > np.cos(np.radians(MAX_INCIDENCE_DEG))
        idx = np.flatnonzero(inside)
        rays = np.concatenate([samples[idx] + 1e-3 * direction[idx], direction[idx]], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        seen = idx[hit >= distance[idx] - 2e-3]
        seen_by[seen] += 1
        depth, _ = read_maps(workspace, name)
        measured = depth[np.rint(v[seen]).astype(int), np.rint(u[seen]).astype(int)]
        held = np.abs(measured - z[seen]) <= HELD_M
        others = partners.get(name, [])
        axes = [np.degrees(np.arccos(np.clip(view.forward @ views[o].forward, -1, 1))) for o in others]
        axis = np.median(axes) if others else np.nan
        if others:
            angles = []
            for other in others:
                to_other = views[other].center - samples[seen]
                to_other /= np.linalg.norm(to_other, axis=1)[:, None]
                cos_angle = np.einsum("ij,ij->i", direction[seen], to_other)
                angles.append(np.degrees(np.arccos(np.clip(cos_angle, -1, 1))))
            triangulation = np.median(np.stack(angles), 0)
        else:
            triangulation = np.full(len(seen), np.nan)
        incidence = np.degrees(np.arccos(cos_incidence[seen]))
        has_depth = np.isfinite(measured) & (measured > 0)
        pairs.append(
            np.stack([incidence, distance[seen], held, triangulation, np.full(len(seen), axis), has_depth], 1)
        )
    pairs = np.concatenate(pairs)
    cloud = np.asarray(o3d.io.read_point_cloud(cloud_path).points)
    reconstructed = cKDTree(cloud).query(samples, k=1, distance_upper_bound=HELD_M)[0] <= HELD_M
    print(
        f"{len(samples)} wall samples, {len(mapped)} maps, {100 * reconstructed.mean():.1f} % "
        f"reconstructed; of the samples they see, maps have a depth at {100 * pairs[:, 5].mean():.1f} % "
        f"and hold {100 * pairs[:, 2].mean():.1f} %"
    )
    for lo, hi in ((0, 3), (3, 5), (5, 7), (7, 10), (10, 10**6)):
        m = (seen_by >= lo) & (seen_by < hi)
        share, done = 100 * m.mean(), 100 * reconstructed[m].mean()
        print(f"  seen by {lo}-{hi - 1} maps: {share:5.1f} % of samples, {done:5.1f} % reconstructed")
    for label, column, edges in (
        ("distance m", 1, (0, 20, 25, 30, 40, 60)),
        ("incidence deg", 0, (0, 15, 30, 45, 60)),
        ("triangulation deg", 3, (0, 10, 15, 20, 30, 90)),
        ("partner axis deg", 4, (0, 10, 20, 30, 45, 90)),
    ):
        cells = []
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            m = (pairs[:, column] >= lo) & (pairs[:, column] < hi)
            if m.sum() >= 200:
                share, held = 100 * m.mean(), 100 * pairs[m, 2].mean()
                cells.append(f"{lo}-{hi}: {share:.0f} % of pairs, {held:.0f} % held")
        print(f"  {label}: " + " | ".join(cells))


if __name__ == "__main__":
    main()
