"""Benchmark of a user's large textured scan: load, render and score a 2-5 M triangle mesh.

    uavplan-bench large-mesh [--subdivisions 4] [--half-more] [--views 10]

The scan is made from what the repository has (no download): the shared school model (Collada,
one texture), subdivided ``--subdivisions`` times (x4 triangles each; ``--half-more`` subdivides
half of the result once more) with its UVs interpolated and a 1 cm displacement noise along the
normals, as a photogrammetry mesh has; written as a textured GLB. Then ``scene.mesh_loader`` loads
it (with the enclosed-surface and plinth checks), the renderer renders ``--views`` views of it,
and the evaluation scores a 5 M point cloud sampled from it. Prints each step's wall and CPU time
and the process's peak resident memory after it.
"""

from __future__ import annotations

import argparse
import glob
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from omegaconf import OmegaConf

from evaluate.geometry import sample_surface
from evaluate.metrics import score_details
from render import RenderSettings, SceneRenderer
from scene.camera import Intrinsics
from scene.mesh_loader import MeshSceneSpec, load_mesh_scene

SCHOOL = sorted(
    glob.glob(str(Path(__file__).resolve().parents[2] / "shared/data/meshes/school/meshes/*.dae"))
)


def peak_rss_gb() -> float:
    """Peak resident memory of this process so far (GB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def timed(label: str, fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    print(
        f"{label:<34} wall {time.perf_counter() - wall:7.1f} s   CPU {time.process_time() - cpu:7.1f} s   "
        f"peak RSS {peak_rss_gb():5.2f} GB",
        flush=True,
    )
    return out


def make_scan(source: str, subdivisions: int, half_more: bool, out: Path) -> tuple[Path, int]:
    """A textured GLB of the school, subdivided and displaced like a scan; returns (path, faces)."""
    loaded = trimesh.load(source, process=False)
    mesh = next(g for g in loaded.dump(concatenate=False) if g.visual.kind == "texture")
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    attrs = {"uv": np.asarray(mesh.visual.uv, float)}
    for k in range(subdivisions + int(half_more)):
        index = np.arange(len(faces) // 2) if k == subdivisions else None
        vertices, faces, attrs = trimesh.remesh.subdivide(
            vertices, faces, face_index=index, vertex_attributes=attrs
        )
    scan = trimesh.Trimesh(vertices, faces, process=False)
    rng = np.random.default_rng(0)
    scan.vertices += (
        scan.vertex_normals * rng.normal(0.0, 0.01, (len(vertices), 1)) / 0.0254
    )  # 1 cm in inches
    scan.visual = trimesh.visual.TextureVisuals(uv=attrs["uv"], material=mesh.visual.material)
    path = out / "scan.glb"
    scan.export(path)
    return path, len(faces)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--subdivisions", type=int, default=4)
    parser.add_argument("--half-more", action="store_true", help="subdivide half of the faces once more")
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--points", type=int, default=5_000_000)
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        path, n_faces = timed(
            "make the scan (not the loader)",
            lambda: make_scan(SCHOOL[0], args.subdivisions, args.half_more, Path(tmp)),
        )
        print(f"scan: {n_faces:,} triangles, {path.stat().st_size / 2**20:.0f} MiB GLB", flush=True)
        # The GLB is in the school's inches: scene.scale converts.
        scene = timed(
            "load (scene.mesh_loader)",
            lambda: load_mesh_scene(path, MeshSceneSpec(scale=0.0254), cache_dir=Path(tmp) / "cache"),
        )
        print(
            f"scene: {scene.n_faces:,} faces with the ground, "
            f"extent {np.round(scene.structure_bounds.extent, 1)} m"
        )
        camera = Intrinsics(1024, 768, 60.0)
        angles = np.linspace(0.0, 2 * np.pi, args.views, endpoint=False)
        views = np.column_stack(
            [
                30 * np.cos(angles),
                30 * np.sin(angles),
                np.full(args.views, 15.0),
                np.degrees(angles) + 180.0,
                np.full(args.views, -20.0),
            ]
        )
        cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf/render/default.yaml")

        def render():
            with SceneRenderer(scene, camera, RenderSettings.from_config(cfg)) as renderer:
                return [renderer.render(v) for v in views]

        timed(f"render {args.views} views at 1024x768", render)
        gt = scene.ground_truth_mesh
        cloud, _ = sample_surface(gt, args.points / gt.area, 1)
        cloud = cloud + np.random.default_rng(2).normal(0.0, 0.01, cloud.shape)
        details = timed(
            f"score {len(cloud):,} points", lambda: score_details(cloud, gt, scene.evaluation_region)
        )
        r = details.record
        n_samples = r["n_gt_samples"] + r["n_gt_samples_enclosed"]
        print(
            f"scored: acc90 {r['acc90_m']:.4f} m, comp 5 cm {r['comp_050']:.1f} %, "
            f"enclosed {r['gt_enclosed_pct']:.1f} % of {n_samples:,} samples"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
