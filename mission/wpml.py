"""DJI WPML waypoint mission: a ``.kmz`` holding ``wpmz/template.kml`` and ``wpmz/waylines.wpml``.

Waylines (what the aircraft executes): sequential waypoint indices, heights relative to the
take-off point, stop at every waypoint with straight lines (no spline), the heading per waypoint,
and at every waypoint one action group: ``gimbalRotate`` to the waypoint's pitch, then
``takePhoto``. The template (what DJI Pilot 2 shows and edits) carries the same waypoints.
"""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
import zipfile

from drone.model import Flight
from mission.model import Mission

KML_NS = "http://www.opengis.net/kml/2.2"
WPML_NS = "http://www.dji.com/wpmz/1.0.2"
SUFFIX = ".kmz"
MAX_WAYPOINTS = None  # the drone setting (max_waypoints_per_file) applies
# DJI's enumeration of the aircraft and camera the file targets (M30 and its camera); DJI Pilot 2
# re-targets a mission to the connected aircraft on import.
DRONE_ENUM = 67
DRONE_SUB_ENUM = 0
PAYLOAD_ENUM = 52
TEMPLATE_KML = "wpmz/template.kml"
WAYLINES_WPML = "wpmz/waylines.wpml"


def _register_namespaces() -> None:
    """KML as the default namespace and ``wpml:`` for DJI's, as DJI's controllers read them.

    ElementTree's prefixes are global: a library that registers its own default namespace after
    this module was imported (pycollada does, for Collada meshes) would otherwise write every KML
    tag as ``ns0:``. So they are set again right before each file is written.
    """
    ET.register_namespace("", KML_NS)
    ET.register_namespace("wpml", WPML_NS)


def _k(tag: str) -> str:
    return f"{{{KML_NS}}}{tag}"


def _w(tag: str) -> str:
    return f"{{{WPML_NS}}}{tag}"


def _sub(parent: ET.Element, tag: str, text=None) -> ET.Element:
    element = ET.SubElement(parent, tag)
    if text is not None:
        element.text = str(text)
    return element


def _mission_config(document: ET.Element, mission: Mission, flight: Flight) -> None:
    drone = mission.drone
    config = _sub(document, _w("missionConfig"))
    _sub(config, _w("flyToWaylineMode"), "safely")
    _sub(config, _w("finishAction"), "goHome")
    _sub(config, _w("exitOnRCLost"), "executeLostAction")
    _sub(config, _w("executeRCLostAction"), "goBack")
    # climb to the first waypoint's height before flying to it (DJI: 1.2 .. 1500 m)
    climb = min(max(float(mission.height_m[flight.start]), 1.2), 1500.0)
    _sub(config, _w("takeOffSecurityHeight"), f"{climb:.2f}")
    _sub(config, _w("globalTransitionalSpeed"), f"{drone.cruise_speed_m_s:g}")
    info = _sub(config, _w("droneInfo"))
    _sub(info, _w("droneEnumValue"), DRONE_ENUM)
    _sub(info, _w("droneSubEnumValue"), DRONE_SUB_ENUM)
    payload = _sub(config, _w("payloadInfo"))
    _sub(payload, _w("payloadEnumValue"), PAYLOAD_ENUM)
    _sub(payload, _w("payloadPositionIndex"), 0)


def _heading_180(heading_deg: float) -> float:
    """WPML headings lie in [-180, 180] (deg, clockwise from north)."""
    return heading_deg - 360.0 if heading_deg > 180.0 else heading_deg


def _placemark(folder: ET.Element, mission: Mission, i: int, index: int, executable: bool) -> None:
    drone = mission.drone
    placemark = _sub(folder, _k("Placemark"))
    point = _sub(placemark, _k("Point"))
    _sub(point, _k("coordinates"), f"{mission.longitude_deg[i]:.9f},{mission.latitude_deg[i]:.9f}")
    _sub(placemark, _w("index"), index)
    height = f"{mission.height_m[i]:.3f}"
    if executable:
        _sub(placemark, _w("executeHeight"), height)
    else:
        _sub(placemark, _w("useGlobalHeight"), 0)
        _sub(placemark, _w("height"), height)
        _sub(placemark, _w("ellipsoidHeight"), height)
        _sub(placemark, _w("useGlobalSpeed"), 1)
        _sub(placemark, _w("useGlobalHeadingParam"), 0)
        _sub(placemark, _w("useGlobalTurnParam"), 0)
    _sub(placemark, _w("waypointSpeed"), f"{drone.cruise_speed_m_s:g}")
    heading = _sub(placemark, _w("waypointHeadingParam"))
    _sub(heading, _w("waypointHeadingMode"), "smoothTransition")
    _sub(heading, _w("waypointHeadingAngle"), f"{_heading_180(float(mission.heading_deg[i])):.4f}")
    _sub(heading, _w("waypointPoiPoint"), "0.000000,0.000000,0.000000")
    _sub(heading, _w("waypointHeadingAngleEnable"), 1)
    _sub(heading, _w("waypointHeadingPathMode"), "followBadArc")
    turn = _sub(placemark, _w("waypointTurnParam"))
    _sub(turn, _w("waypointTurnMode"), "toPointAndStopWithDiscontinuityCurvature")
    _sub(turn, _w("waypointTurnDampingDist"), 0)
    _sub(placemark, _w("useStraightLine"), 1)
    group = _sub(placemark, _w("actionGroup"))
    _sub(group, _w("actionGroupId"), index)
    _sub(group, _w("actionGroupStartIndex"), index)
    _sub(group, _w("actionGroupEndIndex"), index)
    _sub(group, _w("actionGroupMode"), "sequence")
    trigger = _sub(group, _w("actionTrigger"))
    _sub(trigger, _w("actionTriggerType"), "reachPoint")
    rotate = _sub(group, _w("action"))
    _sub(rotate, _w("actionId"), 0)
    _sub(rotate, _w("actionActuatorFunc"), "gimbalRotate")
    params = _sub(rotate, _w("actionActuatorFuncParam"))
    for tag, value in (
        ("gimbalHeadingYawBase", "aircraft"),
        ("gimbalRotateMode", "absoluteAngle"),
        ("gimbalPitchRotateEnable", 1),
        ("gimbalPitchRotateAngle", f"{mission.gimbal_pitch_deg[i]:.4f}"),
        ("gimbalRollRotateEnable", 0),
        ("gimbalRollRotateAngle", 0),
        ("gimbalYawRotateEnable", 0),
        ("gimbalYawRotateAngle", 0),
        ("gimbalRotateTimeEnable", 0),
        ("gimbalRotateTime", 0),
        ("payloadPositionIndex", 0),
    ):
        _sub(params, _w(tag), value)
    photo = _sub(group, _w("action"))
    _sub(photo, _w("actionId"), 1)
    _sub(photo, _w("actionActuatorFunc"), "takePhoto")
    photo_params = _sub(photo, _w("actionActuatorFuncParam"))
    _sub(photo_params, _w("fileSuffix"), f"wp{i:04d}")
    _sub(photo_params, _w("payloadPositionIndex"), 0)


def _document(mission: Mission, flight: Flight, executable: bool) -> bytes:
    drone = mission.drone
    kml = ET.Element(_k("kml"))
    document = _sub(kml, _k("Document"))
    if not executable:
        _sub(document, _w("author"), "uavplan")
    _mission_config(document, mission, flight)
    folder = _sub(document, _k("Folder"))
    if executable:
        _sub(folder, _w("templateId"), 0)
        _sub(folder, _w("executeHeightMode"), "relativeToStartPoint")
        _sub(folder, _w("waylineId"), 0)
        _sub(folder, _w("duration"), f"{flight.time_s:.1f}")
    else:
        _sub(folder, _w("templateType"), "waypoint")
        _sub(folder, _w("templateId"), 0)
        system = _sub(folder, _w("waylineCoordinateSysParam"))
        _sub(system, _w("coordinateMode"), "WGS84")
        _sub(system, _w("heightMode"), "relativeToStartPoint")
        _sub(folder, _w("globalWaypointTurnMode"), "toPointAndStopWithDiscontinuityCurvature")
        _sub(folder, _w("globalUseStraightLine"), 1)
        _sub(folder, _w("gimbalPitchMode"), "usePointSetting")
        _sub(folder, _w("globalHeight"), f"{mission.height_m[flight.start]:.3f}")
    _sub(folder, _w("autoFlightSpeed"), f"{drone.cruise_speed_m_s:g}")
    for index, i in enumerate(range(flight.start, flight.stop)):
        _placemark(folder, mission, i, index, executable)
    ET.indent(kml)
    _register_namespaces()
    return ET.tostring(kml, encoding="utf-8", xml_declaration=True)


def kmz_bytes(mission: Mission, flight: Flight) -> bytes:
    """The ``.kmz`` archive of one flight."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(TEMPLATE_KML, _document(mission, flight, executable=False))
        archive.writestr(WAYLINES_WPML, _document(mission, flight, executable=True))
    return buf.getvalue()


def render(mission: Mission) -> list[bytes]:
    """One ``.kmz`` per flight."""
    return [kmz_bytes(mission, f) for f in mission.flights]
