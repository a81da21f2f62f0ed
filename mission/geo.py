"""Where the local metric frame sits on Earth: local east-north-up metres <-> WGS84.

The world frame of this project (``scene.camera``) is right-handed, Z up, metres, ground at
z = 0. A survey origin places local (0, 0, 0) at a WGS84 position and turns the local +x axis to a
compass heading; the conversion itself is pymap3d's (ENU tangent plane on the WGS84 ellipsoid).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pymap3d

from drone.model import DroneError

HEIGHT_REFERENCES = ("amsl", "ellipsoid")


class MissionError(DroneError):
    """A plan or setting that no drone can fly (the message names the waypoint or the setting)."""


@dataclass(frozen=True)
class SurveyOrigin:
    """The WGS84 position of local (0, 0, 0) and the compass heading of the local +x axis.

    Attributes:
        latitude_deg, longitude_deg: WGS84 position of the local origin (deg).
        height_m: height of the local origin (m) above ``height_reference``.
        height_reference: ``amsl`` (mean sea level) or ``ellipsoid`` (WGS84). Mission altitudes are
            relative to take-off, so this only labels the home altitude; the horizontal error of
            treating an AMSL height as ellipsoidal is below 2 cm for a site 1 km across.
        x_axis_heading_deg: compass heading of local +x (deg, clockwise from north; 90: +x east).
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float = 0.0
    height_reference: str = "amsl"
    x_axis_heading_deg: float = 90.0

    def __post_init__(self) -> None:
        values = {
            "latitude_deg": self.latitude_deg,
            "longitude_deg": self.longitude_deg,
            "height_m": self.height_m,
            "x_axis_heading_deg": self.x_axis_heading_deg,
        }
        for name, value in values.items():
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise MissionError(f"survey.origin.{name} must be a finite number, got {value!r}")
        if not -90.0 <= self.latitude_deg <= 90.0:
            raise MissionError(f"survey.origin.latitude_deg {self.latitude_deg} is outside [-90, 90]")
        if not -180.0 <= self.longitude_deg <= 180.0:
            raise MissionError(f"survey.origin.longitude_deg {self.longitude_deg} is outside [-180, 180]")
        if self.height_reference not in HEIGHT_REFERENCES:
            raise MissionError(
                f"survey.origin.height_reference must be one of {HEIGHT_REFERENCES}, "
                f"got {self.height_reference!r}"
            )

    @classmethod
    def from_config(cls, node: Mapping) -> SurveyOrigin:
        """From a ``survey.origin`` mapping; a missing or unknown key is an error naming it."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(node) - known)
        if unknown:
            raise MissionError(f"survey.origin: unknown key(s) {unknown}; known: {sorted(known)}")
        for key in ("latitude_deg", "longitude_deg"):
            if key not in node:
                raise MissionError(f"survey.origin.{key} is missing")
        return cls(**{k: (float(v) if isinstance(v, int) else v) for k, v in node.items()})

    @classmethod
    def parse(cls, text: str) -> SurveyOrigin:
        """From ``"LAT,LON[,HEIGHT[,X_AXIS_HEADING]]"`` (deg, deg, m AMSL, deg), as on the command line."""
        parts = [p.strip() for p in text.split(",")]
        if not 2 <= len(parts) <= 4:
            raise MissionError(f"--origin {text!r}: expected LAT,LON[,HEIGHT[,X_AXIS_HEADING]]")
        try:
            values = [float(p) for p in parts]
        except ValueError as exc:
            raise MissionError(f"--origin {text!r}: {exc}") from exc
        names = ("latitude_deg", "longitude_deg", "height_m", "x_axis_heading_deg")
        return cls(**dict(zip(names, values, strict=False)))

    def _east_north_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors of local +x and +y in (east, north)."""
        h = math.radians(self.x_axis_heading_deg)
        x_axis = np.array([math.sin(h), math.cos(h)])
        y_axis = np.array([-math.cos(h), math.sin(h)])  # 90 deg counter-clockwise of +x
        return x_axis, y_axis

    def enu_from_local(self, xyz) -> np.ndarray:
        """East, north, up (N, 3) in metres of local points ``xyz`` (N, 3)."""
        p = np.asarray(xyz, dtype=float).reshape(-1, 3)
        x_axis, y_axis = self._east_north_axes()
        en = p[:, :1] * x_axis + p[:, 1:2] * y_axis
        return np.column_stack([en, p[:, 2]])

    def local_from_enu(self, enu) -> np.ndarray:
        """Local points (N, 3) of east, north, up ``enu`` (N, 3) in metres."""
        e = np.asarray(enu, dtype=float).reshape(-1, 3)
        x_axis, y_axis = self._east_north_axes()
        return np.column_stack([e[:, :2] @ x_axis, e[:, :2] @ y_axis, e[:, 2]])

    def geodetic_from_local(self, xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Latitude (deg), longitude (deg) and height (m, in the origin's reference) of local points."""
        enu = self.enu_from_local(xyz)
        lat, lon, h = pymap3d.enu2geodetic(
            enu[:, 0], enu[:, 1], enu[:, 2], self.latitude_deg, self.longitude_deg, self.height_m
        )
        return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float), np.asarray(h, dtype=float)

    def local_from_geodetic(self, latitude_deg, longitude_deg, height_m) -> np.ndarray:
        """Local points (N, 3) of WGS84 positions (deg, deg, m in the origin's reference)."""
        e, n, u = pymap3d.geodetic2enu(
            np.asarray(latitude_deg, dtype=float),
            np.asarray(longitude_deg, dtype=float),
            np.asarray(height_m, dtype=float),
            self.latitude_deg,
            self.longitude_deg,
            self.height_m,
        )
        return self.local_from_enu(np.column_stack([np.ravel(e), np.ravel(n), np.ravel(u)]))

    def heading_from_yaw(self, yaw_deg) -> np.ndarray:
        """Compass heading (deg in [0, 360), clockwise from north) of local yaws (deg, from +x, CCW)."""
        return np.mod(self.x_axis_heading_deg - np.asarray(yaw_deg, dtype=float), 360.0)

    def yaw_from_heading(self, heading_deg) -> np.ndarray:
        """Local yaw (deg in (-180, 180]) of compass headings (deg, clockwise from north)."""
        yaw = np.mod(self.x_axis_heading_deg - np.asarray(heading_deg, dtype=float), 360.0)
        return np.where(yaw > 180.0, yaw - 360.0, yaw)
