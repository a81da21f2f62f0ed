"""The drone's limits and how long a plan takes to fly, split into flights of one battery each.

Model (every constant is a setting of ``conf/drone/default.yaml``):

- a flight: take-off (``takeoff_s``), a leg to its first waypoint, the waypoints in order, a leg
  back to the take-off point, landing (``landing_s``);
- a leg: straight, from standstill to standstill; horizontal and vertical motion run at once, each
  accelerating at ``acceleration_m_s2`` up to its speed limit (``cruise_speed_m_s``; ``climb_rate_m_s``
  or ``descent_rate_m_s``), cruising and decelerating (a triangle profile when too short to reach the
  limit); the slower axis sets the leg's time;
- a waypoint: the aircraft yaws (``yaw_rate_deg_s``) and the gimbal pitches (``gimbal_rate_deg_s``)
  at the same time from the previous waypoint's attitude (the first waypoint starts from its own),
  then one photo (``photo_time_s``);
- flights: waypoints are taken in order into one flight while it still fits in a battery
  (``endurance_s`` x (1 - ``reserve_fraction``), the return included) and in one mission file
  (``max_waypoints_per_file``); one battery per flight.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

# The drone every run and export takes unless its config says otherwise.
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "conf" / "drone" / "default.yaml"


class DroneError(ValueError):
    """A drone setting out of range, or a plan the drone cannot fly (one line naming it)."""


@dataclass(frozen=True)
class DroneSettings:
    """What the drone can fly and how fast; see ``conf/drone/default.yaml`` for each value's choice.

    Angles in degrees, distances in metres, times in seconds, speeds in m/s, rates in deg/s.
    """

    gimbal_pitch_min_deg: float
    gimbal_pitch_max_deg: float
    min_height_m: float
    min_clearance_m: float
    ceiling_m: float
    cruise_speed_m_s: float
    acceleration_m_s2: float
    climb_rate_m_s: float
    descent_rate_m_s: float
    yaw_rate_deg_s: float
    gimbal_rate_deg_s: float
    photo_time_s: float
    takeoff_s: float
    landing_s: float
    endurance_s: float
    reserve_fraction: float
    max_waypoints_per_file: int
    takeoff_xy: tuple[float, float] | None
    qgc_gimbal_command: str

    def __post_init__(self) -> None:
        positive = (
            "cruise_speed_m_s",
            "acceleration_m_s2",
            "climb_rate_m_s",
            "descent_rate_m_s",
            "yaw_rate_deg_s",
            "gimbal_rate_deg_s",
            "endurance_s",
            "ceiling_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise DroneError(f"drone.{name} must be a positive number, got {value!r}")
        for name in ("photo_time_s", "takeoff_s", "landing_s", "min_height_m", "min_clearance_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise DroneError(f"drone.{name} must be a number >= 0, got {value!r}")
        if not 0.0 <= self.reserve_fraction < 1.0:
            raise DroneError(f"drone.reserve_fraction must lie in [0, 1), got {self.reserve_fraction}")
        if not self.gimbal_pitch_min_deg < self.gimbal_pitch_max_deg:
            raise DroneError(
                f"drone.gimbal_pitch_min_deg ({self.gimbal_pitch_min_deg}) must be below "
                f"gimbal_pitch_max_deg ({self.gimbal_pitch_max_deg})"
            )
        if self.min_height_m >= self.ceiling_m:
            raise DroneError(f"drone.min_height_m ({self.min_height_m}) must be below ceiling_m")
        if int(self.max_waypoints_per_file) < 1:
            raise DroneError(f"drone.max_waypoints_per_file must be >= 1, got {self.max_waypoints_per_file}")
        if self.qgc_gimbal_command not in ("gimbal_manager", "mount_control"):
            raise DroneError(
                "drone.qgc_gimbal_command must be gimbal_manager or mount_control, "
                f"got {self.qgc_gimbal_command!r}"
            )

    @classmethod
    def from_config(cls, node: Mapping) -> DroneSettings:
        """From the ``drone`` config mapping; a missing or unknown key is an error naming it."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(node) - names)
        missing = sorted(names - set(node))
        if unknown or missing:
            raise DroneError(f"drone settings: unknown {unknown}, missing {missing}")
        values = dict(node)
        if values["takeoff_xy"] is not None:
            xy = tuple(float(v) for v in values["takeoff_xy"])
            if len(xy) != 2 or not all(math.isfinite(v) for v in xy):
                raise DroneError(f"drone.takeoff_xy must be null or [x, y] in metres, got {xy}")
            values["takeoff_xy"] = xy
        values["max_waypoints_per_file"] = int(values["max_waypoints_per_file"])
        return cls(**values)

    @classmethod
    def default(cls) -> DroneSettings:
        """The drone of ``conf/drone/default.yaml``."""
        return cls.from_config(OmegaConf.to_container(OmegaConf.load(DEFAULT_CONFIG), resolve=True))

    @classmethod
    def of_run(cls, run_dir: str | Path) -> DroneSettings:
        """The drone a run directory was planned with (its ``.hydra/config.yaml``), else the default."""
        config_path = Path(run_dir) / ".hydra" / "config.yaml"
        node = OmegaConf.select(OmegaConf.load(config_path), "drone") if config_path.is_file() else None
        if node is None:
            return cls.default()
        return cls.from_config(OmegaConf.to_container(node, resolve=True))

    @property
    def usable_flight_s(self) -> float:
        """Flight time one battery gives with the reserve kept (s)."""
        return self.endurance_s * (1.0 - self.reserve_fraction)


def leg_time_s(distance_m, speed_limit_m_s: float, acceleration_m_s2: float) -> np.ndarray:
    """Time (s) to cover ``distance_m`` from rest to rest: accelerate, cruise at the limit, decelerate.

    Too short to reach the limit (distance < v^2 / a): a triangle profile, 2 sqrt(d / a).
    """
    d = np.abs(np.asarray(distance_m, dtype=float))
    v, a = float(speed_limit_m_s), float(acceleration_m_s2)
    full = d >= v * v / a
    return np.where(full, d / v + v / a, 2.0 * np.sqrt(d / a))


def legs_time_s(starts, ends, drone: DroneSettings) -> np.ndarray:
    """Time (s) of straight legs ``starts[i] -> ends[i]`` (each (N, 3), metres)."""
    delta = np.asarray(ends, dtype=float) - np.asarray(starts, dtype=float)
    horizontal = leg_time_s(
        np.linalg.norm(delta[:, :2], axis=1), drone.cruise_speed_m_s, drone.acceleration_m_s2
    )
    dz = delta[:, 2]
    vertical = np.where(
        dz >= 0,
        leg_time_s(dz, drone.climb_rate_m_s, drone.acceleration_m_s2),
        leg_time_s(dz, drone.descent_rate_m_s, drone.acceleration_m_s2),
    )
    return np.maximum(horizontal, vertical)


def stops_time_s(yaw_deg, pitch_deg, drone: DroneSettings) -> np.ndarray:
    """Time (s) at each waypoint: yaw and gimbal from the previous waypoint's attitude, then a photo.

    ``yaw_deg``, ``pitch_deg``: (..., V) in flight order along the last axis."""
    yaw = np.asarray(yaw_deg, dtype=float)
    pitch = np.asarray(pitch_deg, dtype=float)
    turn = np.abs((np.diff(yaw, prepend=yaw[..., :1]) + 180.0) % 360.0 - 180.0)
    tilt = np.abs(np.diff(pitch, prepend=pitch[..., :1]))
    return np.maximum(turn / drone.yaw_rate_deg_s, tilt / drone.gimbal_rate_deg_s) + drone.photo_time_s


@dataclass(frozen=True)
class Flight:
    """One battery's flight: waypoints ``start`` .. ``stop - 1`` of the plan, and its time (s)."""

    start: int
    stop: int
    time_s: float


def split_flights(
    viewpoints: np.ndarray, takeoff: np.ndarray, drone: DroneSettings, max_waypoints: int | None = None
) -> list[Flight]:
    """Cut the plan, in order, into flights that each fit one battery and one mission file.

    Args:
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (local metres, degrees).
        takeoff: (3,) take-off point (local metres).
        drone: the drone's settings.
        max_waypoints: waypoints per flight (default ``drone.max_waypoints_per_file``).

    Raises:
        DroneError: one waypoint alone does not fit a battery (its index is named).
    """
    cap = int(max_waypoints or drone.max_waypoints_per_file)
    positions = viewpoints[:, :3]
    home = np.asarray(takeoff, dtype=float)[None]
    homes = np.repeat(home, len(positions), axis=0)
    to_wp = legs_time_s(homes, positions, drone)  # take-off point -> waypoint i
    from_wp = legs_time_s(positions, homes, drone)  # waypoint i -> take-off point
    between = legs_time_s(positions[:-1], positions[1:], drone)  # waypoint i -> i + 1
    stops = stops_time_s(viewpoints[:, 3], viewpoints[:, 4], drone)
    fixed = drone.takeoff_s + drone.landing_s

    flights: list[Flight] = []
    start = 0
    while start < len(positions):
        # Time of the flight start..stop-1 (stop exclusive) for every feasible stop, vectorised:
        # cumulative stops and inter-waypoint legs from ``start``.
        stop_max = min(len(positions), start + cap)
        idx = np.arange(start, stop_max)
        stop_sum = np.cumsum(stops[idx])
        leg_sum = np.concatenate([[0.0], np.cumsum(between[start : stop_max - 1])])
        totals = fixed + to_wp[start] + stop_sum + leg_sum + from_wp[idx]
        over = np.flatnonzero(totals > drone.usable_flight_s)
        if len(over) and over[0] == 0:
            raise DroneError(
                f"waypoint {start}: a flight to it and back takes {totals[0]:.0f} s, more than one "
                f"battery gives ({drone.usable_flight_s:.0f} s: drone.endurance_s x (1 - reserve_fraction))"
            )
        # A flight ends before the first waypoint that no longer fits (in order, none skipped).
        last = int(over[0]) - 1 if len(over) else len(idx) - 1
        flights.append(Flight(start=start, stop=start + last + 1, time_s=float(totals[last])))
        start += last + 1
    return flights


def default_takeoff(viewpoints: np.ndarray, drone: DroneSettings) -> np.ndarray:
    """The take-off point (3,): ``drone.takeoff_xy`` on the ground, else the ground under waypoint 0."""
    xy = drone.takeoff_xy if drone.takeoff_xy is not None else viewpoints[0, :2]
    return np.array([float(xy[0]), float(xy[1]), 0.0])


def flight_summary(viewpoints: np.ndarray, drone: DroneSettings) -> dict:
    """``flight_time_s`` (s, all flights, battery swaps excluded), ``n_batteries`` (one per flight) and
    ``flight_times_s`` (s, per flight)."""
    flights = split_flights(viewpoints, default_takeoff(viewpoints, drone), drone)
    return {
        "flight_time_s": float(sum(f.time_s for f in flights)),
        "n_batteries": len(flights),
        "flight_times_s": [round(f.time_s, 1) for f in flights],
    }
