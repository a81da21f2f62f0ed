"""The evaluation stage: score a reconstruction file against a scene, write the ground truth it was
scored against and the error pictures, return the flat record for ``metrics.json``.
"""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh

from evaluate.geometry import clip_mesh_to_box
from evaluate.metrics import score_details, score_file_details
from evaluate.settings import EvaluationSettings
from evaluate.visualise import write_error_visualisation
from scene.base import Box
from scene.io import write_atomic

log = logging.getLogger(__name__)

GT_REGION_FILE = "gt_region.ply"


def evaluate_reconstruction(reconstruction_path: str | Path | None, scene, cfg, out_dir: str | Path) -> dict:
    """Score a reconstruction against ``scene`` and write the evaluation's files into ``out_dir``.

    Args:
        reconstruction_path: point cloud or mesh in world metres (``recon/dense.ply``); None scores
            an empty reconstruction (a failed run): counts, null distances, zero completeness.
        scene: ``scene.base.Scene`` or ``evaluate.metrics.GroundTruth``.
        cfg: the ``evaluate`` config (Mapping/DictConfig/``EvaluationSettings``; None = defaults).
        out_dir: folder for ``gt_region.ply`` (the ground truth cut to the region, to re-score
            with ``uavplan-evaluate FILE --gt-mesh gt_region.ply --region <eval_region>``) and the
            error pictures (``error_points.ply``, ``gt_coverage.ply``, ``error_*.png``, ``coverage_*.png``).

    Returns:
        The flat metrics record (``evaluate.metrics.score_points``'s keys) plus
        ``reconstruction_path``, ``reconstruction_kind``, ``gt_mesh_path``, ``eval_region``
        (``"x0,y0,z0,x1,y1,z1"``), ``eval_dir`` and ``eval_total_time_s``.

    Raises:
        FileNotFoundError, evaluate.loading.ReconstructionFileError: unreadable reconstruction.
    """
    settings = EvaluationSettings.from_config(cfg)
    start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    region: Box = scene.evaluation_region
    region_mesh = clip_mesh_to_box(scene.ground_truth_mesh, region)
    if reconstruction_path is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # logged by score_details; the record says it
            details = score_details(np.zeros((0, 3)), scene.ground_truth_mesh, region, settings, region_mesh)
        details.record.update(reconstruction_path=None, reconstruction_kind=None)
    else:
        details = score_file_details(reconstruction_path, scene, settings, region_mesh, progress=True)
    record = details.record
    record["gt_mesh_path"] = None
    if settings.export_gt_mesh:
        record["gt_mesh_path"] = str(export_region_mesh(region_mesh, out_dir / GT_REGION_FILE).resolve())
    record["eval_region"] = format_region(region)
    record["eval_dir"] = str(out_dir.resolve())
    if settings.visualise.enabled and len(details.points_in_region):
        write_error_visualisation(
            out_dir,
            details.points_in_region,
            details.accuracy_distances,
            details.gt_samples,
            details.completeness_distances,
            Box.from_points(region_mesh.bounds),
            settings.visualise,
            label=str(getattr(scene, "name", "")),
        )
    record["eval_total_time_s"] = time.perf_counter() - start
    log.info(
        "evaluate: %d/%d points in region, %s",
        record["n_points_in_region"],
        record["n_points"],
        summary(record),
    )
    return record


def export_region_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write the ground truth cut to the region as a binary PLY with float64 vertices, atomically.

    Double precision (trimesh writes float32) so that re-scoring from the file draws exactly the
    same surface samples and distances.
    """
    vertices = np.ascontiguousarray(mesh.vertices, dtype="<f8")
    faces = np.empty(len(mesh.faces), dtype=[("count", "u1"), ("index", "<i4", (3,))])
    faces["count"] = 3
    faces["index"] = mesh.faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment ground truth cut to the evaluation region\n"
        f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )

    def writer(tmp: Path) -> None:
        with tmp.open("wb") as f:
            f.write(header.encode("ascii"))
            f.write(vertices.tobytes())
            f.write(faces.tobytes())

    return write_atomic(path, writer)


def format_region(region: Box) -> str:
    """``"x0,y0,z0,x1,y1,z1"`` in metres (full precision), the CLI's ``--region`` format."""
    return ",".join(repr(float(v)) for v in (*region.lo, *region.hi))


def parse_region(text: str) -> Box:
    """Inverse of ``format_region``; raises ValueError naming the text when it is not six numbers."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError as exc:
        raise ValueError(f"--region {text!r}: expected six numbers x0,y0,z0,x1,y1,z1") from exc
    if len(values) != 6:
        raise ValueError(f"--region {text!r}: expected six numbers x0,y0,z0,x1,y1,z1, got {len(values)}")
    return Box(tuple(values[:3]), tuple(values[3:]))


def summary(record: dict) -> str:
    """One line of the headline metrics (accuracy in m, completeness in %)."""
    parts = []
    for key, value in record.items():
        if (key.startswith("acc") and key[3:4].isdigit()) or key.startswith("comp_"):
            parts.append(f"{key}={'null' if value is None else f'{value:.4g}'}")
    return " ".join(parts)
