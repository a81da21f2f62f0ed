"""Mission export: geodesy, flight time, and each format read back by an independent reader."""

import csv
import dataclasses
import json
import xml.etree.ElementTree as ET
import zipfile

import numpy as np
import pyproj
import pytest
from fastkml import kml

from drone.model import DroneError, leg_time_s, split_flights
from mission.__main__ import main as mission_main
from mission.export import default_settings, export_mission
from mission.geo import MissionError, SurveyOrigin
from mission.litchi import HEADER as LITCHI_HEADER
from scene.plan import Plan, write_plan

WPML = "{http://www.dji.com/wpmz/1.0.2}"
KML = "{http://www.opengis.net/kml/2.2}"
ZURICH = SurveyOrigin(47.397742, 8.545594, 488.0, "amsl", 90.0)


def drone(**changes):
    return dataclasses.replace(default_settings()[1], **changes)


def plan_views(n=12, seed=0):
    """A plan around a 40 m building: heights 8-60 m, every heading, pitches over the gimbal range."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    radius = rng.uniform(20.0, 60.0, n)
    xyz = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(8.0, 60.0, n)])
    yaw = np.degrees(angle) + 180.0 - 360.0 * (angle > np.pi)  # facing the building, (-180, 180]
    pitch = np.linspace(-90.0, 30.0, n)
    return np.column_stack([xyz, yaw, pitch])


def angle_diff(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


# --- geodesy -------------------------------------------------------------------------------------


def test_1000_m_east_and_north_matches_proj():
    # Published by PROJ's topocentric conversion (pyproj 3.7.2, WGS84): 1000 m east and 1000 m north
    # of 47.397742 N 8.545594 E, 488 m, on the tangent plane, is 47.4067350753836 N 8.5588420752857 E
    # at 488.15673 m (the plane rises above the ellipsoid away from its origin).
    lat, lon, h = ZURICH.geodetic_from_local([[1000.0, 1000.0, 0.0]])
    assert lat[0] == pytest.approx(47.4067350753836, abs=1e-10)
    assert lon[0] == pytest.approx(8.5588420752857, abs=1e-10)
    assert h[0] == pytest.approx(488.15673, abs=1e-4)
    proj = pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0=47.397742 +lon_0=8.545594 "
        "+h_0=488 +step +inv +proj=cart +ellps=WGS84 +step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    lon_p, lat_p, h_p = proj.transform(1000.0, 1000.0, 0.0)
    assert (lat[0], lon[0]) == pytest.approx((lat_p, lon_p), abs=1e-11)  # deg: 1 micrometre
    assert h[0] == pytest.approx(h_p, abs=1e-6)
    # The same point with local +x pointing north (+y then points west).
    north_up = dataclasses.replace(ZURICH, x_axis_heading_deg=0.0)
    lat_n, lon_n, _ = north_up.geodetic_from_local([[1000.0, -1000.0, 0.0]])
    assert (lat_n[0], lon_n[0]) == pytest.approx((lat[0], lon[0]), abs=1e-12)


def test_local_geodetic_round_trip_and_headings():
    origin = dataclasses.replace(ZURICH, x_axis_heading_deg=30.0)
    xyz = plan_views()[:, :3]
    back = origin.local_from_geodetic(*origin.geodetic_from_local(xyz))
    np.testing.assert_allclose(back, xyz, atol=1e-6)
    # yaw 0 looks along +x, whose heading is 30 deg; yaw 90 (+y) is 90 deg counter-clockwise of it
    np.testing.assert_allclose(origin.heading_from_yaw([0.0, 90.0, -90.0]), [30.0, 300.0, 120.0])
    np.testing.assert_allclose(origin.yaw_from_heading([30.0, 300.0, 120.0]), [0.0, 90.0, -90.0], atol=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("95,8", "latitude_deg 95.0 is outside [-90, 90]"),
        ("47,190", "longitude_deg 190.0 is outside [-180, 180]"),
        ("47", "expected LAT,LON"),
        ("47,abc", "could not convert"),
    ],
)
def test_bad_origin_is_refused(text, message):
    with pytest.raises(MissionError, match=message.replace("[", r"\[").replace("]", r"\]")):
        SurveyOrigin.parse(text)


# --- flight time ---------------------------------------------------------------------------------


def test_flight_time_of_a_square_equals_the_hand_value():
    # 20 m square at 10 m, take-off under the first corner, headings 0/90/180/270 deg, 4 photos.
    # cruise 5 m/s, 2 m/s^2: a 20 m leg = 20/5 + 5/2 = 6.5 s (x3); climb 10 m at 3 m/s = 10/3 + 3/2;
    # return: 20 m horizontal (6.5 s) and 10 m down at 2 m/s (10/2 + 2/2 = 6 s) at once: 6.5 s;
    # stops: photo 1.5 s, +90 deg at 60 deg/s = 1.5 s at the last three; take-off 10 s, landing 15 s.
    d = drone(
        cruise_speed_m_s=5.0,
        acceleration_m_s2=2.0,
        climb_rate_m_s=3.0,
        descent_rate_m_s=2.0,
        yaw_rate_deg_s=60.0,
        gimbal_rate_deg_s=45.0,
        photo_time_s=1.5,
        takeoff_s=10.0,
        landing_s=15.0,
        takeoff_xy=None,
    )
    square = np.array(
        [[0, 0, 10, 0, -45], [20, 0, 10, 90, -45], [20, 20, 10, 180, -45], [0, 20, 10, -90, -45]], float
    )
    flights = split_flights(square, np.zeros(3), d)
    hand = 10.0 + (10 / 3 + 1.5) + 3 * 6.5 + (1.5 + 3 * 3.0) + 6.5 + 15.0
    assert len(flights) == 1
    assert flights[0].time_s == pytest.approx(hand, abs=0.1)
    assert hand == pytest.approx(66.33, abs=0.01)
    # A leg too short to reach cruise speed is a triangle profile: 2 m at 2 m/s^2 = 2 sqrt(2/2) s.
    assert leg_time_s(2.0, 5.0, 2.0) == pytest.approx(2.0)


def test_a_long_plan_takes_several_batteries_each_within_its_endurance():
    d = drone(endurance_s=300.0, reserve_fraction=0.2)
    views = plan_views(60)
    flights = split_flights(views, np.array([0.0, 0.0, 0.0]), d)
    assert len(flights) >= 2
    assert [f.start for f in flights[1:]] == [f.stop for f in flights[:-1]]
    assert flights[0].start == 0 and flights[-1].stop == 60
    assert all(f.time_s <= 240.0 for f in flights)
    # one waypoint farther than a battery can reach is named
    far = np.array([[5000.0, 0.0, 20.0, 0.0, -30.0]])
    with pytest.raises(DroneError, match="waypoint 0: a flight to it and back takes"):
        split_flights(far, np.zeros(3), d)


# --- formats, read back --------------------------------------------------------------------------


def origin_30():
    return dataclasses.replace(ZURICH, x_axis_heading_deg=30.0)


def test_qgc_round_trip(tmp_path):
    views, origin = plan_views(), origin_30()
    mission, paths = export_mission(views, origin, drone(), "qgc", tmp_path / "m.plan")
    assert paths == [tmp_path / "m.plan"]
    doc = json.loads(paths[0].read_text())
    assert doc["fileType"] == "Plan" and doc["mission"]["version"] == 2
    items = doc["mission"]["items"]
    assert items[0]["command"] == 22 and items[-1]["command"] == 20
    assert [it["doJumpId"] for it in items] == list(range(1, len(items) + 1))
    nav = [k for k, it in enumerate(items) if it["command"] == 16]
    assert len(nav) == len(views)
    home_h = doc["mission"]["plannedHomePosition"][2]
    lat, lon, alt = np.array([items[k]["params"][4:7] for k in nav]).T
    xyz = origin.local_from_geodetic(lat, lon, home_h + alt)
    np.testing.assert_allclose(xyz, views[:, :3], atol=0.1)
    yaw = origin.yaw_from_heading([items[k]["params"][3] for k in nav])
    assert angle_diff(yaw, views[:, 3]).max() < 0.1
    gimbal = [items[k - 1] for k in nav]
    assert {g["command"] for g in gimbal} == {1000}
    np.testing.assert_allclose([g["params"][0] for g in gimbal], views[:, 4], atol=0.1)
    capture = [items[k + 1] for k in nav]
    assert {c["command"] for c in capture} == {2000} and {c["params"][2] for c in capture} == {1}
    # the option for older autopilots
    _, (old,) = export_mission(
        views, origin, drone(qgc_gimbal_command="mount_control"), "qgc", tmp_path / "o.plan"
    )
    mount = [it for it in json.loads(old.read_text())["mission"]["items"] if it["command"] == 205]
    np.testing.assert_allclose([m["params"][0] for m in mount], views[:, 4], atol=0.1)


def test_litchi_round_trip(tmp_path):
    views, origin = plan_views(), origin_30()
    mission, (path,) = export_mission(views, origin, drone(), "litchi", tmp_path / "m.csv")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames[:8] == [
        "latitude", "longitude", "altitude(m)", "heading(deg)", "curvesize(m)", "rotationdir", "gimbalmode",
        "gimbalpitchangle",
    ]  # fmt: skip
    assert reader.fieldnames[8:10] == ["actiontype1", "actionparam1"]
    assert reader.fieldnames[36:] == [
        "actiontype15", "actionparam15", "altitudemode", "speed(m/s)", "poi_latitude", "poi_longitude",
        "poi_altitude(m)", "poi_altitudemode", "photo_timeinterval", "photo_distinterval",
    ]  # fmt: skip
    assert reader.fieldnames == LITCHI_HEADER and len(LITCHI_HEADER) == 46
    lat, lon, alt = (np.array([float(r[k]) for r in rows]) for k in ("latitude", "longitude", "altitude(m)"))
    xyz = origin.local_from_geodetic(lat, lon, mission.takeoff_geodetic[2] + alt)
    np.testing.assert_allclose(xyz, views[:, :3], atol=0.1)
    yaw = origin.yaw_from_heading([float(r["heading(deg)"]) for r in rows])
    assert angle_diff(yaw, views[:, 3]).max() < 0.1
    np.testing.assert_allclose([float(r["gimbalpitchangle"]) for r in rows], views[:, 4], atol=0.1)
    assert {r["actiontype1"] for r in rows} == {"1"} and {r["curvesize(m)"] for r in rows} == {"0"}


def test_wpml_round_trip(tmp_path):
    views, origin = plan_views(), origin_30()
    mission, (path,) = export_mission(views, origin, drone(), "wpml", tmp_path / "m.kmz")
    with zipfile.ZipFile(path) as archive:
        assert sorted(archive.namelist()) == ["wpmz/template.kml", "wpmz/waylines.wpml"]
        waylines = ET.fromstring(archive.read("wpmz/waylines.wpml"))
        template = archive.read("wpmz/template.kml").decode()
    marks = waylines.findall(f".//{KML}Placemark")
    assert [int(m.find(f"{WPML}index").text) for m in marks] == list(range(len(views)))
    lon, lat = np.array([m.find(f"{KML}Point/{KML}coordinates").text.split(",") for m in marks], float).T
    height = np.array([float(m.find(f"{WPML}executeHeight").text) for m in marks])
    xyz = origin.local_from_geodetic(lat, lon, mission.takeoff_geodetic[2] + height)
    np.testing.assert_allclose(xyz, views[:, :3], atol=0.1)
    heading = [float(m.find(f".//{WPML}waypointHeadingAngle").text) for m in marks]
    assert angle_diff(origin.yaw_from_heading(heading), views[:, 3]).max() < 0.1
    for m, pitch in zip(marks, views[:, 4], strict=True):
        actions = [a.find(f"{WPML}actionActuatorFunc").text for a in m.findall(f".//{WPML}action")]
        assert actions == ["gimbalRotate", "takePhoto"]
        assert float(m.find(f".//{WPML}gimbalPitchRotateAngle").text) == pytest.approx(pitch, abs=0.1)
        assert m.find(f"{WPML}useStraightLine").text == "1"
        assert m.find(f".//{WPML}waypointTurnMode").text == "toPointAndStopWithDiscontinuityCurvature"
    # the template, read by a maintained KML library
    document = next(iter(kml.KML.from_string(template).features))
    folder = next(iter(document.features))
    coords = np.array([p.geometry.coords[0][:2] for p in folder.features])
    np.testing.assert_allclose(coords, np.column_stack([lon, lat]), atol=1e-9)


def test_wpml_keeps_kml_as_its_default_namespace_after_a_collada_mesh_is_read(tmp_path):
    # pycollada registers the Collada namespace as ElementTree's (global) default one; DJI's
    # controllers read waylines written with KML's default namespace and the wpml: prefix.
    import collada  # noqa: F401  (its import registers the Collada namespace)

    ET.register_namespace("", "http://www.collada.org/2005/11/COLLADASchema")
    _, (path,) = export_mission(plan_views(), origin_30(), drone(), "wpml", tmp_path / "m.kmz")
    with zipfile.ZipFile(path) as archive:
        text = archive.read("wpmz/waylines.wpml").decode()
    assert text.count("<Placemark>") == len(plan_views())
    assert "ns0:" not in text and "<wpml:index>" in text


def test_450_waypoints_export_as_3_wpml_files_of_at_most_200(tmp_path):
    views = plan_views(450, seed=1)
    d = drone(endurance_s=1e6)  # only the controller's limit splits
    mission, paths = export_mission(views, ZURICH, d, "wpml", tmp_path / "big.kmz")
    assert [p.name for p in paths] == ["big_1of3.kmz", "big_2of3.kmz", "big_3of3.kmz"]
    counts = []
    for p in paths:
        with zipfile.ZipFile(p) as archive:
            marks = ET.fromstring(archive.read("wpmz/waylines.wpml")).findall(f".//{KML}Placemark")
        indices = [int(m.find(f"{WPML}index").text) for m in marks]
        assert indices == list(range(len(marks)))
        counts.append(len(marks))
    assert sum(counts) == 450 and max(counts) <= 200
    assert not (tmp_path / "big.kmz").exists()


# --- bad input -----------------------------------------------------------------------------------


def run_dir_with(tmp_path, views):
    run_dir = tmp_path / "run"
    write_plan(Plan(np.asarray(views, float), ["detail"] * len(views), "test"), run_dir / "plan")
    return run_dir


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"pitch": 45.0}, "waypoint 3: gimbal pitch 45.00 deg above the gimbal's 30.0 deg"),
        ({"z": 1.0}, "waypoint 3: height 1.00 m below drone.min_height_m"),
        ({"z": 150.0}, "waypoint 3: height 150.00 m above drone.ceiling_m = 120.0 m"),
    ],
)
def test_unflyable_waypoint_is_named_and_nothing_is_written(tmp_path, capsys, change, message):
    views = plan_views()
    views[3, 4] = change.get("pitch", views[3, 4])
    views[3, 2] = change.get("z", views[3, 2])
    out = tmp_path / "m.plan"
    assert mission_main([str(run_dir_with(tmp_path, views)), "--format", "qgc", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err
    assert list(tmp_path.glob("m*")) == []


def test_bad_paths_and_values_give_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    out = tmp_path / "m.kmz"
    assert mission_main([str(tmp_path / "empty"), "--format", "wpml", "--out", str(out)]) == 2
    assert "empty: no plan (plan/viewpoints.csv is missing)" in capsys.readouterr().err
    run_dir = run_dir_with(tmp_path, plan_views())
    assert mission_main([str(run_dir), "--format", "wpml", "--out", str(out), "--origin", "91,8"]) == 2
    assert "latitude_deg 91.0 is outside [-90, 90]" in capsys.readouterr().err
    csv_path = run_dir / "plan" / "viewpoints.csv"
    lines = csv_path.read_text().splitlines()
    lines[2] = ",".join(lines[2].split(",")[:3] + ["nan"] + lines[2].split(",")[4:])
    csv_path.write_text("\n".join(lines) + "\n")
    assert mission_main([str(csv_path), "--format", "litchi", "--out", str(out), "--origin", "47,8"]) == 2
    err = capsys.readouterr().err
    assert "viewpoints.csv" in err and "viewpoint 1 has a non-finite value" in err
    assert mission_main([str(csv_path), "--format", "litchi", "--out", str(out)]) == 2
    assert "needs --origin" in capsys.readouterr().err
    assert not out.exists()


def test_cli_exports_a_run_directory_with_its_settings(tmp_path, capsys):
    run_dir = run_dir_with(tmp_path, plan_views())
    out = tmp_path / "m.csv"
    assert mission_main([str(run_dir), "--format", "litchi", "--out", str(out)]) == 0
    assert "12 waypoints, 1 flight(s) / batteries" in capsys.readouterr().out
    assert len(out.read_text().splitlines()) == 13
