"""Where the proxy is unsure, read from the exploratory flight's own reconstruction (``ours_plus``).

The proxy is a Poisson surface of the exploration's fused cloud. Where the cloud measured the
surface, the proxy follows it; where the cloud is thin, missing or disagrees (a recess the flight
saw from one side, an overhang, a courtyard), Poisson bridges the gap with a smooth guess, and a
planner that trusts the guess never targets what it hides. Per proxy sample, three signals from
the cloud (``proxy.metadata[PROXY_CLOUD_KEY]``: points and unit normals, no ground truth):

- ``gap``: distance to the nearest cloud point. The surface there is interpolated, not measured.
- ``support``: cloud points within ``radius_m``, against the median over the samples: thin evidence.
- ``normal``: angle between the proxy's normal and the mean normal of the cloud points within
  ``radius_m``. At the rim of a bridged recess the cloud turns into the recess; the proxy does not.

and, when the exploration's registered views come with the proxy and ``photo`` is set, one from its
images (``planner.ours.photo_evidence``):

- ``photo``: how little the sample's patch of proxy looks the same in the views that see it (mean
  NCC). A surface the cloud itself places centimetres off looks sure to the three above, not here.

Each signal maps linearly onto [0, 1] between its two settings; a sample's uncertainty is the
largest of them and its weight ``1 + weight * uncertainty`` (``weight`` 0: all ones).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from planner.ours.photo_evidence import PhotoSettings, PhotoViews, photo_consistency
from scene.plan import PlanningError
from scene.proxy_mesh import PROXY_CLOUD_KEY, PROXY_VIEWS_KEY


@dataclass(frozen=True)
class EvidenceSettings:
    """How cloud evidence becomes sample weights (``conf/planner/ours_plus.yaml``: ``evidence``).

    Distances in metres, angles in degrees; each ``*_lo`` .. ``*_hi`` pair is the ramp from 0 to 1.
    """

    weight: float
    radius_m: float
    gap_lo_m: float
    gap_hi_m: float
    support_lo: float  # support ratio (count / median count) at which the support signal is 1 ...
    support_hi: float  # ... and at which it is 0
    normal_lo_deg: float
    normal_hi_deg: float
    photo: PhotoSettings | None = None  # None: no image evidence

    @classmethod
    def from_config(cls, node: Mapping) -> EvidenceSettings:
        photo = node.get("photo")
        photo = PhotoSettings.from_config(photo) if photo and photo.get("enabled", True) else None
        s = cls(**{k: float(node[k]) for k in cls.__dataclass_fields__ if k != "photo"}, photo=photo)
        if s.weight < 0:
            raise PlanningError(f"planner ours_plus: evidence.weight must be >= 0, got {s.weight}")
        if s.radius_m <= 0:
            raise PlanningError(f"planner ours_plus: evidence.radius_m must be > 0, got {s.radius_m}")
        for lo, hi in (
            ("gap_lo_m", "gap_hi_m"),
            ("support_lo", "support_hi"),
            ("normal_lo_deg", "normal_hi_deg"),
        ):
            if not getattr(s, lo) < getattr(s, hi):
                raise PlanningError(
                    f"planner ours_plus: evidence.{lo} must be below evidence.{hi}, "
                    f"got {getattr(s, lo)} and {getattr(s, hi)}"
                )
        return s


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def evidence_signals(
    points: np.ndarray,
    normals: np.ndarray,
    cloud_points: np.ndarray,
    cloud_normals: np.ndarray,
    s: EvidenceSettings,
    photo: Mapping[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """The cloud's three signals (each (P,), in [0, 1]) and their raw values for the samples.

    Args:
        points, normals: (P, 3) proxy samples and unit normals (world metres).
        cloud_points, cloud_normals: (N, 3) the exploration's fused cloud and its unit normals.
        photo: ``planner.ours.photo_evidence.photo_consistency``'s result for the same samples, if any.

    Returns:
        ``gap``, ``support``, ``normal`` (signals), ``gap_m``, ``support_ratio``, ``normal_deg``
        (raw values), with ``photo`` and ``photo_ncc`` when ``photo`` is given, and ``uncertainty``
        (the largest signal).
    """
    cloud = _cloud_signals(points, normals, cloud_points, cloud_normals, s)
    if photo is not None:
        cloud |= {"photo": np.asarray(photo["signal"], float), "photo_ncc": np.asarray(photo["ncc"], float)}
        cloud["uncertainty"] = np.maximum(cloud["uncertainty"], cloud["photo"])
    return cloud


def proxy_evidence(
    proxy: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, s: EvidenceSettings
) -> dict[str, np.ndarray] | None:
    """``evidence_signals`` for samples of ``proxy`` from what it carries of its exploration: the
    fused cloud (``PROXY_CLOUD_KEY``) and, with ``s.photo``, the registered views (``PROXY_VIEWS_KEY``).

    Returns:
        the signals, or None when the proxy carries no cloud (a degraded ground truth).
    """
    cloud = proxy.metadata.get(PROXY_CLOUD_KEY)
    if not cloud or len(cloud["points"]) == 0:
        return None
    where = proxy.metadata.get(PROXY_VIEWS_KEY)
    photo = None
    if s.photo is not None and where:
        views = PhotoViews.from_reconstruction(where["recon_dir"], where["image_dir"])
        photo = photo_consistency(points, normals, proxy, views, s.photo)
    return evidence_signals(points, normals, cloud["points"], cloud["normals"], s, photo)


def _cloud_signals(
    points: np.ndarray,
    normals: np.ndarray,
    cloud_points: np.ndarray,
    cloud_normals: np.ndarray,
    s: EvidenceSettings,
) -> dict[str, np.ndarray]:
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    n = len(points)
    if len(cloud_points) == 0:
        one = np.ones(n)
        return {
            "gap": one,
            "support": one,
            "normal": one,
            "uncertainty": one,
            "gap_m": np.full(n, np.inf),
            "support_ratio": np.zeros(n),
            "normal_deg": np.full(n, 180.0),
        }
    tree = cKDTree(np.asarray(cloud_points, float))
    gap_m, _ = tree.query(points)
    neighbours = tree.query_ball_point(points, s.radius_m)
    count = np.fromiter((len(nb) for nb in neighbours), dtype=np.int64, count=n)
    median = max(float(np.median(count)), 1.0)
    support_ratio = count / median
    # Mean cloud normal per sample (sum over its neighbours), vectorised through one flat index.
    owner = np.repeat(np.arange(n), count)
    flat = np.fromiter((i for nb in neighbours for i in nb), dtype=np.int64, count=int(count.sum()))
    mean = np.zeros((n, 3))
    np.add.at(mean, owner, np.asarray(cloud_normals, float)[flat])
    length = np.linalg.norm(mean, axis=1)
    cos = np.einsum("ij,ij->i", mean, normals) / np.maximum(length, 1e-12)
    normal_deg = np.where(length > 1e-9, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 180.0)
    gap = _ramp(gap_m, s.gap_lo_m, s.gap_hi_m)
    support = 1.0 - _ramp(support_ratio, s.support_lo, s.support_hi)
    normal = _ramp(normal_deg, s.normal_lo_deg, s.normal_hi_deg)
    return {
        "gap": gap,
        "support": support,
        "normal": normal,
        "uncertainty": np.maximum.reduce([gap, support, normal]),
        "gap_m": gap_m,
        "support_ratio": support_ratio,
        "normal_deg": normal_deg,
    }


def sample_weights(uncertainty: np.ndarray, s: EvidenceSettings) -> np.ndarray:
    """``1 + weight * uncertainty`` (P,): an unsure sample counts up to ``1 + weight`` times."""
    return 1.0 + s.weight * np.asarray(uncertainty, float)
