"""Drop verified image pairs whose relative pose contradicts the flight's own priors.

A survey drone logs, with every photo, its GNSS position and its gimbal's attitude. Two views of a
facade whose bays repeat can match one bay against the next: the pair passes RANSAC (the geometry
is self-consistent), and the mapper may then register the view in the wrong bay, metres from its
GNSS fix (the cathedral's nave: archive/pre_p1/archive/planner_ours.md). Such a pair's estimated relative pose
disagrees with the one the priors give: its rotation with the logged attitudes, its translation
direction with the GNSS baseline. Dropping those pairs before mapping is the pose-prior check of
aerial SfM pipelines.

What two views cannot show: a pair whose baseline runs along the repetition (two views on one
flight line along the nave, matched one bay off) has the prior's direction and rotation, only a
different baseline length, and a pair fixes no length. Such a pair passes; pairs across flight
lines or heights that match the wrong bay do not.

With ``x_i = R_i (X - c_i)`` (``cam_from_world``), the priors give ``cam2_from_cam1``:
``R = R_2 R_1^T`` and ``t = R_2 (c_1 - c_2)``; COLMAP's estimate is up to the scale of ``t``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)

# Configurations whose cam2_from_cam1 COLMAP estimates with ``compute_relative_pose``.
POSED_CONFIGS = (
    pycolmap.TwoViewGeometryConfiguration.CALIBRATED,
    pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED,
    pycolmap.TwoViewGeometryConfiguration.PLANAR,
    pycolmap.TwoViewGeometryConfiguration.PANORAMIC,
    pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC,
)


@dataclass(frozen=True)
class PairCheckSettings:
    """``reconstruct.sfm.matching.prior_check``. Angles in degrees, distances in metres."""

    enabled: bool
    attitude_sigma_deg: float  # the logged gimbal attitude's error (simulated on the true attitude)
    max_rotation_deg: float  # largest angle between the estimated and the prior relative rotation
    max_direction_deg: float  # largest angle between the estimated and the prior baseline direction
    min_baseline_m: float  # GNSS baselines shorter than this: the direction is not checked

    @classmethod
    def from_config(cls, node: Mapping | None) -> PairCheckSettings:
        node = dict(node or {"enabled": False})
        if not node.get("enabled", False):
            return cls(False, 0.0, 180.0, 180.0, 0.0)
        s = cls(
            enabled=True,
            attitude_sigma_deg=float(node["attitude_sigma_deg"]),
            max_rotation_deg=float(node["max_rotation_deg"]),
            max_direction_deg=float(node["max_direction_deg"]),
            min_baseline_m=float(node["min_baseline_m"]),
        )
        prefix = "reconstruct.sfm.matching.prior_check"
        if s.attitude_sigma_deg < 0:
            raise ValueError(f"{prefix}.attitude_sigma_deg must be >= 0, got {s.attitude_sigma_deg}")
        for name in ("max_rotation_deg", "max_direction_deg"):
            if not 0 < getattr(s, name) <= 180:
                raise ValueError(f"{prefix}.{name} must be in (0, 180], got {getattr(s, name)}")
        if s.min_baseline_m < 0:
            raise ValueError(f"{prefix}.min_baseline_m must be >= 0, got {s.min_baseline_m}")
        return s


def logged_attitudes(rotations: np.ndarray, sigma_deg: float, seed: int) -> np.ndarray:
    """The gimbal's logged ``cam_from_world`` rotations (N, 3, 3): the true ones turned by a random
    rotation whose angle per axis has standard deviation ``sigma_deg`` (seeded)."""
    rng = np.random.default_rng([int(seed), 0xA77])
    noise = Rotation.from_rotvec(rng.normal(0.0, np.radians(sigma_deg), (len(rotations), 3)))
    return np.einsum("nij,njk->nik", noise.as_matrix(), rotations)


def _angle_deg(cos: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def prior_disagreement(
    estimated_r: np.ndarray,
    estimated_t: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    pairs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair, how far COLMAP's relative pose lies from the priors'.

    Args:
        estimated_r: (P, 3, 3) estimated ``cam2_from_cam1`` rotations.
        estimated_t: (P, 3) estimated ``cam2_from_cam1`` translations (any scale).
        rotations: (N, 3, 3) prior ``cam_from_world`` rotations; positions: (N, 3) prior centres (m).
        pairs: (P, 2) indices into ``rotations`` of image 1 and image 2.

    Returns:
        rotation error (deg), baseline direction error (deg; NaN where the estimate has no
        translation), GNSS baseline (m); each (P,).
    """
    r1, r2 = rotations[pairs[:, 0]], rotations[pairs[:, 1]]
    prior_r = np.einsum("pij,pkj->pik", r2, r1)
    rot_cos = (np.einsum("pij,pij->p", estimated_r, prior_r) - 1.0) / 2.0  # trace(R_est^T R_prior)
    baseline = positions[pairs[:, 0]] - positions[pairs[:, 1]]
    baseline_m = np.linalg.norm(baseline, axis=1)
    prior_t = np.einsum("pij,pj->pi", r2, baseline)
    est_norm = np.linalg.norm(estimated_t, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        dir_cos = np.einsum("pi,pi->p", estimated_t, prior_t) / (est_norm * baseline_m)
    direction = np.where(est_norm > 1e-9, _angle_deg(dir_cos), np.nan)
    return _angle_deg(rot_cos), direction, baseline_m


def reject_pairs_against_priors(
    database_path: Path,
    names: tuple[str, ...],
    rotations: np.ndarray,
    positions: np.ndarray,
    settings: PairCheckSettings,
) -> dict[str, int]:
    """Delete from the database's verified pairs those whose relative pose contradicts the priors.

    A pair is dropped when its rotation differs from the prior one by more than
    ``max_rotation_deg``, or, for a GNSS baseline of at least ``min_baseline_m``, its translation
    direction by more than ``max_direction_deg``. Its raw matches stay; the mapper no longer sees it.

    Args:
        names: image names, in the order of ``rotations`` (logged attitudes) and ``positions``
            (GNSS fixes, metres).

    Returns:
        ``n_pairs_checked``, ``n_pairs_rejected``, ``n_pairs_unposed`` (verified without a relative
        pose: not checked).
    """
    index = {name: i for i, name in enumerate(names)}
    with pycolmap.Database.open(database_path) as db:
        images = {image.image_id: image for image in db.read_all_images() if image.name in index}
        row_of = {image_id: index[image.name] for image_id, image in images.items()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        keypoints: dict[int, np.ndarray] = {}

        def points(image_id: int) -> np.ndarray:
            if image_id not in keypoints:
                keypoints[image_id] = np.asarray(db.read_keypoints(image_id)[:, :2], float)
            return keypoints[image_id]

        pair_ids, geometries = db.read_two_view_geometries()
        ids, est_r, est_t, unposed = [], [], [], 0
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            image_ids = pycolmap.pair_id_to_image_pair(pair_id)
            if len(geometry.inlier_matches) == 0 or not all(i in row_of for i in image_ids):
                continue
            if geometry.config in POSED_CONFIGS and geometry.cam2_from_cam1 is None:
                # Verified without ``compute_relative_pose``: decompose its E / F / H now.
                a, b = (images[i] for i in image_ids)
                pycolmap.estimate_two_view_geometry_pose(
                    cameras[a.camera_id],
                    points(a.image_id),
                    cameras[b.camera_id],
                    points(b.image_id),
                    geometry,
                )
            if geometry.config not in POSED_CONFIGS or geometry.cam2_from_cam1 is None:
                unposed += 1
                continue
            ids.append(image_ids)
            est_r.append(geometry.cam2_from_cam1.rotation.matrix())
            est_t.append(np.asarray(geometry.cam2_from_cam1.translation, float))
        if not ids:
            return {"n_pairs_checked": 0, "n_pairs_rejected": 0, "n_pairs_unposed": unposed}
        pairs = np.array([(row_of[a], row_of[b]) for a, b in ids])
        rot_err, dir_err, baseline_m = prior_disagreement(
            np.array(est_r), np.array(est_t), rotations, positions, pairs
        )
        checked_direction = (baseline_m >= settings.min_baseline_m) & np.isfinite(dir_err)
        reject = (rot_err > settings.max_rotation_deg) | (
            checked_direction & (dir_err > settings.max_direction_deg)
        )
        for k in np.flatnonzero(reject):
            db.delete_two_view_geometry(*ids[k])
    log.info(
        "prior check: %d of %d verified pairs contradict the GNSS and attitude priors and were dropped "
        "(rotation > %.0f deg: %d; direction > %.0f deg: %d)",
        int(reject.sum()),
        len(ids),
        settings.max_rotation_deg,
        int((rot_err > settings.max_rotation_deg).sum()),
        settings.max_direction_deg,
        int((checked_direction & (dir_err > settings.max_direction_deg)).sum()),
    )
    return {"n_pairs_checked": len(ids), "n_pairs_rejected": int(reject.sum()), "n_pairs_unposed": unposed}
