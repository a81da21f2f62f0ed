"""Smith et al.'s best-viewing-direction search: direction bins and a hemisphere grid of camera axes.

The gain of every surface sample that a trial camera position could observe is accumulated into
bins over the sphere of directions (camera -> sample; the vertices of an icosphere, 642 for
subdivision 3, as in the public code). For every camera direction of a grid over the lower
hemisphere (128 yaw x 45 pitch in the original) the gains of the bins inside that camera's frustum
are summed; the best direction is the one with the largest total gain (the most negative sum of
objective changes). The bin-in-frustum matrix is built once, so a search is one matrix product.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sparse
import trimesh
from scipy.spatial import cKDTree

from scene.camera import Intrinsics, world_from_cam_rotation

# Resolution of the direction -> bin look-up table (degrees per cell); far below the bin spacing.
_LUT_STEP_DEG = 0.5


class DirectionSearch:
    """Direction bins, their look-up table and the (grid direction x bin) frustum matrix.

    Args:
        intrinsics: the camera (its field of view decides which bins a direction sees).
        n_yaw: yaw steps over 360 degrees.
        n_pitch: pitch steps from 0 (horizontal) down to (nearly) -90 degrees.
        bin_subdivisions: icosphere subdivisions of the direction bins (3: 642 bins).
        fov_margin_deg: the field of view is narrowed by this many degrees (the public code
            narrows it by 2 degrees to absorb the binning error).
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        n_yaw: int = 128,
        n_pitch: int = 45,
        bin_subdivisions: int = 3,
        fov_margin_deg: float = 2.0,
    ) -> None:
        if int(n_yaw) < 1 or int(n_pitch) < 1:
            raise ValueError(f"smith: direction grid must have >= 1 step, got {n_yaw} x {n_pitch}")
        if not (0.0 <= float(fov_margin_deg) < intrinsics.hfov_deg):
            raise ValueError(f"smith: fov_margin_deg must lie in [0, hfov), got {fov_margin_deg}")
        self.bins = trimesh.creation.icosphere(subdivisions=int(bin_subdivisions)).vertices
        self.bins = self.bins / np.linalg.norm(self.bins, axis=1, keepdims=True)
        # Grid of camera directions as in the public code: yaw = 2 pi x / n_yaw, pitch from
        # horizontal (row 0) towards nadir in n_pitch equal steps.
        yaw = np.arange(int(n_yaw)) * 360.0 / int(n_yaw)
        pitch = -np.arange(int(n_pitch)) * 90.0 / int(n_pitch)
        grid_yaw, grid_pitch = np.meshgrid(yaw, pitch, indexing="xy")
        self.grid_yaw = grid_yaw.ravel()
        self.grid_pitch = grid_pitch.ravel()
        hfov = math.radians(intrinsics.hfov_deg - float(fov_margin_deg))
        focal = 0.5 * intrinsics.width / math.tan(hfov / 2.0)
        half_w, half_h = 0.5 * intrinsics.width, 0.5 * intrinsics.height
        world_from_cam = world_from_cam_rotation(self.grid_yaw, self.grid_pitch)  # (G, 3, 3)
        cam = np.einsum("gki,bk->gbi", world_from_cam, self.bins)  # (G, B, 3) bins in camera axes
        z = cam[..., 2]
        inside = (
            (z > 0)
            & (np.abs(cam[..., 0]) * focal <= half_w * z)
            & (np.abs(cam[..., 1]) * focal <= half_h * z)
        )
        # (G, B) sparse: a direction sees ~6 % of the bins, and dense BLAS is slow on shared cores.
        self.frustum = sparse.csr_matrix(inside.astype(np.float32))
        # Look-up table from (yaw, pitch) cells to the nearest bin.
        n_lon = int(round(360.0 / _LUT_STEP_DEG))
        n_lat = int(round(180.0 / _LUT_STEP_DEG)) + 1
        lon = np.radians(np.arange(n_lon) * _LUT_STEP_DEG - 180.0)
        lat = np.radians(np.arange(n_lat) * _LUT_STEP_DEG - 90.0)
        lon_g, lat_g = np.meshgrid(lon, lat, indexing="ij")
        dirs = np.stack([np.cos(lat_g) * np.cos(lon_g), np.cos(lat_g) * np.sin(lon_g), np.sin(lat_g)], -1)
        _, nearest = cKDTree(self.bins).query(dirs.reshape(-1, 3))
        self._lut = nearest.reshape(n_lon, n_lat).astype(np.int32)
        self._n_lon, self._n_lat = n_lon, n_lat

    @property
    def n_bins(self) -> int:
        return len(self.bins)

    def bin_of(self, directions: np.ndarray) -> np.ndarray:
        """Bin index (N,) of unit directions (N, 3)."""
        d = np.asarray(directions, dtype=float)
        lon = np.degrees(np.arctan2(d[:, 1], d[:, 0])) + 180.0
        lat = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0))) + 90.0
        i = np.rint(lon / _LUT_STEP_DEG).astype(np.int64) % self._n_lon
        j = np.clip(np.rint(lat / _LUT_STEP_DEG).astype(np.int64), 0, self._n_lat - 1)
        return self._lut[i, j]

    def best(self, bin_gains: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Best grid direction for each row of per-bin objective changes.

        Args:
            bin_gains: (N, n_bins) summed objective change per bin (negative = improvement).

        Returns:
            value (N,) the smallest frustum sum (<= 0; 0 when nothing improves), and the yaw (N,)
            and pitch (N,) in degrees of that direction.
        """
        sums = np.asarray((self.frustum @ np.asarray(bin_gains, dtype=np.float32).T).T)  # (N, G)
        k = np.argmin(sums, axis=1)
        value = np.minimum(sums[np.arange(len(k)), k].astype(float), 0.0)
        return value, self.grid_yaw[k], self.grid_pitch[k]
