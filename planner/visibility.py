"""Which sampled surface points each viewpoint sees: frustum, range, facing and occlusion.

A point p with unit normal n is visible from a viewpoint when
  * it lies in front of the camera and projects inside the image,
  * its distance to the camera centre lies in [min_distance_m, max_distance_m],
  * it faces the camera: the incidence angle between n and the direction to the camera is at
    most ``max_incidence_deg`` (and below 90 degrees),
  * the segment from p (lifted by ``ray_offset_m`` along n) to the camera centre hits no triangle
    of the proxy (Open3D ``RaycastingScene.test_occlusions``, one batch per call).

Everything is vectorised over (V, P) viewpoint-point pairs; only the pairs that pass the cheap
tests are ray cast. ``VisibilityCache`` keeps the (V, P) observations of a viewpoint set and
recomputes only the rows of viewpoints that changed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from planner.sampling import validate_proxy
from scene.camera import Intrinsics, forward_vectors, validate_viewpoint_array
from scene.enclosure import (
    ENCLOSED_BACK_FRACTION,
    ENCLOSED_DIRECTIONS,
    GRID_DIRECTIONS,
    enclosed_positions,
    raycasting_scene,
)
from scene.plan import PlanningError

# Rows per chunk of the (V, P) geometry: bounds the float temporaries to ~ 64 MB at P = 2048.
_ROW_CHUNK = 512


@dataclass(frozen=True)
class VisibilityLimits:
    """Range and incidence limits of a valid observation.

    Attributes:
        min_distance_m: closest allowed camera-to-point distance in metres.
        max_distance_m: farthest allowed camera-to-point distance in metres.
        max_incidence_deg: largest angle in degrees between the surface normal and the direction
            from the point to the camera (< 90).
    """

    min_distance_m: float
    max_distance_m: float
    max_incidence_deg: float

    def __post_init__(self) -> None:
        lo, hi, inc = float(self.min_distance_m), float(self.max_distance_m), float(self.max_incidence_deg)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
            raise PlanningError(
                f"impossible visibility range: need 0 <= min_distance_m < max_distance_m, got {lo}, {hi}"
            )
        if not (0.0 < inc < 90.0):
            raise PlanningError(f"max_incidence_deg must lie in (0, 90), got {inc}")

    @property
    def min_cos_incidence(self) -> float:
        return math.cos(math.radians(float(self.max_incidence_deg)))


@dataclass
class Observations:
    """Geometry of every viewpoint-point pair of a batch.

    Attributes:
        visible: (V, P) bool, the visibility matrix A.
        distance: (V, P) float32 camera-to-point distance in metres.
        direction: (V, P, 3) float32 unit vectors from the point to the camera centre (u_v) for
            the visible pairs; zero for the others.
        cos_incidence: (V, P) float32 dot product of the point normal with ``direction``.
        n_rays: number of occlusion rays cast for this batch.
    """

    visible: np.ndarray
    distance: np.ndarray
    direction: np.ndarray
    cos_incidence: np.ndarray
    n_rays: int = 0

    def __len__(self) -> int:
        return self.visible.shape[0]

    def take(self, rows) -> Observations:
        """The observations of the given rows (a copy)."""
        rows = np.asarray(rows, dtype=np.intp)
        return Observations(
            self.visible[rows], self.distance[rows], self.direction[rows], self.cos_incidence[rows], 0
        )

    @staticmethod
    def concatenate(parts: list[Observations], n_points: int) -> Observations:
        """Stack observations of several batches row-wise (an empty list gives 0 rows)."""
        if not parts:
            return Observations.empty(n_points)
        return Observations(
            np.concatenate([o.visible for o in parts]),
            np.concatenate([o.distance for o in parts]),
            np.concatenate([o.direction for o in parts]),
            np.concatenate([o.cos_incidence for o in parts]),
            int(sum(o.n_rays for o in parts)),
        )

    @staticmethod
    def empty(n_points: int) -> Observations:
        return Observations(
            np.zeros((0, n_points), bool),
            np.zeros((0, n_points), np.float32),
            np.zeros((0, n_points, 3), np.float32),
            np.zeros((0, n_points), np.float32),
            0,
        )


class VisibilityModel:
    """Visibility of fixed surface samples of a proxy mesh from arbitrary viewpoints.

    Args:
        proxy: triangle mesh in world metres (the occluder and the clearance reference).
        points: (P, 3) surface samples in metres.
        normals: (P, 3) unit normals of the samples.
        intrinsics: the camera.
        limits: range and incidence limits.
        ray_offset_m: occlusion rays start this far along the normal from the point, so that the
            point's own triangle never occludes it.
        image_margin_px: a point must project at least this far inside the image border.
    """

    def __init__(
        self,
        proxy: trimesh.Trimesh,
        points: np.ndarray,
        normals: np.ndarray,
        intrinsics: Intrinsics,
        limits: VisibilityLimits,
        ray_offset_m: float = 0.02,
        image_margin_px: float = 0.0,
        _scene: o3d.t.geometry.RaycastingScene | None = None,
    ) -> None:
        validate_proxy(proxy)
        points = np.asarray(points, dtype=float)
        normals = np.asarray(normals, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
            raise PlanningError(
                f"points and normals must both be (P, 3), got {points.shape}, {normals.shape}"
            )
        if not (np.isfinite(points).all() and np.isfinite(normals).all()):
            raise PlanningError("surface samples or normals contain NaN or inf")
        if float(ray_offset_m) < 0 or float(image_margin_px) < 0:
            raise PlanningError(
                f"ray_offset_m and image_margin_px must be >= 0, got {ray_offset_m}, {image_margin_px}"
            )
        if 2 * float(image_margin_px) >= min(intrinsics.width, intrinsics.height):
            raise PlanningError(f"image_margin_px={image_margin_px} leaves no image area")
        self.proxy = proxy
        self.points = points
        self.normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        self.intrinsics = intrinsics
        self.limits = limits
        self.ray_offset_m = float(ray_offset_m)
        self.image_margin_px = float(image_margin_px)
        self._scene = raycasting_scene(proxy) if _scene is None else _scene
        self._ray_origins = (self.points + self.ray_offset_m * self.normals).astype(np.float32)
        self.rays_cast = 0

    @property
    def n_points(self) -> int:
        return len(self.points)

    def with_limits(self, limits: VisibilityLimits) -> VisibilityModel:
        """A model with other limits sharing this one's samples and ray-casting scene."""
        return VisibilityModel(
            self.proxy,
            self.points,
            self.normals,
            self.intrinsics,
            limits,
            self.ray_offset_m,
            self.image_margin_px,
            _scene=self._scene,
        )

    def observe(self, viewpoints: np.ndarray) -> Observations:
        """Observations (visibility and pair geometry) of all points from (V, 5) viewpoints.

        All occlusion rays of the call go to Open3D in one batch.
        """
        vps = validate_viewpoint_array(viewpoints)
        n_vp, n_pt = len(vps), self.n_points
        visible = np.zeros((n_vp, n_pt), bool)
        distance = np.empty((n_vp, n_pt), np.float32)
        direction = np.zeros((n_vp, n_pt, 3), np.float32)
        cos_inc = np.empty((n_vp, n_pt), np.float32)
        lim = self.limits
        f = self.intrinsics.focal_px
        half_w = 0.5 * self.intrinsics.width - self.image_margin_px
        half_h = 0.5 * self.intrinsics.height - self.image_margin_px
        yaw = np.radians(vps[:, 3])
        forward = forward_vectors(vps[:, 3], vps[:, 4])
        right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
        down = np.cross(forward, right)
        positions = vps[:, :3]
        pts, nrm = self.points, self.normals
        pts_sq = np.einsum("pk,pk->p", pts, pts)
        n_dot_p = np.einsum("pk,pk->p", nrm, pts)
        min_cos = max(lim.min_cos_incidence, 1e-6)
        # Plain 2-D products (V, 3) @ (3, P) for every projection: far faster than (V, P, 3) einsums.
        for lo in range(0, n_vp, _ROW_CHUNK):
            sl = slice(lo, min(lo + _ROW_CHUNK, n_vp))
            c = positions[sl]
            dist = np.sqrt(
                np.maximum(np.einsum("vk,vk->v", c, c)[:, None] + pts_sq[None] - 2.0 * (c @ pts.T), 0.0)
            )
            safe = np.maximum(dist, 1e-12)
            cosi = (c @ nrm.T - n_dot_p[None]) / safe
            depth = forward[sl] @ pts.T - np.einsum("vk,vk->v", forward[sl], c)[:, None]
            x = right[sl] @ pts.T - np.einsum("vk,vk->v", right[sl], c)[:, None]
            y = down[sl] @ pts.T - np.einsum("vk,vk->v", down[sl], c)[:, None]
            ok = (depth > 1e-6) & (dist >= lim.min_distance_m) & (dist <= lim.max_distance_m)
            ok &= cosi >= min_cos
            ok &= (np.abs(x) * f <= half_w * depth) & (np.abs(y) * f <= half_h * depth)
            visible[sl] = ok
            distance[sl] = dist
            cos_inc[sl] = cosi
        vi, pi = np.nonzero(visible)
        n_rays = len(vi)
        if n_rays:
            occluded = self._segments_occluded(self._ray_origins[pi], positions[vi].astype(np.float32))
            visible[vi[occluded], pi[occluded]] = False
        # Unit directions only where they are used: the visible pairs (a third of the cost otherwise).
        vi, pi = np.nonzero(visible)
        direction[vi, pi] = (positions[vi] - self.points[pi]) / np.maximum(distance[vi, pi, None], 1e-12)
        return Observations(visible, distance, direction, cos_inc, n_rays)

    def sees(self, viewpoints: np.ndarray, point_index) -> np.ndarray:
        """(V,) bool: whether viewpoint i sees point ``point_index[i]`` (or one index for all).

        The same tests as ``observe`` for one pair per viewpoint (one ray each).
        """
        vps = validate_viewpoint_array(viewpoints)
        idx = np.broadcast_to(np.asarray(point_index, dtype=np.intp), (len(vps),))
        if len(vps) == 0:
            return np.zeros(0, bool)
        lim = self.limits
        yaw = np.radians(vps[:, 3])
        forward = forward_vectors(vps[:, 3], vps[:, 4])
        right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
        down = np.cross(forward, right)
        to_cam = vps[:, :3] - self.points[idx]
        dist = np.linalg.norm(to_cam, axis=1)
        cosi = np.einsum("vk,vk->v", to_cam, self.normals[idx]) / np.maximum(dist, 1e-12)
        depth = -np.einsum("vk,vk->v", to_cam, forward)
        x = -np.einsum("vk,vk->v", to_cam, right)
        y = -np.einsum("vk,vk->v", to_cam, down)
        f = self.intrinsics.focal_px
        half_w = 0.5 * self.intrinsics.width - self.image_margin_px
        half_h = 0.5 * self.intrinsics.height - self.image_margin_px
        ok = (depth > 1e-6) & (dist >= lim.min_distance_m) & (dist <= lim.max_distance_m)
        ok &= cosi >= max(lim.min_cos_incidence, 1e-6)
        ok &= (np.abs(x) * f <= half_w * depth) & (np.abs(y) * f <= half_h * depth)
        if ok.any():
            rows = np.flatnonzero(ok)
            ok[
                rows[self._segments_occluded(self._ray_origins[idx[rows]], vps[rows, :3].astype(np.float32))]
            ] = False
        return ok

    def visibility(self, viewpoints: np.ndarray) -> np.ndarray:
        """The (V, P) boolean visibility matrix of (V, 5) viewpoints."""
        return self.observe(viewpoints).visible

    def occluded(self, origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(N,) bool: whether the open segment from each origin (N, 3) to its target hits the proxy."""
        o = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
        t = np.asarray(targets, dtype=np.float32).reshape(-1, 3)
        if len(o) != len(t):
            raise ValueError(f"{len(o)} origins for {len(t)} targets")
        return self._segments_occluded(o, t) if len(o) else np.zeros(0, bool)

    def _segments_occluded(self, origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
        # Unnormalised directions make t = 1 the target, so one scalar tfar serves every segment.
        rays = np.concatenate([origins, targets - origins], axis=1).astype(np.float32)
        self.rays_cast += len(rays)
        hit = self._scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0 - 1e-4)
        return hit.numpy().astype(bool)

    def closest_points(self, positions: np.ndarray) -> np.ndarray:
        """(N, 3) closest proxy surface points in metres of positions (N, 3)."""
        q = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        if len(q) == 0:
            return np.zeros((0, 3))
        return self._scene.compute_closest_points(o3d.core.Tensor(q))["points"].numpy().astype(float)

    def enclosed(
        self, positions: np.ndarray, min_back_fraction: float = ENCLOSED_BACK_FRACTION
    ) -> np.ndarray:
        """(N,) bool: positions (N, 3) inside a closed part of the proxy (``scene.enclosure``)."""
        q = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.rays_cast += len(q) * (len(GRID_DIRECTIONS) + ENCLOSED_DIRECTIONS)
        return enclosed_positions(self._scene, q, min_back_fraction)

    def clearance(self, positions: np.ndarray) -> np.ndarray:
        """(N,) distance in metres from each position (N, 3) to the nearest proxy surface."""
        q = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        if len(q) == 0:
            return np.zeros(0)
        return self._scene.compute_distance(o3d.core.Tensor(q)).numpy().astype(float)


class VisibilityCache:
    """The observations of a viewpoint set, kept up to date row by row.

    Attributes:
        viewpoints: (V, 5) current viewpoints.
        obs: their ``Observations``; ``obs.visible`` is the (V, P) visibility matrix.
    """

    def __init__(self, model: VisibilityModel, viewpoints: np.ndarray | None = None) -> None:
        self.model = model
        vps = np.zeros((0, 5)) if viewpoints is None or len(viewpoints) == 0 else viewpoints
        self.viewpoints = validate_viewpoint_array(vps).copy()
        self.obs = (
            model.observe(self.viewpoints) if len(self.viewpoints) else Observations.empty(model.n_points)
        )

    @property
    def visibility(self) -> np.ndarray:
        return self.obs.visible

    def update(self, rows, new_viewpoints: np.ndarray) -> None:
        """Replace the viewpoints at ``rows`` and recompute only those rows."""
        rows = np.asarray(rows, dtype=np.intp).reshape(-1)
        new = validate_viewpoint_array(new_viewpoints)
        if len(new) != len(rows):
            raise ValueError(f"{len(new)} viewpoints for {len(rows)} rows")
        if len(rows) == 0:
            return
        fresh = self.model.observe(new)
        self.viewpoints[rows] = new
        self.obs.visible[rows] = fresh.visible
        self.obs.distance[rows] = fresh.distance
        self.obs.direction[rows] = fresh.direction
        self.obs.cos_incidence[rows] = fresh.cos_incidence

    def append(self, new_viewpoints: np.ndarray) -> None:
        """Append viewpoints (their rows are computed, the others kept)."""
        new = validate_viewpoint_array(new_viewpoints)
        if len(new) == 0:
            return
        fresh = self.model.observe(new)
        self.viewpoints = np.concatenate([self.viewpoints, new])
        self.obs = Observations.concatenate([self.obs, fresh], self.model.n_points)

    def remove(self, rows) -> None:
        """Drop the viewpoints at ``rows``."""
        keep = np.ones(len(self.viewpoints), bool)
        keep[np.asarray(rows, dtype=np.intp)] = False
        self.viewpoints = self.viewpoints[keep]
        self.obs = self.obs.take(np.flatnonzero(keep))
