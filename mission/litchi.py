"""Litchi mission CSV (Litchi Mission Hub import) for DJI aircraft.

Per waypoint: position, altitude above take-off, heading (deg clockwise from north), straight lines
with a stop (curve size 0), the gimbal pitch interpolated to the waypoint's (gimbal mode 2) and one
take-photo action. Litchi accepts 99 waypoints per mission, so longer flights split.
"""

from __future__ import annotations

import csv
import io

from mission.model import Mission

N_ACTIONS = 15
HEADER = (
    ["latitude", "longitude", "altitude(m)", "heading(deg)", "curvesize(m)", "rotationdir"]
    + ["gimbalmode", "gimbalpitchangle"]
    + [f"action{kind}{i}" for i in range(1, N_ACTIONS + 1) for kind in ("type", "param")]
    + ["altitudemode", "speed(m/s)", "poi_latitude", "poi_longitude", "poi_altitude(m)"]
    + ["poi_altitudemode", "photo_timeinterval", "photo_distinterval"]
)
ACTION_NONE = -1
ACTION_TAKE_PHOTO = 1
GIMBAL_INTERPOLATE = 2
ALTITUDE_ABOVE_TAKEOFF = 0
SUFFIX = ".csv"
MAX_WAYPOINTS = 99  # Litchi's limit per mission


def render(mission: Mission) -> list[bytes]:
    """One CSV per flight."""
    files = []
    for flight in mission.flights:
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(HEADER)
        for i in range(flight.start, flight.stop):
            actions = [ACTION_TAKE_PHOTO, 0] + [ACTION_NONE, 0] * (N_ACTIONS - 1)
            writer.writerow(
                [f"{mission.latitude_deg[i]:.9f}", f"{mission.longitude_deg[i]:.9f}"]
                + [f"{mission.height_m[i]:.3f}", f"{mission.heading_deg[i]:.3f}", 0, 0]
                + [GIMBAL_INTERPOLATE, f"{mission.gimbal_pitch_deg[i]:.3f}"]
                + actions
                + [ALTITUDE_ABOVE_TAKEOFF, f"{mission.drone.cruise_speed_m_s:g}", 0, 0, 0, 0, -1, -1]
            )
        files.append(buf.getvalue().encode())
    return files
