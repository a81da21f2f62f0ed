"""Camera model, viewpoints and every frame conversion of the project (the one place for them).

Conventions
-----------
World frame: right-handed, Z up, metres, ground at z = 0.
Viewpoint: position (x, y, z) in metres + yaw + pitch in degrees, roll 0 (gimbal-stabilised).
    yaw 0 looks along +x, counter-clockwise positive; pitch 0 is horizontal, -90 is nadir.
COLMAP / OpenCV camera frame: x right, y down, z forward.
MuJoCo / OpenGL camera frame: x right, y up, the camera looks along -z.

Rotations and transforms are named ``tgt_from_src`` the COLMAP way: ``cam_from_world`` maps world
points into the camera frame, ``x_cam = R @ x_world + t``.

Arrays of viewpoints are ``(V, 5)`` float arrays with columns ``x, y, z, yaw_deg, pitch_deg``
(``VIEWPOINT_COLUMNS``); the planners' hot paths use them instead of lists of ``Viewpoint``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VIEWPOINT_COLUMNS = ("x", "y", "z", "yaw_deg", "pitch_deg")

# OpenCV camera axes expressed in MuJoCo camera axes: x stays, y and z flip.
_MJCAM_FROM_CVCAM = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera without distortion; square pixels; principal point at the image centre.

    Attributes:
        width, height: image size in pixels.
        hfov_deg: horizontal field of view in degrees.
    """

    width: int
    height: int
    hfov_deg: float

    def __post_init__(self) -> None:
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (0.0 < float(self.hfov_deg) < 180.0):
            raise ValueError(f"hfov_deg must lie in (0, 180) degrees, got {self.hfov_deg}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (fx = fy)."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def cx(self) -> float:
        """Principal point x in pixels, COLMAP convention (pixel centres at +0.5)."""
        return 0.5 * self.width

    @property
    def cy(self) -> float:
        """Principal point y in pixels, COLMAP convention (pixel centres at +0.5)."""
        return 0.5 * self.height

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view in degrees."""
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.focal_px))

    @property
    def K(self) -> np.ndarray:
        """3x3 calibration matrix."""
        f = self.focal_px
        return np.array([[f, 0.0, self.cx], [0.0, f, self.cy], [0.0, 0.0, 1.0]])

    def gsd_m(self, distance_m: float | np.ndarray) -> float | np.ndarray:
        """Ground sampling distance in metres per pixel for a fronto-parallel surface at a distance."""
        return np.asarray(distance_m) / self.focal_px

    def distance_for_gsd(self, gsd_m: float) -> float:
        """Distance in metres at which a fronto-parallel surface is imaged at ``gsd_m`` metres/pixel."""
        return float(gsd_m) * self.focal_px

    def to_colmap(self):
        """The equivalent ``pycolmap.Camera`` (model PINHOLE, camera_id 1)."""
        import pycolmap  # imported here: the scene package must not drag pycolmap into every process

        f = self.focal_px
        return pycolmap.Camera(
            model="PINHOLE",
            width=int(self.width),
            height=int(self.height),
            params=[f, f, self.cx, self.cy],
            camera_id=1,
        )

    def as_dict(self) -> dict:
        """Plain-dict form for JSON records."""
        return {
            "width": int(self.width),
            "height": int(self.height),
            "hfov_deg": float(self.hfov_deg),
            "focal_px": self.focal_px,
            "cx": self.cx,
            "cy": self.cy,
        }


@dataclass(frozen=True)
class Viewpoint:
    """A camera pose: position in metres, yaw and pitch in degrees, roll 0."""

    x: float
    y: float
    z: float
    yaw_deg: float
    pitch_deg: float

    def __post_init__(self) -> None:
        values = (self.x, self.y, self.z, self.yaw_deg, self.pitch_deg)
        if not all(math.isfinite(float(v)) for v in values):
            raise ValueError(f"viewpoint has a non-finite value: {values}")

    @property
    def position(self) -> np.ndarray:
        """Position (3,) in metres."""
        return np.array([self.x, self.y, self.z], dtype=float)

    def as_array(self) -> np.ndarray:
        """Row ``x, y, z, yaw_deg, pitch_deg``."""
        return np.array([self.x, self.y, self.z, self.yaw_deg, self.pitch_deg], dtype=float)

    @classmethod
    def from_array(cls, row) -> Viewpoint:
        """Inverse of ``as_array``."""
        row = np.asarray(row, dtype=float).reshape(5)
        return cls(*(float(v) for v in row))


def validate_viewpoint_array(viewpoints: np.ndarray) -> np.ndarray:
    """Return ``viewpoints`` as a (V, 5) float array; raise ValueError on a wrong shape or NaN/inf."""
    arr = np.asarray(viewpoints, dtype=float)
    if arr.ndim == 1 and arr.shape[0] == 5:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 5:
        raise ValueError(f"viewpoints must have shape (V, 5) = {VIEWPOINT_COLUMNS}, got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"viewpoint {i} has a non-finite value: {arr[i].tolist()}")
    return arr


def forward_vectors(yaw_deg, pitch_deg) -> np.ndarray:
    """Unit viewing directions (..., 3) in the world frame for yaw and pitch in degrees."""
    yaw = np.radians(np.asarray(yaw_deg, dtype=float))
    pitch = np.radians(np.asarray(pitch_deg, dtype=float))
    cp = np.cos(pitch)
    return np.stack([cp * np.cos(yaw), cp * np.sin(yaw), np.sin(pitch)], axis=-1)


def yaw_pitch_from_direction(direction) -> tuple[np.ndarray, np.ndarray]:
    """Yaw and pitch in degrees (each (...,)) of viewing directions (..., 3); need not be unit."""
    d = np.asarray(direction, dtype=float)
    norm = np.linalg.norm(d, axis=-1)
    if np.any(norm == 0):
        raise ValueError("a viewing direction has zero length")
    d = d / norm[..., None]
    yaw = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    pitch = np.degrees(np.arcsin(np.clip(d[..., 2], -1.0, 1.0)))
    return yaw, pitch


def look_at(position, target) -> Viewpoint:
    """The viewpoint at ``position`` (m) aimed at ``target`` (m)."""
    position = np.asarray(position, dtype=float)
    yaw, pitch = yaw_pitch_from_direction(np.asarray(target, dtype=float) - position)
    return Viewpoint(*position.tolist(), float(yaw), float(pitch))


def aim_at(positions, targets, pitch_min_deg: float = -90.0, pitch_max_deg: float = 90.0) -> np.ndarray:
    """(N, 5) viewpoints at ``positions`` (N, 3) looking at ``targets`` ((N, 3) or one (3,)), the
    pitch clipped to the gimbal range [``pitch_min_deg``, ``pitch_max_deg``] (the one place a
    planner aims a view at a point)."""
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    yaw, pitch = yaw_pitch_from_direction(np.asarray(targets, dtype=float) - pos)
    return np.column_stack([pos, yaw, np.clip(pitch, pitch_min_deg, pitch_max_deg)])


def world_from_cam_rotation(yaw_deg, pitch_deg) -> np.ndarray:
    """Rotations (..., 3, 3) whose columns are the OpenCV camera axes (right, down, forward) in world.

    At exactly nadir or zenith (|pitch| = 90) the yaw still fixes the image's "right" axis, so
    the camera's up direction in the image is the yaw direction.
    """
    yaw = np.radians(np.asarray(yaw_deg, dtype=float))
    forward = forward_vectors(yaw_deg, pitch_deg)
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=-1)


def cam_from_world(viewpoint: Viewpoint | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP ``cam_from_world`` of one or many viewpoints as (R (...,3,3), t (...,3)).

    ``x_cam = R @ x_world + t``; ``viewpoint`` is a ``Viewpoint`` or an array (..., 5).
    """
    row = viewpoint.as_array() if isinstance(viewpoint, Viewpoint) else np.asarray(viewpoint, float)
    world_from_cam = world_from_cam_rotation(row[..., 3], row[..., 4])
    rot = np.swapaxes(world_from_cam, -1, -2)
    t = -np.einsum("...ij,...j->...i", rot, row[..., :3])
    return rot, t


def viewpoint_from_cam_from_world(rotation, translation, roll_tol_deg: float = 0.5) -> Viewpoint:
    """Inverse of ``cam_from_world`` for one pose; raise ValueError if the pose has roll.

    Args:
        rotation: (3, 3) ``cam_from_world`` rotation.
        translation: (3,) ``cam_from_world`` translation in metres.
        roll_tol_deg: largest tolerated roll in degrees (gimbal-stabilised cameras have none).
    """
    rot = np.asarray(rotation, dtype=float)
    world_from_cam = rot.T
    position = -world_from_cam @ np.asarray(translation, dtype=float)
    # The image's right axis is horizontal for a roll-free camera, so it fixes the yaw even at nadir.
    right = world_from_cam[:, 0]
    yaw = math.degrees(math.atan2(right[0], -right[1]))
    pitch = math.degrees(math.asin(float(np.clip(world_from_cam[2, 2], -1.0, 1.0))))
    expected = world_from_cam_rotation(yaw, pitch)
    # ||R1 - R2||_2 = 2 sin(angle / 2) for the angle of the rotation between them.
    residual = float(np.linalg.norm(expected - world_from_cam, 2))
    roll = 2.0 * math.degrees(math.asin(min(1.0, residual / 2.0)))
    if roll > roll_tol_deg:
        raise ValueError(f"pose has a roll of {roll:.3f} deg; viewpoints are roll-free")
    return Viewpoint(*position.tolist(), yaw, pitch)


def mujoco_camera_pose(viewpoint: Viewpoint | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo camera ``pos`` (3,) and ``quat`` (4,) (w, x, y, z) of one viewpoint in the world body."""
    row = viewpoint.as_array() if isinstance(viewpoint, Viewpoint) else np.asarray(viewpoint, float)
    world_from_mjcam = world_from_cam_rotation(row[3], row[4]) @ _MJCAM_FROM_CVCAM.T
    return row[:3].copy(), quat_from_matrix(world_from_mjcam)


def quat_from_matrix(rotation) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a 3x3 rotation matrix."""
    m = np.asarray(rotation, dtype=float)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def matrix_from_quat(quat) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (w, x, y, z); need not be unit."""
    w, x, y, z = np.asarray(quat, dtype=float) / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def project_points(points_world, viewpoints, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into every viewpoint (COLMAP pixel convention).

    Args:
        points_world: (P, 3) points in metres.
        viewpoints: (V, 5) viewpoint array (or one ``Viewpoint``).
        intrinsics: the camera.

    Returns:
        pixels (V, P, 2) in pixels (top-left corner of the image is (0, 0)), and
        depth (V, P) in metres along the optical axis (<= 0 means behind the camera).
    """
    if isinstance(viewpoints, Viewpoint):
        viewpoints = viewpoints.as_array()
    vps = validate_viewpoint_array(viewpoints)
    pts = np.asarray(points_world, dtype=float).reshape(-1, 3)
    rot, t = cam_from_world(vps)
    cam = np.einsum("vij,pj->vpi", rot, pts) + t[:, None, :]
    depth = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = cam[..., :2] / depth[..., None]
    pixels = uv * intrinsics.focal_px + np.array([intrinsics.cx, intrinsics.cy])
    return pixels, depth
