"""Flight limits and candidate viewpoint groups around one surface point (paper Sec. III-C).

For a selected point p with normal n, approximately frontal directions are sampled around n (n
itself and a ring at ``frontal_jitter_deg``), and side directions at ``side_angle_deg`` around each
frontal one. A candidate sits at ``distance`` from p along its direction and is aimed at p; its
pitch is clipped to the gimbal range. Candidates that break the altitude or clearance limits or do
not see p are dropped. The group is the valid frontal candidate closest to n, then side candidates
chosen greedily to be angularly spread apart (each maximises its smallest angle to the views
already chosen). A point whose candidates are all invalid at ``distance`` (a confined face: a
courtyard wall, a buttress bay) gets fallbacks in order: the axis tilted up by each of
``fallback_tilt_deg`` (looking down onto the face over what blocks it), then each of
``fallback_distance_factors`` x ``distance`` with and without the tilt. No valid candidate after
them: no group (the caller excludes the point).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from planner.visibility import VisibilityModel
from scene.camera import aim_at, validate_viewpoint_array
from scene.plan import PlanningError


@dataclass(frozen=True)
class FlightLimits:
    """Limits every viewpoint must respect.

    Attributes:
        pitch_min_deg, pitch_max_deg: gimbal pitch range in degrees (-90 is nadir).
        min_altitude_m: lowest allowed camera height (z) in metres.
        min_clearance_m: smallest allowed distance in metres from the camera to the proxy.
        reject_enclosed: a camera inside a closed part of the proxy (``VisibilityModel.enclosed``)
            violates the limits by ``min_clearance_m`` + 1 m.
    """

    pitch_min_deg: float = -90.0
    pitch_max_deg: float = 30.0
    min_altitude_m: float = 2.0
    min_clearance_m: float = 3.0
    reject_enclosed: bool = True

    def __post_init__(self) -> None:
        lo, hi = float(self.pitch_min_deg), float(self.pitch_max_deg)
        if not (-90.0 <= lo <= hi <= 90.0):
            raise PlanningError(
                f"impossible gimbal limits: need -90 <= pitch_min_deg <= pitch_max_deg <= 90, got {lo}, {hi}"
            )
        if not math.isfinite(float(self.min_altitude_m)):
            raise PlanningError(f"min_altitude_m must be finite, got {self.min_altitude_m}")
        if not float(self.min_clearance_m) >= 0.0:
            raise PlanningError(f"min_clearance_m must be >= 0, got {self.min_clearance_m}")

    def violations(self, viewpoints: np.ndarray, model: VisibilityModel) -> np.ndarray:
        """(V,) total violation (>= 0; 0 = feasible) in metres and degrees of (V, 5) viewpoints."""
        vps = validate_viewpoint_array(viewpoints)
        v = np.maximum(self.pitch_min_deg - vps[:, 4], 0.0) + np.maximum(vps[:, 4] - self.pitch_max_deg, 0.0)
        v += np.maximum(self.min_altitude_m - vps[:, 2], 0.0)
        v += np.maximum(self.min_clearance_m - model.clearance(vps[:, :3]), 0.0)
        if self.reject_enclosed:
            v += np.where(model.enclosed(vps[:, :3]), self.min_clearance_m + 1.0, 0.0)
        return v

    def feasible(self, viewpoints: np.ndarray, model: VisibilityModel, tol: float = 1e-6) -> np.ndarray:
        """(V,) bool: the viewpoints that respect every limit."""
        return self.violations(viewpoints, model) <= tol


def _orthonormal_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def cone_directions(axis: np.ndarray, angle_deg: float, n: int, phase_deg: float = 0.0) -> np.ndarray:
    """``n`` unit directions (n, 3) at ``angle_deg`` from ``axis``, evenly spread in azimuth."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    e1, e2 = _orthonormal_basis(axis)
    az = np.radians(phase_deg + 360.0 * np.arange(n) / max(n, 1))
    a = math.radians(angle_deg)
    d = math.cos(a) * axis + math.sin(a) * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def candidate_directions(
    normal: np.ndarray, n_frontal: int, frontal_jitter_deg: float, n_side: int, side_angle_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate directions from the point (C, 3), whether each is frontal (C,), and the index of
    the frontal direction each belongs to (C,).

    Frontal: the normal and ``n_frontal - 1`` directions at ``frontal_jitter_deg`` around it.
    Side: ``n_side`` directions at ``side_angle_deg`` around every frontal direction.
    """
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    frontal = [n[None]]
    if n_frontal > 1:
        frontal.append(cone_directions(n, frontal_jitter_deg, n_frontal - 1))
    frontal = np.concatenate(frontal)
    side = [cone_directions(f, side_angle_deg, n_side, phase_deg=22.5 * i) for i, f in enumerate(frontal)]
    side = np.concatenate(side) if n_side > 0 else np.zeros((0, 3))
    dirs = np.concatenate([frontal, side])
    parent = np.r_[np.arange(len(frontal)), np.repeat(np.arange(len(frontal)), n_side)]
    return dirs, np.r_[np.ones(len(frontal), bool), np.zeros(len(side), bool)], parent


def select_spread(directions: np.ndarray, first: int, size: int, allowed=None) -> list[int]:
    """Greedy angular spread: start at ``first``, then add the ``allowed`` index whose smallest
    angle to the chosen ones is largest (ties: the smallest sum of cosines to the chosen ones, then
    the lowest index) until ``size`` are chosen or none are left."""
    chosen = [int(first)]
    d = np.asarray(directions, dtype=float)
    best_cos = d @ d[first]  # largest cosine to a chosen view = smallest angle
    sum_cos = best_cos.copy()
    available = np.ones(len(d), bool) if allowed is None else np.asarray(allowed, bool).copy()
    available[first] = False
    while len(chosen) < size and available.any():
        cand = np.flatnonzero(available)
        # largest smallest-angle first; ties (common: the first view is usually the nearest) go to
        # the candidate farthest from all chosen views on the whole, then to the lowest index
        i = int(cand[np.lexsort((cand, np.round(sum_cos[cand], 9), np.round(best_cos[cand], 9)))[0]])
        chosen.append(i)
        available[i] = False
        c = d @ d[i]
        best_cos = np.maximum(best_cos, c)
        sum_cos += c
    return chosen


@dataclass
class CandidateSettings:
    """How candidate groups are sampled (see the module docstring)."""

    distance_m: float
    group_size: int = 3
    n_frontal: int = 5
    frontal_jitter_deg: float = 10.0
    n_side: int = 8
    side_angle_deg: float = 25.0
    fallback_distance_factors: tuple[float, ...] = (0.7, 0.5)
    fallback_tilt_deg: tuple[float, ...] = (30.0,)

    def attempts(self) -> list[tuple[float, float]]:
        """(distance in metres, tilt in degrees) in the order they are tried."""
        tilts = [0.0, *map(float, self.fallback_tilt_deg)]
        factors = [1.0, *map(float, self.fallback_distance_factors)]
        return [(self.distance_m * f, t) for f in factors for t in tilts]


def tilted_up(normal: np.ndarray, tilt_deg: float) -> np.ndarray:
    """``normal`` turned towards +z by ``tilt_deg`` (unchanged when it points nearly straight up or
    down, where tilting picks no better side)."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    up = np.array([0.0, 0.0, 1.0]) - n[2] * n
    norm = np.linalg.norm(up)
    if tilt_deg == 0.0 or norm < 0.3:  # |n_z| > 0.95
        return n
    t = math.radians(tilt_deg)
    return math.cos(t) * n + math.sin(t) * up / norm


def valid_candidates(
    point_index: int, model: VisibilityModel, limits: FlightLimits, settings: CandidateSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The valid candidates around one point: viewpoints (C', 5), directions (C', 3), frontal (C',)
    and parent frontal index (C',), from the first of ``settings.attempts()`` that has any."""
    p = model.points[point_index]
    n = model.normals[point_index]
    for distance, tilt in settings.attempts():
        dirs, frontal, parent = candidate_directions(
            tilted_up(n, tilt),
            settings.n_frontal,
            settings.frontal_jitter_deg,
            settings.n_side,
            settings.side_angle_deg,
        )
        vps = aim_at(p[None] + distance * dirs, p, limits.pitch_min_deg, limits.pitch_max_deg)
        ok = limits.feasible(vps, model)
        if ok.any():
            rows = np.flatnonzero(ok)
            ok[rows] = model.sees(vps[rows], point_index)
        if ok.any():
            return vps[ok], dirs[ok], frontal[ok], parent[ok]
    return vps[ok], dirs[ok], frontal[ok], parent[ok]


def detail_group(
    point_index: int, model: VisibilityModel, limits: FlightLimits, settings: CandidateSettings
) -> np.ndarray | None:
    """A candidate group (g, 5) for one point: the most frontal valid view, then angularly spread
    side views; None when no candidate is valid."""
    vps, dirs, frontal, parent = valid_candidates(point_index, model, limits, settings)
    if len(vps) == 0:
        return None
    alignment = dirs @ model.normals[point_index]
    # the most frontal valid candidate (a side one when every frontal candidate is invalid)
    pool = np.flatnonzero(frontal) if frontal.any() else np.arange(len(vps))
    first = int(pool[np.argmax(alignment[pool])])
    return vps[select_spread(dirs, first, settings.group_size, allowed=side_pool(frontal, parent, first))]


def side_pool(frontal: np.ndarray, parent: np.ndarray, first: int) -> np.ndarray:
    """Side candidates to pick from: those around the chosen first view's frontal direction, or
    every side candidate when none of those is valid, or every candidate when no side one is."""
    own = ~frontal & (parent == parent[first])
    if own.sum() > 0:
        return own
    return ~frontal if (~frontal).any() else np.ones(len(frontal), bool)
