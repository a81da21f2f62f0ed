"""Where a cell's accuracy goes: the SfM model's placement in the world (the GNSS datum), its cameras'
own errors, and what is left to the dense stage.

    uavplan-diagnose accuracy-sources study/settled/tomb/ours/gsd0.03/lowest/seed0 \\
        study/settled/tomb/ours/gsd0.03/high/seed0 --out archive/pre_p1/accuracy_sources/tomb

For every finished run (``recon/sparse``, ``images/cameras.json``, ``recon/dense.ply``):

- **Cameras.** The similarity that best maps the SfM camera centres onto the true ones (Umeyama,
  ``pycolmap.estimate_sim3d``): its rotation, scale and shift are the model's datum error, set by
  the GNSS fixes it was held to (``reconstruct.gnss.sigma_m``), the same for every point of the
  cloud. What each camera is off by after it (rotation, position) is the model's own, internal
  error, the one that biases a stereo pair.
- **Cloud.** The fused cloud registered to the ground truth by point-to-plane ICP (Open3D,
  ``--icp-points`` points of the cloud against as many surface samples, within
  ``--icp-distance-m``), then scored by the cell's own evaluator (``evaluate.metrics.score_points``).
  Its accuracy beside the record's is the accuracy with the datum taken out: the part a flight plan
  and the dense stage answer for. Benchmarks that register a submission to the ground truth before
  scoring it (Tanks and Temples, ETH3D) report this one; the study's tables keep the record's,
  where the datum counts, as it does for a crew without ground control points.

Writes ``accuracy_sources.csv`` and ``accuracy_sources.md`` into ``--out``.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh

from evaluate.__main__ import load_scene_by_name, load_settings
from evaluate.loading import load_reconstruction
from evaluate.metrics import score_points
from experiments.observations import SPARSE_DIR
from experiments.runs import RunDirectoryError, out_is_a_file, tool_parser, write_findings
from reconstruct.align import rotation_angles_deg
from reconstruct.flight import read_flight

log = logging.getLogger(__name__)

DENSE_FILE = Path("recon") / "dense.ply"
IMAGES_DIR = Path("images")
CLASSES = ("ground", "roofs", "walls")


def camera_errors(
    centers: np.ndarray, rotations: np.ndarray, true_centers: np.ndarray, true_rotations: np.ndarray
) -> dict:
    """SfM cameras (centres (N, 3) m, world-to-camera rotations (N, 3, 3)) against the true ones:
    the best similarity between the centres (``datum_rotation_deg``, ``datum_scale_ppm``,
    ``datum_shift_m``: how far it moves the centres' centroid) and each camera's error after it
    (``internal_rotation_*_deg``, ``internal_position_*_m``, median and p90)."""
    # heavy (pycolmap): imported on use
    import pycolmap

    if len(centers) < 3:
        raise RunDirectoryError(f"{len(centers)} registered cameras of the flight: too few for a similarity")
    true_from_model = pycolmap.estimate_sim3d(centers, true_centers)
    if true_from_model is None:
        raise RunDirectoryError("the camera centres admit no similarity onto the true ones (degenerate)")
    matrix = np.asarray(true_from_model.matrix())
    scale = float(np.cbrt(np.linalg.det(matrix[:, :3])))
    turn = matrix[:, :3] / scale
    moved = centers @ matrix[:, :3].T + matrix[:, 3]
    # A camera's rotation in the true frame: cam_from_model @ model_from_true, whose rotation is turn^T.
    internal_rotation = rotation_angles_deg(rotations @ turn.T, true_rotations)
    internal_position = np.linalg.norm(moved - true_centers, axis=1)
    centroid = centers.mean(axis=0)
    return {
        "datum_rotation_deg": float(rotation_angles_deg(turn[None], np.eye(3)[None])[0]),
        "datum_scale_ppm": (scale - 1.0) * 1e6,
        "datum_shift_m": float(np.linalg.norm(centroid @ matrix[:, :3].T + matrix[:, 3] - centroid)),
        "internal_rotation_median_deg": float(np.median(internal_rotation)),
        "internal_rotation_p90_deg": float(np.percentile(internal_rotation, 90)),
        "internal_position_median_m": float(np.median(internal_position)),
        "internal_position_p90_m": float(np.percentile(internal_position, 90)),
    }


def model_cameras(reconstruction, flight) -> tuple[np.ndarray, ...]:
    """The registered cameras of ``flight``: SfM centres and rotations, true centres and rotations."""
    index = {name: i for i, name in enumerate(flight.names)}
    images = [reconstruction.image(i) for i in reconstruction.reg_image_ids()]
    images = [image for image in images if image.name in index]
    truth = np.array([index[image.name] for image in images], dtype=int)
    centers = np.array([image.projection_center() for image in images]).reshape(-1, 3)
    rotations = np.array([image.cam_from_world().rotation.matrix() for image in images]).reshape(-1, 3, 3)
    return centers, rotations, flight.positions[truth], flight.rotations[truth]


def icp_to_ground_truth(
    points: np.ndarray, gt_mesh, n_points: int, max_distance_m: float, seed: int = 0
) -> np.ndarray:
    """The rigid 4x4 transform (world metres) that registers ``points`` to ``gt_mesh``: Open3D's
    point-to-plane ICP from ``n_points`` of the points to as many surface samples, pairs farther
    apart than ``max_distance_m`` ignored. Coordinates are taken about the points' centroid."""
    # heavy (open3d): imported on use
    import open3d as o3d

    rng = np.random.default_rng(seed)
    source = points[rng.choice(len(points), min(len(points), n_points), replace=False)]
    samples, faces = trimesh.sample.sample_surface(gt_mesh, n_points, seed=seed)
    origin = source.mean(axis=0)
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(samples) - origin))
    target.normals = o3d.utility.Vector3dVector(np.asarray(gt_mesh.face_normals)[faces])
    moving = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source - origin))
    result = o3d.pipelines.registration.registration_icp(
        moving,
        target,
        max_distance_m,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=100
        ),
    )
    about_origin = np.asarray(result.transformation)
    shift = np.eye(4)
    shift[:3, 3] = origin
    unshift = np.eye(4)
    unshift[:3, 3] = -origin
    return shift @ about_origin @ unshift


def analyse_run(run_dir: Path, icp_points: int, icp_distance_m: float) -> dict:
    """One row: the run's names, its record's accuracy, camera errors, registered accuracy."""

    # heavy (pycolmap): imported on use
    import pycolmap

    for needed in ("metrics.json", SPARSE_DIR, IMAGES_DIR, DENSE_FILE):
        if not (run_dir / needed).exists():
            raise RunDirectoryError(f"{run_dir}: no {needed} (not a finished run with its dense cloud)")
    record = json.loads((run_dir / "metrics.json").read_text())
    scene = load_scene_by_name(str(record["scene"]))
    settings = load_settings("default", [], no_vis=True)
    row = {
        "run": str(run_dir),
        "scene": record["scene"],
        "planner": record["planner"],
        "n_images": record.get("n_viewpoints"),
    }
    row |= camera_errors(
        *model_cameras(pycolmap.Reconstruction(str(run_dir / SPARSE_DIR)), read_flight(run_dir / IMAGES_DIR))
    )
    points, _ = load_reconstruction(run_dir / DENSE_FILE)
    inside = scene.evaluation_region.contains(points)
    transform = icp_to_ground_truth(points[inside], scene.ground_truth_mesh, icp_points, icp_distance_m)
    centroid = points[inside].mean(axis=0)
    row["icp_rotation_deg"] = float(rotation_angles_deg(transform[None, :3, :3], np.eye(3)[None])[0])
    row["icp_shift_m"] = float(np.linalg.norm(transform[:3, :3] @ centroid + transform[:3, 3] - centroid))
    registered = points @ transform[:3, :3].T + transform[:3, 3]
    scored = score_points(registered, scene.ground_truth_mesh, scene.evaluation_region, settings)
    for key in ("acc90_m", *(f"acc90_{c}_m" for c in CLASSES), "comp_050"):
        row[key] = record.get(key)
        row[f"registered_{key}"] = scored.get(key)
    return row


def summarise(frame: pd.DataFrame) -> str:
    """The findings as markdown: one table row per run."""
    cm = 100.0
    lines = [
        "| run | images | datum rot. (deg) / shift (mm) | cameras after it: rot. p50 (deg) / pos. p50 (mm) "
        "| cloud's ICP rot. (deg) / shift (mm) | acc90 (cm) | registered | ground | roofs "
        "| walls (record -> registered) | comp. 5 cm record / registered |",
        "| :-- | --: | --: | --: | --: | --: | --: | --: | --: | --: | --: |",
    ]
    for row in frame.itertuples():
        classes = [
            f"{getattr(row, f'acc90_{c}_m') * cm:.2f} -> {getattr(row, f'registered_acc90_{c}_m') * cm:.2f}"
            for c in CLASSES
        ]
        lines.append(
            f"| {'/'.join(Path(row.run).parts[-5:])} | {row.n_images} "
            f"| {row.datum_rotation_deg:.4f} / {row.datum_shift_m * 1e3:.1f} "
            f"| {row.internal_rotation_median_deg:.4f} / {row.internal_position_median_m * 1e3:.1f} "
            f"| {row.icp_rotation_deg:.4f} / {row.icp_shift_m * 1e3:.1f} "
            f"| {row.acc90_m * cm:.2f} | {row.registered_acc90_m * cm:.2f} | {' | '.join(classes)} "
            f"| {row.comp_050:.2f} / {row.registered_comp_050:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = tool_parser("uavplan-diagnose accuracy-sources", __doc__)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (a cell's output with its cloud)")
    parser.add_argument("--out", type=Path, required=True, help="folder for accuracy_sources.csv and .md")
    # 1M points register in ~20 s; 3 cm keeps pairs within the clouds' error (acc95 ~3 cm) and
    # off the next surface.
    parser.add_argument("--icp-points", type=int, default=1_000_000, help="points ICP registers")
    parser.add_argument("--icp-distance-m", type=float, default=0.03, help="ICP pair distance bound (m)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.icp_points < 100 or not args.icp_distance_m > 0:
        print("error: --icp-points must be >= 100 and --icp-distance-m > 0", file=sys.stderr)
        return 2
    if out_is_a_file(args.out):
        return 2
    try:
        frame = pd.DataFrame([analyse_run(run, args.icp_points, args.icp_distance_m) for run in args.runs])
    except RunDirectoryError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    write_findings(args.out, "accuracy_sources", frame, "Where the accuracy goes", summarise(frame))
    return 0


if __name__ == "__main__":
    sys.exit(main())
