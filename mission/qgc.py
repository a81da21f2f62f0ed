"""QGroundControl ``.plan`` (JSON, fileType Plan, mission version 2) for PX4 and ArduPilot.

Per flight: take-off at the take-off point, then per waypoint a gimbal command (sent before the leg,
so the gimbal pitches while the aircraft flies), ``MAV_CMD_NAV_WAYPOINT`` with the heading and a
hold for the photo, and one ``MAV_CMD_IMAGE_START_CAPTURE``; then return to launch. Altitudes are
relative to take-off (MAV_FRAME_GLOBAL_RELATIVE_ALT). MAVLink headings: degrees clockwise from north.
"""

from __future__ import annotations

import json

from drone.model import Flight
from mission.model import Mission

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_MOUNT_CONTROL = 205
MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW = 1000
MAV_CMD_IMAGE_START_CAPTURE = 2000
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_MOUNT_MODE_MAVLINK_TARGETING = 2
MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_QUADROTOR = 2
SUFFIX = ".plan"
MAX_WAYPOINTS = None  # PX4 and ArduPilot store thousands of items: only the drone setting applies


def _item(seq: int, command: int, frame: int, params: list, altitude: float | None = None) -> dict:
    item = {
        "autoContinue": True,
        "command": command,
        "doJumpId": seq,
        "frame": frame,
        "params": params,
        "type": "SimpleItem",
    }
    if altitude is not None:
        item.update({"AMSLAltAboveTerrain": None, "Altitude": altitude, "AltitudeMode": 1})
    return item


def _gimbal(seq: int, pitch_deg: float, command: str) -> dict:
    if command == "mount_control":
        # pitch, roll, yaw (deg), reserved x3, mount mode
        params = [pitch_deg, 0.0, 0.0, 0.0, 0.0, 0.0, MAV_MOUNT_MODE_MAVLINK_TARGETING]
        return _item(seq, MAV_CMD_DO_MOUNT_CONTROL, MAV_FRAME_MISSION, params)
    # pitch (deg, up positive), yaw (deg, relative to the vehicle), pitch rate, yaw rate (None: the
    # gimbal's own), flags, reserved, gimbal device id (0: primary)
    params = [pitch_deg, 0.0, None, None, 0, 0, 0]
    return _item(seq, MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, MAV_FRAME_MISSION, params)


def plan_document(mission: Mission, flight: Flight) -> dict:
    """The ``.plan`` JSON object of one flight of ``mission``."""
    drone = mission.drone
    t_lat, t_lon, t_h = mission.takeoff_geodetic
    first = flight.start
    items = [
        _item(
            1,
            MAV_CMD_NAV_TAKEOFF,
            MAV_FRAME_GLOBAL_RELATIVE_ALT,
            [
                0.0,
                0.0,
                0.0,
                None,
                t_lat,
                t_lon,
                round(max(float(mission.height_m[first]), drone.min_height_m), 3),
            ],
            altitude=round(max(float(mission.height_m[first]), drone.min_height_m), 3),
        )
    ]
    for i in range(flight.start, flight.stop):
        items.append(
            _gimbal(len(items) + 1, round(float(mission.gimbal_pitch_deg[i]), 4), drone.qgc_gimbal_command)
        )
        height = round(float(mission.height_m[i]), 3)
        # hold time (s), acceptance radius (m; 0: the autopilot's), pass radius, heading (deg), lat, lon, alt
        nav = [drone.photo_time_s, 0.0, 0.0, round(float(mission.heading_deg[i]), 4)]
        nav += [float(mission.latitude_deg[i]), float(mission.longitude_deg[i]), height]
        items.append(
            _item(len(items) + 1, MAV_CMD_NAV_WAYPOINT, MAV_FRAME_GLOBAL_RELATIVE_ALT, nav, altitude=height)
        )
        # camera id (0: all), interval (s), total images, sequence number, reserved x3
        capture = [0, 0, 1, i + 1, None, None, None]
        items.append(_item(len(items) + 1, MAV_CMD_IMAGE_START_CAPTURE, MAV_FRAME_MISSION, capture))
    items.append(_item(len(items) + 1, MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_FRAME_MISSION, [0.0] * 7))
    home_amsl = t_h  # the origin's height reference: AMSL by default (survey.origin.height_reference)
    return {
        "fileType": "Plan",
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": drone.cruise_speed_m_s,
            "firmwareType": MAV_AUTOPILOT_PX4,
            "globalPlanAltitudeMode": 1,
            "hoverSpeed": drone.cruise_speed_m_s,
            "items": items,
            "plannedHomePosition": [t_lat, t_lon, round(home_amsl, 3)],
            "vehicleType": MAV_TYPE_QUADROTOR,
            "version": 2,
        },
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }


def render(mission: Mission) -> list[bytes]:
    """One ``.plan`` file per flight."""
    return [(json.dumps(plan_document(mission, f), indent=2) + "\n").encode() for f in mission.flights]
