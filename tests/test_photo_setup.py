"""What the photos say about their own reconstruction: the GNSS class, the camera, the refinement
rule, the config precedence, the sanity gate, the height envelope, the controllers' caps, and the
refusals' fixes typed as printed (pipeline/photo_setup.py, mission/envelope.py, mission/controllers.py).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_dir

from experiments.photo_roundtrip import write_photo
from mission.controllers import CAPS, caps_for, dji_app
from mission.envelope import keep_within_heights
from pipeline.photo_setup import (
    camera_from_photos,
    gnss_class,
    model_residuals,
    photo_reconstruct_config,
    refinement_allowed,
    sanity_failures,
)
from pipeline.photos import (
    PhotoError,
    local_viewpoints,
    parse_dewarp,
    parse_origin,
    read_photo,
    read_photos,
    scaled_camera,
    takeoff_origin,
)
from scene.config import plain
from scene.plan import Plan

ROOT = Path(__file__).resolve().parents[1]
BRIGHTON = ROOT.parent / "shared" / "data" / "photos" / "brighton_beach"
RGB = (np.random.default_rng(0).random((1300, 1600, 3)) * 255).astype(np.uint8)[:48, :64]
# A DJI P4 Multispectral's XMP as DJI's "P4 Multispectral Image Processing Guide" lays it out:
# RTK fixed with its standard deviations, the factory calibration in pixels, and DewarpData
# "calibration date;fx,fy,cx,cy,k1,k2,p1,p2,k3" with cx, cy offsets from the optical centre.
DJI_RTK_XMP = {
    "RtkFlag": "50",
    "RtkStdLon": "0.01234",
    "RtkStdLat": "0.01567",
    "RtkStdHgt": "0.02589",
    "CalibratedFocalLength": "1913.333374",
    "CalibratedOpticalCenterX": "800.000000",
    "CalibratedOpticalCenterY": "650.000000",
    "DewarpData": "2019-09-26;1909.680000000000,1909.680000000000,-2.620000000000,5.860000000000,"
    "-0.394227306158,0.245627379242,0.000120000000,-0.000230000000,-0.121852202339",
}


def dji_photo(
    folder: Path,
    name: str,
    xmp: dict | None = None,
    pitch: float = -90.0,
    heading: float = 0.0,
    lat: float = 46.8426,
    lon: float = -91.9945,
    rel: float | None = 40.0,
) -> Path:
    return write_photo(folder / name, RGB, lat, lon, 198.3, rel, heading, pitch, 5.74, 64 / 6.4, xmp)


def compose_photos(*overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return compose("photos", overrides=["photos.dir=/nonexistent", *overrides])


# -- XMP: the shared flight's real headers and DJI's documented tags --------------------------------


@pytest.mark.skipif(not BRIGHTON.is_dir(), reason="the shared Phantom 3 flight is not here")
def test_the_phantom_3_headers_read_as_a_consumer_drone_with_an_exif_camera():
    record = read_photo(BRIGHTON / "DJI_0018.JPG")
    assert record.camera == "DJI FC300S"
    assert (record.width, record.height) == (4000, 2250)
    assert record.relative_altitude_m == pytest.approx(39.80)
    assert record.absolute_altitude_m == pytest.approx(198.31)
    assert record.gps_altitude_m == pytest.approx(198.309)
    assert record.pitch_deg == pytest.approx(-89.9) and record.heading_deg == pytest.approx(45.0)
    assert record.roll_deg == pytest.approx(0.0)
    assert record.latitude_deg == pytest.approx(46 + 50 / 60 + 33.3855 / 3600, abs=1e-9)
    assert record.longitude_deg == pytest.approx(-(91 + 59 / 60 + 40.4156 / 3600), abs=1e-9)
    # 20 mm (35 mm equivalent) on the 4000 x 2250 frame's diagonal: 20 / 43.27 x 4589.1 px.
    assert record.focal_px == pytest.approx(20 / math.hypot(36, 24) * math.hypot(4000, 2250), rel=1e-9)
    assert record.rtk_flag is None and record.rtk_std_m is None and record.dewarp is None
    assert record.calibrated_focal_px is None
    report = read_photos(BRIGHTON)
    assert len(report.records) == 18
    klass = gnss_class(report.records, 2.0, 0.02)
    assert klass["name"] == "consumer" and klass["sigma_m"] == 2.0
    camera = camera_from_photos(report.records)
    assert camera["model"] == "SIMPLE_RADIAL" and camera["source"] == "exif"
    assert camera["params"] == pytest.approx([record.focal_px, 2000.0, 1125.0, 0.0])
    origin = takeoff_origin(report.records)
    assert origin.height_m == pytest.approx(158.5, abs=0.05)
    allowed, why = refinement_allowed(local_viewpoints(report.records, origin))
    assert not allowed and "0 of 18 photos oblique" in why  # nadir only: the camera is held


def test_dji_rtk_and_calibration_tags_read_as_documented(tmp_path):
    record = read_photo(dji_photo(tmp_path, "rtk.JPG", DJI_RTK_XMP))
    assert record.rtk_flag == 50
    assert record.rtk_std_m == pytest.approx((0.01234, 0.01567, 0.02589))
    assert record.calibrated_focal_px == pytest.approx(1913.333374)
    assert record.calibrated_center_px == pytest.approx((800.0, 650.0))
    assert record.dewarp == pytest.approx(
        (1909.68, 1909.68, -2.62, 5.86, -0.394227306158, 0.245627379242, 0.00012, -0.00023, -0.121852202339)
    )
    klass = gnss_class([record] * 3, 2.0, 0.02)
    rms = math.sqrt((0.01234**2 + 0.01567**2 + 0.02589**2) / 3)
    assert klass["name"] == "rtk_fixed" and klass["sigma_m"] == 0.02  # RMS 1.89 cm, floored at 2 cm
    assert gnss_class([record] * 3, 2.0, 0.01)["sigma_m"] == pytest.approx(rms)
    camera = camera_from_photos([record])
    assert camera["model"] == "FULL_OPENCV" and camera["source"] == "xmp_dewarp" and not camera["refinable"]
    assert camera["params"] == pytest.approx(
        [
            1909.68,
            1909.68,
            797.38,
            655.86,
            -0.394227306158,
            0.245627379242,
            0.00012,
            -0.00023,
            -0.121852202339,
            0.0,
            0.0,
            0.0,
        ]
    )
    # The photos' own camera wins over EXIF only where asked: exif keeps the former pinhole.
    assert camera_from_photos([record], "exif")["model"] == "PINHOLE"
    # Downscaled to half for the proxy: pixels halve, coefficients stay.
    half = scaled_camera(camera, 0.5)
    assert half["params"][:4] == pytest.approx([954.84, 954.84, 398.69, 327.93])
    assert half["params"][4:] == camera["params"][4:]


def test_calibrated_focal_length_without_dewarp_data_is_a_pinhole_and_float_rtk_is_its_class(tmp_path):
    xmp = {k: v for k, v in DJI_RTK_XMP.items() if k != "DewarpData"} | {"RtkFlag": "34"}
    records = [read_photo(dji_photo(tmp_path, f"f{i}.JPG", xmp)) for i in range(3)]
    camera = camera_from_photos(records)
    assert camera["model"] == "PINHOLE" and camera["params"] == pytest.approx([1913.333374] * 2 + [800, 650])
    assert gnss_class(records, 2.0, 0.02)["name"] == "rtk_float"
    # Single-point fixes (RtkFlag 16) are a consumer receiver's.
    single = [read_photo(dji_photo(tmp_path, f"s{i}.JPG", {"RtkFlag": "16"})) for i in range(3)]
    assert gnss_class(single, 2.0, 0.02) == {
        "name": "consumer",
        "sigma_m": 2.0,
        "why": "RtkFlag 50/34 in only 0 of 3 photos: consumer grade",
    }
    with pytest.raises(PhotoError, match="photos.camera=auto"):
        camera_from_photos(single, "xmp")


def test_malformed_dewarp_data_is_ignored():
    assert parse_dewarp("2019-09-26;1,2,3") is None
    assert parse_dewarp("2019-09-26;a,b,c,d,e,f,g,h,i") is None
    assert parse_dewarp(None) is None
    assert parse_dewarp("1909.68,1909.68,0,0,0,0,0,0,0")[0] == 1909.68  # no date: still nine numbers


def test_the_refinement_rule_wants_oblique_views_from_two_headings():
    nadir = np.column_stack(
        [np.arange(10.0), np.zeros(10), np.full(10, 40.0), np.zeros(10), np.full(10, -90.0)]
    )
    assert not refinement_allowed(nadir)[0]
    one_side = nadir.copy()
    one_side[:6, 4] = -45.0
    allowed, why = refinement_allowed(one_side)
    assert not allowed and "within 0 deg" in why
    two_sides = one_side.copy()
    two_sides[:3, 3] = 180.0
    allowed, why = refinement_allowed(two_sides)
    assert allowed and "180 deg apart" in why


# -- the config's precedence ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def consumer_records(tmp_path_factory):
    folder = tmp_path_factory.mktemp("consumer")
    return [read_photo(dji_photo(folder, f"c{i}.JPG", lat=46.8426 + i * 1e-4)) for i in range(4)]


@pytest.fixture(scope="module")
def rtk_records(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rtk")
    return [read_photo(dji_photo(folder, f"r{i}.JPG", DJI_RTK_XMP, lat=46.8426 + i * 1e-4)) for i in range(4)]


def resolved(cfg, records):
    origin = takeoff_origin(records)
    return photo_reconstruct_config(
        plain(cfg.reconstruct), plain(cfg.photos), records, local_viewpoints(records, origin)
    )


def test_the_default_takes_sigma_from_the_photos_gnss_class(consumer_records, rtk_records):
    cfg = compose_photos()
    assert cfg.reconstruct.gnss.sigma_m == "auto"
    recon, used = resolved(cfg, consumer_records)
    assert recon["gnss"]["sigma_m"] == 2.0 and used["gnss"]["name"] == "consumer"
    assert used["gnss"]["source"].startswith("the photos")
    recon, used = resolved(cfg, rtk_records)
    assert recon["gnss"]["sigma_m"] == pytest.approx(0.02) and used["gnss"]["name"] == "rtk_fixed"
    assert recon["sfm"]["mapping"]["refine_focal_length"] is False  # nadir: held
    assert recon["sfm"]["extraction"]["max_image_size"] == 1024


def test_photos_without_a_logged_pitch_hold_the_camera_as_a_pinhole(consumer_records):
    """No XMP: the pitch is taken as nadir, so the rule says why it cannot judge the flight, and
    the held one-term lens is written as the pinhole it is."""
    import dataclasses

    bare = [dataclasses.replace(r, pitch_deg=None, heading_deg=None) for r in consumer_records]
    recon, used = resolved(compose_photos(), bare)
    assert recon["sfm"]["mapping"]["refine_focal_length"] is False
    assert recon["sfm"]["mapping"]["refine_extra_params"] is False
    assert used["refine"]["why"].endswith("no gimbal pitch in the photos (no DJI XMP): camera held")
    assert used["camera"]["model"] == "PINHOLE"
    focal = bare[0].focal_px
    assert used["camera"]["params"] == [focal, focal, bare[0].width / 2.0, bare[0].height / 2.0]


def test_reconstruct_consumer_gnss_reaches_the_sfm_settings_over_the_photos(rtk_records):
    recon, used = resolved(compose_photos("reconstruct=consumer_gnss"), rtk_records)
    assert recon["gnss"]["sigma_m"] == 2.0  # the group chosen, though the photos say RTK
    assert used["gnss"]["source"] == "yours (reconstruct.gnss.sigma_m)"


def test_a_typed_sigma_reaches_the_sfm_settings(consumer_records):
    recon, used = resolved(compose_photos("reconstruct.gnss.sigma_m=0.7"), consumer_records)
    assert recon["gnss"]["sigma_m"] == 0.7 and used["gnss"]["sigma_m"] == 0.7
    recon, _ = resolved(compose_photos("reconstruct.sfm.mapping.refine_focal_length=true"), consumer_records)
    assert recon["sfm"]["mapping"]["refine_focal_length"] is True  # typed beats the rule too
    with pytest.raises(PhotoError, match="reconstruct.gnss.sigma_m"):
        resolved(compose_photos("reconstruct.gnss.sigma_m=-1"), consumer_records)


def test_the_simulated_study_keeps_its_reconstruction():
    """conf/config.yaml's reconstruct group is untouched: the photo defaults live in their own group."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("config", overrides=["scene=tomb"])
    assert cfg.reconstruct.gnss.sigma_m == 0.05
    assert cfg.reconstruct.sfm.extraction.max_image_size == 3200
    assert cfg.reconstruct.sfm.mapping.refine_focal_length is False


# -- the sanity gate -----------------------------------------------------------------------------


def flight_grid(n_rows: int = 3, n_cols: int = 6) -> np.ndarray:
    """Camera centres of a three-line nadir survey over 84 m at 40 m (the shared flight's shape)."""
    xs, ys = np.meshgrid(np.linspace(0, 84, n_cols), np.linspace(0, 84, n_rows))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 40.0)])


def test_the_gate_passes_a_consumer_model_within_its_class():
    rng = np.random.default_rng(0)
    centres = flight_grid()
    fixes = centres + rng.normal(0, 0.8, centres.shape)
    record = model_residuals(centres, fixes) | {"rotation_error_median_deg": 3.5}
    assert record["position_error_median_m"] < 2.0
    assert sanity_failures(record, 2.0, 3.0, 5.0) == []


def test_the_gate_refuses_a_model_from_shuffled_gnss_tags():
    rng = np.random.default_rng(1)
    centres = flight_grid()
    fixes = (centres + rng.normal(0, 0.8, centres.shape))[rng.permutation(len(centres))]
    record = model_residuals(centres, fixes) | {"rotation_error_median_deg": 2.0}
    assert record["position_error_median_m"] > 6.0
    failures = sanity_failures(record, 2.0, 3.0, 5.0)
    assert len(failures) == 1 and "more than photos.max_residual_sigmas = 3 x 2 m" in failures[0]


def test_the_gate_refuses_camera_centres_17_m_from_their_fixes():
    rng = np.random.default_rng(2)
    centres = flight_grid(5, 15)
    direction = rng.normal(size=centres.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    fixes = centres + 17.0 * direction  # every fix 17 m off, in its own direction
    record = model_residuals(centres, fixes)
    assert 12.0 < record["position_error_median_m"] < 20.0  # the similarity cannot absorb them
    assert sanity_failures(record | {"position_error_median_m": 17.6}, 2.0, 3.0, 5.0)
    assert sanity_failures(record, 2.0, 3.0, 5.0)


def test_the_gate_refuses_rotations_off_the_gimbal_unless_the_photos_log_none():
    record = {"position_error_median_m": 0.5, "rotation_error_median_deg": 77.7}
    (failure,) = sanity_failures(record, 2.0, 3.0, 5.0)
    assert "77.7 deg" in failure and "photos.max_rotation_deg = 5" in failure
    assert sanity_failures(record, 2.0, 3.0, 5.0, attitude_logged=False) == []


# -- the drone's heights, by construction --------------------------------------------------------


def ground_proxy() -> trimesh.Trimesh:
    return trimesh.creation.box(
        extents=(200.0, 200.0, 1.0), transform=trimesh.transformations.translation_matrix((0.0, 0.0, -0.5))
    )


def test_views_above_the_ceiling_move_down_and_below_the_floor_move_up(tmp_path):
    from drone.model import DroneSettings

    drone = DroneSettings.default()
    vps = np.array(
        [[0, 0, 66.4, 0, -90], [10, 0, 137.19, 0, -90], [20, 0, 168.2, 0, -60], [30, 0, 1.0, 0, -30]]
    )
    plan = Plan(vps, ["a", "b", "c", "d"], "test")
    bounded, record = keep_within_heights(plan, ground_proxy(), drone)
    assert record["n_moved_down"] == 2 and record["n_moved_up"] == 1 and record["n_dropped"] == 0
    # Down to 0.5 m under the ceiling (the curvature a mission's ellipsoidal heights add), up to the floor.
    assert bounded.viewpoints[:, 2].tolist() == [66.4, 119.5, 119.5, 2.0]
    assert record["max_move_m"] == pytest.approx(48.7)
    assert bounded.info["envelope"] == record
    # A plan within the heights is the same object: nothing of the simulated study moves.
    inside = Plan(vps[:1], ["a"], "test")
    assert keep_within_heights(inside, ground_proxy(), drone) == (inside, None)


def test_a_view_moved_into_the_proxy_is_dropped():
    from drone.model import DroneSettings

    drone = DroneSettings.default()
    tower = trimesh.creation.box(
        extents=(10.0, 10.0, 130.0), transform=trimesh.transformations.translation_matrix((50.0, 0.0, 65.0))
    )
    proxy = trimesh.util.concatenate([ground_proxy(), tower])
    vps = np.array([[0, 0, 50.0, 0, -90], [50, 0, 140.0, 0, -90]])
    bounded, record = keep_within_heights(Plan(vps, ["a", "b"], "test"), proxy, drone)
    assert record["n_dropped"] == 1 and len(bounded.viewpoints) == 1


# -- controllers -----------------------------------------------------------------------------------


def test_each_controller_has_its_cap_chosen_by_the_drone():
    assert (
        dji_app("DJI FC300S") == "fly"
        and dji_app("DJI M3E") == "pilot2"
        and dji_app("DJI FC6360") == "pilot2"
    )
    assert caps_for("DJI FC300S") == {"qgc": 240, "litchi": 99, "wpml": CAPS["fly"]}
    assert caps_for("DJI M3E") == {"qgc": 240, "litchi": 99, "wpml": 200}
    assert caps_for("DJI M3E", "fly")["wpml"] == 99
    assert caps_for("DJI FC300S", max_waypoints=50) == {"qgc": 50, "litchi": 50, "wpml": 50}


def test_a_mission_past_a_controllers_cap_splits_and_reads_back(tmp_path):
    import json
    import zipfile

    from drone.model import DroneSettings
    from mission.export import export_mission
    from mission.geo import SurveyOrigin

    drone = DroneSettings.default()
    origin = SurveyOrigin(46.8426, -91.9945, 158.5, "amsl", 90.0)
    n = 230
    vps = np.column_stack(
        [np.arange(n) * 2.0 % 80, np.arange(n) // 40 * 8.0, np.full(n, 40.0), np.zeros(n), np.full(n, -90.0)]
    )
    caps = caps_for("DJI FC300S")
    _, litchi = export_mission(vps, origin, drone, "litchi", tmp_path / "m.csv", caps["litchi"])
    _, wpml = export_mission(vps, origin, drone, "wpml", tmp_path / "m.kmz", caps["wpml"])
    _, qgc = export_mission(vps, origin, drone, "qgc", tmp_path / "m.plan", caps["qgc"])
    rows = [len(p.read_text().strip().splitlines()) - 1 for p in litchi]
    assert rows == [99, 99, 32]
    placemarks = []
    for path in wpml:
        with zipfile.ZipFile(path) as kmz:
            text = kmz.read("wpmz/waylines.wpml").decode()
        placemarks.append(text.count("<Placemark>"))
    assert placemarks == [99, 99, 32]
    waypoints = [
        sum(item.get("command") == 16 for item in json.loads(p.read_text())["mission"]["items"]) for p in qgc
    ]
    assert waypoints == [200, 30]  # drone.max_waypoints_per_file (200) is below QGC's 240


# -- the refusals' fixes, typed as printed ----------------------------------------------------------


def fixes_in(message: str) -> list[str]:
    """The settings a refusal tells the user to type: ``key=value`` words (a bad value the message
    echoes is quoted, ``key='value':``, and is not one)."""
    return re.findall(r"(?<=\s)((?:photos|reconstruct)\.[\w.]+=[^\s;:']+)(?=[\s;]|$)", message)


def test_every_refusals_fix_runs_as_printed(tmp_path):
    """Each setting a refusal prints is taken by Hydra as typed and by the job's own parser."""
    from pipeline.photo_survey import site_box

    messages = []
    for bad in ("46.8,-91.9", "[1,2]"):
        with pytest.raises(PhotoError) as info:
            parse_origin(bad)
        messages.append(str(info.value))
    no_altitude = read_photo(dji_photo(tmp_path, "noalt.JPG", rel=None))
    no_altitude = type(no_altitude)(
        **{**no_altitude.__dict__, "gps_altitude_m": None, "absolute_altitude_m": None}
    )
    with pytest.raises(PhotoError) as info:
        takeoff_origin([no_altitude])
    messages.append(str(info.value))
    with pytest.raises(PhotoError) as info:
        site_box("47.3,8.5", parse_origin([46.8, -91.9, 158.5]))
    messages.append(str(info.value))
    with pytest.raises(PhotoError) as info:
        camera_from_photos([no_altitude], "xmp")
    messages.append(str(info.value))
    from pipeline.photo_gate import gate_refusal

    messages.append(gate_refusal("camera centres a median 17.60 m from their GNSS fixes", 17.6, 2.0, 3.0))
    messages.append(gate_refusal("centres 18.12 m off; turned 6.2 deg", 18.12, 2.0, 3.0, 6.2, 5.0))
    fixes = [fix for message in messages for fix in fixes_in(message)]
    assert [len(fixes_in(m)) for m in messages] == [1, 1, 1, 1, 1, 1, 2], (fixes, messages)
    assert fixes[-2:] == ["reconstruct.gnss.sigma_m=6.1", "photos.max_rotation_deg=8"]
    for fix in fixes:
        cfg = compose_photos(fix)  # Hydra takes it as typed
        key, _, _ = fix.partition("=")
        value = cfg
        for part in key.split("."):
            value = value[part]
        if key == "photos.origin":
            parse_origin(value)
        elif key == "photos.roi":
            site_box(value, parse_origin([46.8, -91.9, 158.5]))
        elif key == "reconstruct.gnss.sigma_m":
            assert float(value) > 0
        elif key == "photos.max_rotation_deg":
            assert float(value) > 5
        else:
            assert key == "photos.camera" and value in ("auto", "xmp", "exif")


def test_an_rtk_flight_is_allowed_the_residual_floor():
    record = {"position_error_median_m": 0.09, "rotation_error_median_deg": 1.0}
    (failure,) = sanity_failures(record, 0.02, 3.0, 5.0)  # 9 cm > 3 x 2 cm
    assert "more than photos.max_residual_sigmas = 3 x 0.02 m" in failure
    assert sanity_failures(record, 0.02, 3.0, 5.0, min_residual_limit_m=0.15) == []
    (failure,) = sanity_failures({**record, "position_error_median_m": 0.4}, 0.02, 3.0, 5.0, True, 0.15)
    assert "at least photos.min_residual_limit_m = 0.15 m" in failure


def test_origin_and_site_typed_with_bare_commas_become_lists_hydra_takes():
    from pipeline.cli import photo_overrides

    argv = photo_overrides(
        ["/data/f", "photos.origin=46.8,-91.9,158.5", "photos.roi=1,2,3,4", "planner=ours"]
    )
    assert argv == [
        "photos.dir=/data/f",
        "photos.origin=[46.8,-91.9,158.5]",
        "photos.roi=[1,2,3,4]",
        "planner=ours",
    ]
    assert photo_overrides(["photos.origin=[1,2,3]", "photos.roi='1,2,3,4'"]) == [
        "photos.origin=[1,2,3]",
        "photos.roi='1,2,3,4'",
    ]
    cfg = compose_photos(*argv[1:3])
    assert parse_origin(cfg.photos.origin).height_m == 158.5


def test_too_few_photos_registered_is_refused_with_the_settings_that_take_them():
    from pipeline.photo_gate import registration_refusal
    from reconstruct.errors import ReconstructionError

    exc = ReconstructionError(
        "exploratory flight registered 66.7% < reconstruct.proxy.min_registered_fraction 90%",
        {"stage": "proxy", "registered_fraction": 12 / 18},
    )
    message = str(registration_refusal(exc, {"gnss": {"sigma_m": 0.05}}))
    assert fixes_in(message) == [
        "reconstruct.gnss.sigma_m=2.0",
        "reconstruct.proxy.min_registered_fraction=0.66",
    ]
    mapping = ReconstructionError("only 3 of 18", {"stage": "mapping", "registered_fraction": 3 / 18})
    message = str(registration_refusal(mapping, {"gnss": {"sigma_m": 2.0}}))
    assert fixes_in(message) == [
        "reconstruct.min_registered_fraction=0.16",
        "reconstruct.proxy.min_registered_fraction=0.16",
    ]
    for fix in fixes_in(message):
        key, _, value = fix.partition("=")
        cfg = compose_photos(fix)
        assert float(
            cfg.reconstruct[key.split(".")[-1]]
            if key.count(".") == 1
            else cfg.reconstruct.proxy["min_registered_fraction"]
        ) == float(value)
    other = ReconstructionError("dense reconstruction produced no points", {"stage": "dense"})
    assert registration_refusal(other, {"gnss": {"sigma_m": 2.0}}) is other


def test_too_few_photos_offer_the_count_there_is(tmp_path):
    for i in range(4):
        dji_photo(tmp_path, f"{i}.JPG", lat=46.8426 + i * 1e-4)
    with pytest.raises(PhotoError) as info:
        read_photos(tmp_path, min_photos=10)
    (fix,) = fixes_in(str(info.value))
    assert fix == "photos.min_photos=4" and compose_photos(fix).photos.min_photos == 4
    assert len(read_photos(tmp_path, min_photos=compose_photos(fix).photos.min_photos).records) == 4


def test_the_lens_round_trips_warp_puts_a_point_where_colmaps_simple_radial_does():
    import pycolmap

    from experiments.photo_roundtrip import radial_warp

    w, h, f, k1 = 400, 300, 350.0, -0.1
    undistorted = np.zeros((h, w, 3), np.uint8)
    u, v = 330.0, 250.0  # pixel centre (COLMAP: +0.5)
    undistorted[int(v), int(u)] = 255
    warped = radial_warp(undistorted, k1, f)
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, w / 2, h / 2, k1])
    expected = camera.img_from_cam(np.array([[(u + 0.5 - w / 2) / f, (v + 0.5 - h / 2) / f, 1.0]]))[0]
    ys, xs = np.nonzero(warped[..., 0] > 60)
    weights = warped[ys, xs, 0].astype(float)
    found = np.array([np.average(xs + 0.5, weights=weights), np.average(ys + 0.5, weights=weights)])
    assert np.linalg.norm(found - expected) < 0.6
    assert np.linalg.norm(expected - [u + 0.5, v + 0.5]) > 3  # the lens moved it (3.6 px)


def test_a_tilted_model_is_levelled_by_the_gimbal_and_keeps_its_heading():
    from scipy.spatial.transform import Rotation

    from pipeline.photo_setup import gimbal_tilt

    rng = np.random.default_rng(3)
    gimbal = Rotation.from_euler("xyz", rng.uniform(-40, 40, (20, 3)), degrees=True).as_matrix()
    datum = Rotation.from_rotvec(np.radians([1.5, -0.8, 1.3])).as_matrix()  # model = true rotated
    model = gimbal @ datum  # cam_from_world of a model whose world is turned by the datum error
    tilt = gimbal_tilt(model, gimbal)
    up = np.array([0.0, 0.0, 1.0])
    assert np.allclose(tilt @ datum.T @ up, up)  # the model's vertical turned onto the true one
    # Levelled (world points p' = tilt p), what is left of the datum error is a turn about the
    # vertical, the heading the GNSS fixes gave: 1.3 deg of it, none of the 1.7 deg tilt.
    left = datum @ tilt.T
    assert np.allclose(left @ up, up, atol=1e-9)
    angle = np.degrees(np.arccos((np.trace(left) - 1.0) / 2.0))
    assert 1.2 < angle < 1.4
    levelled = model @ tilt.T
    assert np.allclose(gimbal.transpose(0, 2, 1) @ levelled, left)
    assert np.allclose(gimbal_tilt(gimbal, gimbal), np.eye(3))
