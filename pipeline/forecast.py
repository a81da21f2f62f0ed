"""The plan's forecast: how well its views observe each surface class of a mesh, before any flight.

A view *observes a sample well* when the sample lies in its image, unoccluded by the mesh, within
``max_distance_factor`` x the survey's target distance d_t and at most ``max_incidence_deg`` off the
surface normal. ``predicted_coverage`` applies this to the proxy and every planned view (what
``plan.json`` and ``metrics.json`` record as ``predicted_well_observed_<class>_pct``);
``experiments.observations`` applies it to the ground truth and the registered views of a flown run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import trimesh

from evaluate.metrics import SURFACE_CLASSES, surface_classes
from evaluate.settings import EvaluationSettings
from planner.sampling import sample_surface
from planner.visibility import VisibilityLimits, VisibilityModel

# "Seen at all": any distance, up to the planners' facing limit (conf/planner/*: max_incidence_deg).
SEEN_MAX_INCIDENCE_DEG = 80.0


@dataclass(frozen=True)
class ObservationCriteria:
    """When views observe a ground-truth sample well enough for dense matching.

    Attributes:
        min_views: views needed (MVS fuses a point seen by about 3 agreeing views).
        max_distance_factor: farthest observation, in multiples of the target distance d_t.
        max_incidence_deg: largest angle between the surface normal and the direction to the camera.
        n_samples: ground-truth samples per run (uniform by area).
        seed: sampling seed.
    """

    min_views: int = 3
    max_distance_factor: float = 1.3
    max_incidence_deg: float = 60.0
    n_samples: int = 5000
    seed: int = 0

    def __post_init__(self) -> None:
        if self.min_views < 1:
            raise ValueError(f"min_views must be >= 1, got {self.min_views}")
        if not self.max_distance_factor > 0:
            raise ValueError(f"max_distance_factor must be > 0, got {self.max_distance_factor}")
        if not 0 < self.max_incidence_deg <= SEEN_MAX_INCIDENCE_DEG:
            raise ValueError(
                f"max_incidence_deg must be in (0, {SEEN_MAX_INCIDENCE_DEG:g}], got {self.max_incidence_deg}"
            )
        if self.n_samples < 1:
            raise ValueError(f"n_samples must be >= 1, got {self.n_samples}")


def observation_shares(
    ground_truth: trimesh.Trimesh,
    views: np.ndarray,
    intrinsics,
    target_distance_m: float,
    criteria: ObservationCriteria,
    settings: EvaluationSettings,
) -> pd.DataFrame:
    """Per surface class: samples, share observed well by ``min_views`` views, share seen by as many.

    Args:
        ground_truth: the ground truth of the evaluation region (world metres); also the occluder.
        views: (V, 5) x, y, z (m), yaw, pitch (deg) of the views that count.
        intrinsics: the survey camera.
        target_distance_m: d_t, the distance of the survey's target GSD.
        criteria: what counts as observed well.
        settings: the evaluation settings that class the samples (ground height, facing threshold).

    Returns:
        One row per class of ``SURFACE_CLASSES``: ``surface``, ``n_samples``, ``well_observed_pct``,
        ``seen_pct`` (NaN for a class without samples), ``median_views``.
    """
    samples, normals = sample_surface(ground_truth, criteria.n_samples, criteria.seed)
    classes = surface_classes(samples, normals, settings.ground_height_m, settings.facing_normal_z)
    max_distance = criteria.max_distance_factor * float(target_distance_m)
    limits = VisibilityLimits(0.0, 1e6, SEEN_MAX_INCIDENCE_DEG)
    model = VisibilityModel(ground_truth, samples, normals, intrinsics, limits, ray_offset_m=0.02)
    views = np.asarray(views, dtype=float).reshape(-1, 5)
    obs = model.observe(views)
    well = (
        obs.visible
        & (obs.distance <= max_distance)
        & (obs.cos_incidence >= np.cos(np.radians(criteria.max_incidence_deg)))
    )
    n_seen, n_well = obs.visible.sum(axis=0), well.sum(axis=0)
    rows = []
    for index, name in enumerate(SURFACE_CLASSES):
        members = classes == index
        count = int(members.sum())
        rows.append(
            {
                "surface": name,
                "n_samples": count,
                "well_observed_pct": 100.0 * np.mean(n_well[members] >= criteria.min_views)
                if count
                else np.nan,
                "seen_pct": 100.0 * np.mean(n_seen[members] >= criteria.min_views) if count else np.nan,
                "median_views": float(np.median(n_seen[members])) if count else np.nan,
            }
        )
    return pd.DataFrame(rows)


def predicted_coverage(
    proxy: trimesh.Trimesh,
    views: np.ndarray,
    intrinsics,
    target_distance_m: float,
    settings: EvaluationSettings,
    criteria: ObservationCriteria | None = None,
) -> dict[str, float]:
    """What a plan promises before it is flown: ``observation_shares`` on the proxy, every planned
    view counted as registered. Returns ``predicted_well_observed_<class>_pct`` per surface class
    (None for a class the proxy lacks: JSON has no NaN), for ``plan.json`` and ``metrics.json``."""
    shares = observation_shares(
        proxy, views, intrinsics, target_distance_m, criteria or ObservationCriteria(), settings
    )
    return {
        f"predicted_well_observed_{r.surface}_pct": None
        if np.isnan(r.well_observed_pct)
        else float(r.well_observed_pct)
        for r in shares.itertuples()
    }
