"""A plan made flyable: checked against the drone, placed on Earth, cut into one-battery flights.

Every exporter (``mission.qgc``, ``mission.litchi``, ``mission.wpml``) writes a ``Mission``; none
of them converts frames or checks limits on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drone.model import DroneSettings, Flight, default_takeoff, split_flights
from mission.geo import MissionError, SurveyOrigin
from scene.camera import VIEWPOINT_COLUMNS


@dataclass(frozen=True)
class Mission:
    """Waypoints in flight order, one photo each.

    Attributes:
        viewpoints: (V, 5) local ``x, y, z, yaw_deg, pitch_deg`` (metres, degrees; ``scene.camera``).
        latitude_deg, longitude_deg: (V,) WGS84 position of each waypoint.
        height_m: (V,) height above the take-off point (m; ellipsoidal height difference, so it
            includes the Earth's curvature: +8 cm at 1 km from take-off).
        heading_deg: (V,) aircraft heading, clockwise from north, in [0, 360).
        gimbal_pitch_deg: (V,) gimbal pitch (0 horizontal, -90 nadir).
        takeoff: (3,) take-off point in the local frame (m); ``takeoff_geodetic`` its latitude,
            longitude (deg) and height (m, in the origin's height reference).
        flights: one-battery flights in order (``Flight.start`` .. ``stop - 1``).
        origin, drone: what it was built with.
    """

    viewpoints: np.ndarray
    latitude_deg: np.ndarray
    longitude_deg: np.ndarray
    height_m: np.ndarray
    heading_deg: np.ndarray
    gimbal_pitch_deg: np.ndarray
    takeoff: np.ndarray
    takeoff_geodetic: tuple[float, float, float]
    flights: list[Flight]
    origin: SurveyOrigin
    drone: DroneSettings

    @property
    def flight_time_s(self) -> float:
        """Total flight time of all flights (s), battery swaps excluded."""
        return float(sum(f.time_s for f in self.flights))


def check_flyable(viewpoints, drone: DroneSettings, takeoff_z: float = 0.0) -> np.ndarray:
    """Return ``viewpoints`` as (V, 5) floats, or raise MissionError naming the first waypoint a
    drone cannot fly: a non-finite value, a gimbal pitch outside the range, a height below the
    minimum or above the ceiling (heights relative to ``takeoff_z``, m)."""
    arr = np.asarray(viewpoints, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 5 or len(arr) == 0:
        raise MissionError(f"a mission needs (V >= 1, 5) viewpoints {VIEWPOINT_COLUMNS}, got {arr.shape}")
    rules = [
        (~np.isfinite(arr).all(axis=1), lambda i: f"a non-finite value {arr[i].tolist()}"),
        (
            arr[:, 4] < drone.gimbal_pitch_min_deg - 1e-9,
            lambda i: f"gimbal pitch {arr[i, 4]:.2f} deg below the gimbal's {drone.gimbal_pitch_min_deg} deg",
        ),
        (
            arr[:, 4] > drone.gimbal_pitch_max_deg + 1e-9,
            lambda i: f"gimbal pitch {arr[i, 4]:.2f} deg above the gimbal's {drone.gimbal_pitch_max_deg} deg",
        ),
        (
            arr[:, 2] - takeoff_z < drone.min_height_m - 1e-9,
            lambda i: (
                f"height {arr[i, 2] - takeoff_z:.2f} m below drone.min_height_m = {drone.min_height_m} m"
            ),
        ),
        (
            arr[:, 2] - takeoff_z > drone.ceiling_m + 1e-9,
            lambda i: f"height {arr[i, 2] - takeoff_z:.2f} m above drone.ceiling_m = {drone.ceiling_m} m",
        ),
    ]
    with np.errstate(invalid="ignore"):
        for bad, message in rules:
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise MissionError(f"waypoint {i}: {message(i)}")
    return arr


def build_mission(
    viewpoints, origin: SurveyOrigin, drone: DroneSettings, max_waypoints: int | None = None
) -> Mission:
    """Check, geo-reference and split a plan's viewpoints (V, 5) into a ``Mission``.

    Args:
        max_waypoints: waypoints per mission file (default ``drone.max_waypoints_per_file``; an
            exporter whose app accepts fewer passes its own cap).
    """
    arr = np.asarray(viewpoints, dtype=float)
    if arr.ndim == 2 and arr.shape[1] == 5 and len(arr) and np.isfinite(arr[0]).all():
        takeoff = default_takeoff(arr, drone)
    else:
        takeoff = np.zeros(3)
    arr = check_flyable(arr, drone, takeoff_z=float(takeoff[2]))
    lat, lon, h = origin.geodetic_from_local(arr[:, :3])
    t_lat, t_lon, t_h = origin.geodetic_from_local(takeoff[None])
    return Mission(
        viewpoints=arr,
        latitude_deg=lat,
        longitude_deg=lon,
        height_m=h - float(t_h[0]),  # geodetic: what barometer and GNSS read, curvature included
        heading_deg=origin.heading_from_yaw(arr[:, 3]),
        gimbal_pitch_deg=arr[:, 4].copy(),
        takeoff=takeoff,
        takeoff_geodetic=(float(t_lat[0]), float(t_lon[0]), float(t_h[0])),
        flights=split_flights(arr, takeoff, drone, max_waypoints),
        origin=origin,
        drone=drone,
    )
