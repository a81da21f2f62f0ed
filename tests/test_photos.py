"""A real exploratory flight's photos: metadata read back, the local frame, and what is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments.photo_roundtrip import write_photo
from mission.geo import SurveyOrigin
from pipeline.photos import (
    PhotoError,
    ground_origin,
    local_viewpoints,
    read_photo,
    read_photos,
    takeoff_height_known,
    takeoff_origin,
    write_photo_flight,
)
from scene.cameras_file import read_cameras

ORIGIN = SurveyOrigin(47.397742, 8.545594, 488.0, "amsl", 90.0)
RGB = (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)


def photo(
    folder,
    name="a.JPG",
    lat=47.3981234,
    lon=8.5461234,
    alt=518.25,
    rel=30.25,
    heading=123.4,
    pitch=-45.5,
    focal_mm=4.5,
    px_per_mm=64 / 6.3,
):
    return write_photo(folder / name, RGB, lat, lon, alt, rel, heading, pitch, focal_mm, px_per_mm)


def test_metadata_reads_back_within_its_encoding_precision(tmp_path):
    record = read_photo(photo(tmp_path))
    # Seconds of arc in 1/10000: 3 mm of latitude; altitudes in millimetres; angles in 1/100 deg.
    # half of 1/10000 arc second: 1.4e-8 deg
    assert record.latitude_deg == pytest.approx(47.3981234, abs=1.4e-8)
    assert record.longitude_deg == pytest.approx(8.5461234, abs=1.4e-8)
    assert record.gps_altitude_m == pytest.approx(518.25, abs=1e-3)
    assert record.absolute_altitude_m == pytest.approx(518.25, abs=1e-3)
    assert record.relative_altitude_m == pytest.approx(30.25, abs=1e-3)
    assert record.heading_deg == pytest.approx(123.4, abs=0.005)
    assert record.pitch_deg == pytest.approx(-45.5, abs=0.005)
    # 4.5 mm at 64 px over 6.3 mm: 45.714 px.
    assert record.focal_px == pytest.approx(4.5 * 64 / 6.3, rel=1e-3)
    assert (record.width, record.height) == (64, 48)
    south_west = read_photo(photo(tmp_path, "b.JPG", lat=-33.5, lon=-70.25))
    assert (south_west.latitude_deg, south_west.longitude_deg) == pytest.approx((-33.5, -70.25), abs=1e-8)


def test_local_east_north_up_against_pyproj():
    """100 m north, 50 m east and 20 m up of the origin, converted back by pyproj's ECEF."""
    from pyproj import Transformer

    lat, lon, h = ORIGIN.geodetic_from_local([[50.0, 100.0, 20.0]])
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    x0 = np.array(to_ecef.transform(ORIGIN.longitude_deg, ORIGIN.latitude_deg, ORIGIN.height_m))
    x1 = np.array(to_ecef.transform(lon[0], lat[0], h[0]))
    phi, lam = math.radians(ORIGIN.latitude_deg), math.radians(ORIGIN.longitude_deg)
    east = np.array([-math.sin(lam), math.cos(lam), 0.0])
    north = np.array([-math.sin(phi) * math.cos(lam), -math.sin(phi) * math.sin(lam), math.cos(phi)])
    up = np.array([math.cos(phi) * math.cos(lam), math.cos(phi) * math.sin(lam), math.sin(phi)])
    d = x1 - x0
    assert [d @ east, d @ north, d @ up] == pytest.approx([50.0, 100.0, 20.0], abs=1e-6)


def test_the_flight_lies_in_a_frame_at_take_off(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    positions = [(0.0, 0.0, 30.0), (20.0, 0.0, 30.0), (20.0, 20.0, 35.0)]
    lat, lon, h = ORIGIN.geodetic_from_local(positions)
    for i in range(3):
        photo(folder, f"{i}.JPG", lat[i], lon[i], h[i], positions[i][2], heading=90.0, pitch=-60.0)
    report = read_photos(folder)
    origin = takeoff_origin(report.records)
    assert origin.height_m == pytest.approx(488.0, abs=1e-3)  # absolute minus relative altitude
    assert (origin.latitude_deg, origin.longitude_deg) == pytest.approx((lat[0], lon[0]), abs=1e-8)
    vps = local_viewpoints(report.records, ORIGIN)
    np.testing.assert_allclose(vps[:, :3], positions, atol=0.01)
    np.testing.assert_allclose(vps[:, 3:], [[0.0, -60.0]] * 3, atol=0.01)  # heading 90 (east) is yaw 0
    cameras = read_cameras(write_photo_flight(folder, tmp_path / "images", report, ORIGIN))
    assert cameras.names == ("0.JPG", "1.JPG", "2.JPG") and cameras.extra["positions"] == "measured"
    assert cameras.intrinsics.focal_px == pytest.approx(4.5 * 64 / 6.3, rel=1e-3)


def test_no_photos_is_refused(tmp_path):
    with pytest.raises(PhotoError, match="no photos"):
        read_photos(tmp_path)


def test_photos_without_gps_or_with_corrupt_metadata_are_left_out_by_name(tmp_path):
    for i in range(3):
        photo(tmp_path, f"good{i}.JPG")
    from PIL import Image

    Image.fromarray(RGB).save(tmp_path / "nogps.JPG")
    (tmp_path / "broken.JPG").write_bytes(b"\xff\xd8\xff\xe1 not a jpeg")
    photo(tmp_path, "far.JPG", lat=95.0)
    report = read_photos(tmp_path)
    assert len(report.records) == 3
    summary = report.as_dict()
    assert summary["n_left_out"] == 3
    assert summary["left_out"]["no GPS position"] == ["nogps.JPG"]
    assert any("unreadable" in reason or "corrupt" in reason for reason in summary["left_out"])
    assert any("outside [-90, 90]" in reason for reason in summary["left_out"])
    with pytest.raises(PhotoError, match=r"3 of 6 photos usable, at least 4 needed"):
        read_photos(tmp_path, min_photos=4)


def test_photos_of_two_cameras_are_refused_naming_both(tmp_path):
    photo(tmp_path, "a.JPG")
    photo(tmp_path, "b.JPG")
    photo(tmp_path, "c.JPG", focal_mm=8.0)
    with pytest.raises(PhotoError, match=r"photos of 2 cameras, one flight needs one"):
        read_photos(tmp_path, min_photos=2)


def test_without_a_take_off_height_the_frame_starts_at_the_photos_altitude(tmp_path):
    """No RelativeAltitude: a provisional origin at the photos' median altitude (plan-photos moves it
    to the ground it reconstructs); no altitude at all: refused with the origin typed as it runs."""
    for i, alt in enumerate((518.0, 520.0, 530.0)):
        photo(tmp_path, f"{i}.JPG", alt=alt, rel=None)
    report = read_photos(tmp_path, min_photos=1)
    assert not takeoff_height_known(report.records)
    origin = takeoff_origin(report.records)
    assert origin.height_m == pytest.approx(520.0, abs=1e-3)
    assert ground_origin(origin, -39.5).height_m == pytest.approx(480.5, abs=1e-3)
    bare = type(report.records[0])(
        **{**report.records[0].__dict__, "gps_altitude_m": None, "absolute_altitude_m": None}
    )
    with pytest.raises(PhotoError, match=r"photos.origin=\[47.398123,8.546123,0.0\]"):
        takeoff_origin([bare])
