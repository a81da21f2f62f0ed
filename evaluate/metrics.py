"""Accuracy, completeness, precision, F-score and Chamfer distance of a reconstruction against a
ground-truth mesh, restricted to the scene's evaluation region (Smith et al. 2018's benchmark,
Middlebury methodology; see ``reference/baselines.md``).

Definitions (distances in metres, percentages in 0-100):

- The scored ground truth is the mesh's surface inside the region, triangles cut exactly at the
  box (``clip_mesh_to_box``): uniform-by-area samples of it are then uniform on the in-region
  surface with an exact count, and a huge ground triangle reaching far outside costs nothing.
- Only reconstructed points inside the region are scored; the others are counted.
- ``acc{q}_m``: the smallest d such that at least q % of the scored points lie within d of the
  scored surface (true point-to-triangle distance; NumPy's ``inverted_cdf`` percentile).
- ``comp_{t}``: % of ground-truth samples within t (<=) of a scored point (t in mm, 3 digits).
- ``prec_{t}``: % of scored points within t of the scored surface; ``fscore_{t}`` = 2PR/(P+R)
  (0 when both are 0).
- ``chamfer_m`` = (``chamfer_acc_m`` + ``chamfer_comp_m``) / 2, the mean distances of each
  direction, each clipped at ``distance_cap_m``: an exact nearest-neighbour search from samples
  far inside a hole costs minutes, and outliers beyond the cap say nothing the percentiles miss.
- Completeness per kind of surface, to see where a flight misses: each ground-truth sample takes
  the class of its triangle (``surface_classes``): ``ground`` (facing up, below
  ``ground_height_m``), ``roofs`` (facing up, above it), ``walls`` (facing sideways) and
  ``undersides`` (facing down: eaves, arches). ``gt_share_{class}`` is the class's % of the samples,
  ``comp_{t}_{class}`` the completeness over its samples (null for a class without samples).
  Accuracy per class: a scored point takes the class of its nearest ground-truth triangle (the
  triangle's normal, the point's height); ``acc_share_{class}`` is the class's % of the scored
  points, ``acc{q}_{class}_m`` the percentile over them (null for a class without points).
- Enclosed surface (``exclude_enclosed``): a sample that no straight ray from it reaches the open
  along (buried faces, sealed interiors; ``scene.enclosure.exposure``) is left out of every
  completeness figure and counted in ``n_gt_samples_enclosed`` and ``gt_enclosed_pct[_{class}]``
  (% of all samples, of the class's samples); ``n_gt_samples`` counts the scored ones.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from evaluate.geometry import SurfaceDistance, clip_mesh_to_box, sample_surface, spatial_order
from evaluate.loading import load_reconstruction
from evaluate.settings import EvaluationSettings, percentile_key, threshold_key
from scene.base import Box
from scene.enclosure import exposure, raycasting_scene

log = logging.getLogger(__name__)


class EmptyReconstructionWarning(UserWarning):
    """No reconstructed point inside the evaluation region: distances are recorded as null."""


@dataclass(frozen=True)
class GroundTruth:
    """What a reconstruction is scored against (a ``scene.base.Scene`` provides the same two fields).

    Attributes:
        name: scene name for the record.
        ground_truth_mesh: the ground-truth surface in world metres.
        evaluation_region: only surface and points inside this box are scored.
    """

    name: str
    ground_truth_mesh: trimesh.Trimesh
    evaluation_region: Box


@dataclass
class ScoreDetails:
    """Everything a score is made of, for the record and the error pictures.

    Attributes:
        record: the flat metrics record (see the module docstring).
        points_in_region: (M, 3) scored reconstruction points (m), in Z-order (not file order).
        accuracy_distances: (M,) their distance to the in-region ground-truth surface (m).
        gt_region_mesh: the ground truth cut to the region (the surface scored against).
        gt_samples: (S, 3) scored (exposed) ground-truth surface samples (m), in Z-order.
        completeness_distances: (S,) distance from each sample to the nearest scored point (m);
            ``inf`` beyond ``distance_cap_m``.
    """

    record: dict
    points_in_region: np.ndarray
    accuracy_distances: np.ndarray
    gt_region_mesh: trimesh.Trimesh
    gt_samples: np.ndarray
    completeness_distances: np.ndarray


def score_points(points, gt_mesh: trimesh.Trimesh, region: Box, cfg=None) -> dict:
    """The flat metrics record of reconstructed points against a ground-truth mesh.

    Args:
        points: (N, 3) reconstructed points in world metres (non-finite rows are dropped and counted).
        gt_mesh: ground-truth mesh in world metres.
        region: evaluation region; surface and points outside it are not scored.
        cfg: ``evaluate`` settings (Mapping, DictConfig or ``EvaluationSettings``; None = defaults).

    Returns:
        Keys ``n_points``, ``n_points_nonfinite``, ``n_points_in_region``, ``n_points_outside_region``,
        ``fraction_outside_region``, ``gt_area_m2``, ``n_gt_samples``, ``acc{q}_m``, ``acc_mean_m``,
        ``comp_{t}``, ``prec_{t}``, ``fscore_{t}``, ``chamfer_m``, ``chamfer_acc_m``,
        ``chamfer_comp_m``, ``gt_beyond_cap_fraction``, ``eval_*time_s`` (metres, percentages
        0-100, seconds). With no point in the region the distance metrics are None (with an
        ``EmptyReconstructionWarning``), completeness and F-score are 0.

    Raises:
        ValueError: malformed points, or no ground-truth surface inside the region.
    """
    return score_details(points, gt_mesh, region, cfg).record


def score_file(path: str | Path, scene, cfg=None) -> dict:
    """The metrics record of a point-cloud or mesh file against a scene's ground truth.

    Args:
        path: reconstruction in world metres (see ``evaluate.loading.load_reconstruction``; meshes are
            scored by their vertices, or by surface samples with ``mesh_input: surface``).
        scene: a ``scene.base.Scene`` or ``GroundTruth`` (``ground_truth_mesh``, ``evaluation_region``).
        cfg: ``evaluate`` settings (None = defaults).

    Raises:
        FileNotFoundError, evaluate.loading.ReconstructionFileError: the file is missing or is not a
            point cloud or mesh (the message names it).
    """
    return score_file_details(path, scene, cfg).record


def score_file_details(
    path: str | Path, scene, cfg=None, gt_region_mesh: trimesh.Trimesh | None = None, progress: bool = False
) -> ScoreDetails:
    """``score_file`` keeping the per-point distances (for the error pictures); see ``score_details``."""
    settings = EvaluationSettings.from_config(cfg)
    points, kind = load_reconstruction(
        path,
        settings.mesh_input,
        settings.mesh_sample_density_per_m2,
        settings.gt_sample_seed,
        max_samples=settings.max_gt_samples,
    )
    details = score_details(
        points, scene.ground_truth_mesh, scene.evaluation_region, settings, gt_region_mesh, progress
    )
    details.record.update(reconstruction_path=str(Path(path).resolve()), reconstruction_kind=kind)
    return details


def score_details(
    points,
    gt_mesh: trimesh.Trimesh,
    region: Box,
    cfg=None,
    gt_region_mesh: trimesh.Trimesh | None = None,
    progress: bool = False,
) -> ScoreDetails:
    """``score_points`` keeping the per-point distances.

    Args:
        gt_region_mesh: ``clip_mesh_to_box(gt_mesh, region)`` when the caller has it already.
        progress: show progress bars.
    """
    settings = EvaluationSettings.from_config(cfg)
    start = time.perf_counter()
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0:
        points = points.reshape(0, 3)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    finite = np.isfinite(points).all(axis=1)
    n_points, n_nonfinite = len(points), int((~finite).sum())
    in_region = finite & region.contains(points)
    scored = points[in_region]
    scored = scored[spatial_order(scored)]  # locality: 3-5x faster queries, same result

    region_mesh = clip_mesh_to_box(gt_mesh, region) if gt_region_mesh is None else gt_region_mesh
    if len(region_mesh.faces) == 0:
        raise ValueError(f"no ground-truth surface inside the evaluation region {region.as_dict()}")
    samples, face_index = sample_surface(
        region_mesh, settings.gt_sample_density_per_m2, settings.gt_sample_seed, settings.max_gt_samples
    )
    # Barycentric rounding may put a sample on a cut face one ulp outside the box.
    samples = np.clip(samples, region.lo_array, region.hi_array)
    order = spatial_order(samples)
    samples = samples[order]
    sample_normals = region_mesh.face_normals[face_index[order]]
    sample_class = surface_classes(
        samples, sample_normals, settings.ground_height_m, settings.facing_normal_z
    )
    if len(samples) == 0:
        raise ValueError(
            f"the ground truth inside {region.as_dict()} ({region_mesh.area:.3g} m^2) gets no sample at "
            f"{settings.gt_sample_density_per_m2} samples/m^2"
        )
    exposure_start = time.perf_counter()
    exposed = (
        exposure(raycasting_scene(gt_mesh), samples, sample_normals)
        if settings.exclude_enclosed
        else np.ones(len(samples), bool)
    )
    enclosed_record = _enclosed_record(exposed, sample_class)
    enclosed_record["eval_exposure_time_s"] = time.perf_counter() - exposure_start
    if not exposed.any():
        raise ValueError(
            f"no ground-truth sample inside {region.as_dict()} can be seen from outside the model"
        )
    samples, sample_class = samples[exposed], sample_class[exposed]

    n_scored = len(scored)
    record = {
        "n_points": n_points,
        "n_points_nonfinite": n_nonfinite,
        "n_points_in_region": n_scored,
        "n_points_outside_region": n_points - n_nonfinite - n_scored,
        "fraction_outside_region": (n_points - n_nonfinite - n_scored) / (n_points - n_nonfinite)
        if n_points > n_nonfinite
        else None,
        "gt_area_m2": float(region_mesh.area),
        "n_gt_samples": len(samples),  # the scored (exposed) ones
        **enclosed_record,
        "gt_sample_density_per_m2": settings.gt_sample_density_per_m2,
        "gt_sample_seed": settings.gt_sample_seed,
        "distance_cap_m": settings.distance_cap_m,
    }
    cap = np.inf if settings.distance_cap_m is None else settings.distance_cap_m

    stage_start = time.perf_counter()
    record["eval_prepare_time_s"] = stage_start - start
    if n_scored:
        accuracy, nearest_face = SurfaceDistance(region_mesh, origin=region.center).nearest(
            scored, settings.chunk_points, progress
        )
        point_class = surface_classes(
            scored, region_mesh.face_normals[nearest_face], settings.ground_height_m, settings.facing_normal_z
        )
        record["eval_accuracy_time_s"] = time.perf_counter() - stage_start
        stage_start = time.perf_counter()
        tree = cKDTree(scored, balanced_tree=False, compact_nodes=False)
        completeness, _ = tree.query(samples, k=1, distance_upper_bound=cap, workers=-1)
        record["eval_completeness_time_s"] = time.perf_counter() - stage_start
    else:
        message = (
            f"no reconstructed point inside the evaluation region ({n_points} points, {n_nonfinite} "
            f"non-finite): accuracy, precision and Chamfer recorded as null, completeness 0"
        )
        warnings.warn(message, EmptyReconstructionWarning, stacklevel=2)
        log.warning(message)
        accuracy = np.zeros(0)
        point_class = np.zeros(0, dtype=np.int8)
        completeness = np.full(len(samples), np.inf)
        record["eval_accuracy_time_s"] = record["eval_completeness_time_s"] = None

    record.update(_accuracy_metrics(accuracy, settings.accuracy_percentiles))
    record.update(_threshold_metrics(accuracy, completeness, settings.completeness_thresholds_m))
    record.update(_class_completeness(completeness, sample_class, settings.completeness_thresholds_m))
    record.update(_class_accuracy(accuracy, point_class, settings.accuracy_percentiles))
    record.update(_chamfer_metrics(accuracy, completeness, cap))
    record["eval_time_s"] = time.perf_counter() - start
    return ScoreDetails(record, scored, accuracy, region_mesh, samples, completeness)


SURFACE_CLASSES = ("ground", "roofs", "walls", "undersides")


def _enclosed_record(exposed: np.ndarray, sample_class: np.ndarray) -> dict:
    """Counts of the samples no exterior line of sight reaches, overall and per surface class (%)."""
    record = {
        "n_gt_samples_enclosed": int(np.count_nonzero(~exposed)),
        "gt_enclosed_pct": 100.0 * np.count_nonzero(~exposed) / len(exposed),
    }
    for index, name in enumerate(SURFACE_CLASSES):
        in_class = sample_class == index
        share = 100.0 * np.count_nonzero(~exposed & in_class) / in_class.sum() if in_class.any() else None
        record[f"gt_enclosed_pct_{name}"] = share
    return record


def surface_classes(
    points: np.ndarray, normals: np.ndarray, ground_height_m: float, facing_normal_z: float
) -> np.ndarray:
    """Index into ``SURFACE_CLASSES`` of each surface point, from its height and unit normal.

    Args:
        points: (N, 3) points on the surface (m, world frame, ground at z = 0).
        normals: (N, 3) unit normals of their triangles.
        ground_height_m: an upward-facing point below this height is ground, above it roof.
        facing_normal_z: a normal with z >= this faces up, z <= -this faces down, else sideways.

    Returns:
        (N,) int8 class indices.
    """
    nz = normals[:, 2]
    classes = np.full(len(points), SURFACE_CLASSES.index("walls"), dtype=np.int8)
    up = nz >= facing_normal_z
    classes[up & (points[:, 2] < ground_height_m)] = SURFACE_CLASSES.index("ground")
    classes[up & (points[:, 2] >= ground_height_m)] = SURFACE_CLASSES.index("roofs")
    classes[nz <= -facing_normal_z] = SURFACE_CLASSES.index("undersides")
    return classes


def _class_completeness(completeness: np.ndarray, sample_class: np.ndarray, thresholds) -> dict:
    record = {}
    counts = np.bincount(sample_class, minlength=len(SURFACE_CLASSES))
    for index, name in enumerate(SURFACE_CLASSES):
        record[f"gt_share_{name}"] = 100.0 * counts[index] / len(sample_class)
        in_class = completeness[sample_class == index]
        for t in thresholds:
            covered = 100.0 * np.count_nonzero(in_class <= t) / len(in_class) if len(in_class) else None
            record[f"comp_{threshold_key(t)}_{name}"] = covered
    return record


def _class_accuracy(accuracy: np.ndarray, point_class: np.ndarray, percentiles) -> dict:
    """Accuracy per surface class of each point's nearest ground-truth face: ``acc_share_{class}``
    (% of the scored points) and ``acc{q}_{class}_m``. A plan that reconstructs more of the hard
    surfaces (undersides, recessed walls) has a higher overall percentile for that alone; per class
    the planners compare on the same kind of surface."""
    record = {}
    for index, name in enumerate(SURFACE_CLASSES):
        in_class = accuracy[point_class == index]
        record[f"acc_share_{name}"] = 100.0 * len(in_class) / len(accuracy) if len(accuracy) else None
        values = _accuracy_metrics(in_class, percentiles)
        for key in map(percentile_key, percentiles):  # acc90_m -> acc90_walls_m
            record[f"{key[:-2]}_{name}_m"] = values[key]
    return record


def _accuracy_metrics(accuracy: np.ndarray, percentiles) -> dict:
    if len(accuracy) == 0:
        return {percentile_key(q): None for q in percentiles} | {"acc_mean_m": None, "acc_max_m": None}
    values = np.percentile(accuracy, list(percentiles), method="inverted_cdf")
    record = {percentile_key(q): float(v) for q, v in zip(percentiles, values, strict=True)}
    return record | {"acc_mean_m": float(accuracy.mean()), "acc_max_m": float(accuracy.max())}


def _threshold_metrics(accuracy: np.ndarray, completeness: np.ndarray, thresholds) -> dict:
    record = {}
    for t in thresholds:
        key = threshold_key(t)
        recall = 100.0 * float(np.count_nonzero(completeness <= t)) / len(completeness)
        precision = 100.0 * float(np.count_nonzero(accuracy <= t)) / len(accuracy) if len(accuracy) else None
        record[f"comp_{key}"] = recall
        record[f"prec_{key}"] = precision
        # With recall 0 the F-score is 0 whatever the precision, so an empty cloud scores 0, not null.
        p = precision or 0.0
        record[f"fscore_{key}"] = 2.0 * p * recall / (p + recall) if p + recall > 0 else 0.0
    return record


def _chamfer_metrics(accuracy: np.ndarray, completeness: np.ndarray, cap: float) -> dict:
    beyond = float(np.count_nonzero(~(completeness < cap))) / len(completeness)
    if len(accuracy) == 0:
        return {
            "chamfer_m": None,
            "chamfer_acc_m": None,
            "chamfer_comp_m": None,
            "gt_beyond_cap_fraction": beyond,
        }
    to_gt = float(np.minimum(accuracy, cap).mean())
    to_recon = float(np.minimum(completeness, cap).mean())
    return {
        "chamfer_m": 0.5 * (to_gt + to_recon),
        "chamfer_acc_m": to_gt,
        "chamfer_comp_m": to_recon,
        "gt_beyond_cap_fraction": beyond,
    }
