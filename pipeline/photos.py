"""A real exploratory flight: a folder of drone photos read into a flight the reconstruction takes.

Every JPEG's position and camera come from its metadata, read with exiv2 (``pyexiv2``):

- EXIF GPS latitude, longitude, altitude (``Exif.GPSInfo.*``); DJI's XMP ``RelativeAltitude``
  (barometric, above the take-off point) and ``AbsoluteAltitude`` where present;
- the camera's attitude from DJI's XMP ``GimbalYawDegree`` and ``GimbalPitchDegree`` (compass
  heading and pitch of the camera; ``FlightYawDegree`` when the gimbal's yaw is missing), nadir when
  there is none;
- the focal length from ``FocalLengthIn35mmFilm`` (35 mm equivalent on the diagonal) or
  ``FocalLength`` with the sensor's ``FocalPlaneXResolution``, and the image size from the file.

Positions go into a local east-north-up frame (``mission.geo.SurveyOrigin``, pymap3d) at the
flight's take-off point, Z up, metres: the first photo's horizontal position at the take-off height
(the photos' ``AbsoluteAltitude - RelativeAltitude``), or an origin the user gives. The flight is
written as ``cameras.json`` beside links to the photos (``scene.cameras_file``), marked as measured
GNSS positions, so the reconstruction takes them as its priors as they are.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyexiv2
from PIL import Image

from mission.geo import SurveyOrigin
from scene.camera import Intrinsics
from scene.cameras_file import write_cameras

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg")
DJI_XMP_NAMESPACE = ("http://www.dji.com/drone-dji/1.0/", "drone-dji")
# The diagonal (mm) of the 36 x 24 mm frame a 35 mm equivalent focal length refers to.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
# EXIF FocalPlaneResolutionUnit: 2 inch, 3 centimetre, 4 millimetre.
FOCAL_PLANE_UNIT_MM = {"2": 25.4, "3": 10.0, "4": 1.0}
# Fewer photos than this cannot make a model at all (no fix is offered below it).
MIN_PHOTOS_FLOOR = 3
# Where the camera's attitude is not logged the photo is taken as a nadir view.
NADIR_PITCH_DEG = -90.0


class PhotoError(ValueError):
    """The photos cannot make a flight (the message names the files and what is missing)."""


@dataclass(frozen=True)
class PhotoRecord:
    """What one photo's metadata says (degrees, metres, pixels)."""

    name: str
    latitude_deg: float
    longitude_deg: float
    gps_altitude_m: float | None
    relative_altitude_m: float | None
    absolute_altitude_m: float | None
    heading_deg: float | None
    pitch_deg: float | None
    focal_px: float
    width: int
    height: int
    camera: str
    # DJI XMP where the drone logs them (None otherwise): the RTK solution (``RtkFlag``: 0 none,
    # 16 single point, 34 float, 50 fixed) and its standard deviations (m: ``RtkStdLon``,
    # ``RtkStdLat``, ``RtkStdHgt``); the factory calibration (``CalibratedFocalLength``,
    # ``CalibratedOpticalCenterX/Y`` in px; ``DewarpData``: fx, fy, cx, cy offsets from the optical
    # centre, k1, k2, p1, p2, k3).
    rtk_flag: int | None = None
    rtk_std_m: tuple[float, float, float] | None = None
    calibrated_focal_px: float | None = None
    calibrated_center_px: tuple[float, float] | None = None
    dewarp: tuple[float, ...] | None = None
    roll_deg: float | None = None


@dataclass
class PhotoReport:
    """What the photos allowed: the photos kept, and those left out with the reason."""

    records: list[PhotoRecord] = field(default_factory=list)
    left_out: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        reasons: dict[str, list[str]] = {}
        for name, reason in self.left_out.items():
            reasons.setdefault(reason, []).append(name)
        return {
            "n_photos": len(self.records) + len(self.left_out),
            "n_used": len(self.records),
            "n_left_out": len(self.left_out),
            "left_out": {reason: sorted(names) for reason, names in reasons.items()},
        }


def _rational(text: str) -> float:
    num, _, den = str(text).partition("/")
    return float(num) / float(den or 1)


def _dms(text: str) -> float:
    """Degrees of an EXIF ``d/1 m/1 s/100`` triple."""
    parts = [_rational(p) for p in str(text).split()]
    if len(parts) != 3:
        raise ValueError(f"expected degrees, minutes, seconds, got {text!r}")
    return parts[0] + parts[1] / 60.0 + parts[2] / 3600.0


def _float(xmp: dict, key: str) -> float | None:
    value = xmp.get(f"Xmp.drone-dji.{key}")
    if value is None:
        return None
    value = float(str(value).strip())
    return value if math.isfinite(value) else None


def _text(xmp: dict, key: str) -> str | None:
    value = xmp.get(f"Xmp.drone-dji.{key}")
    return None if value is None else str(value).strip()


def parse_dewarp(text: str | None) -> tuple[float, ...] | None:
    """DJI's ``DewarpData`` (``"DATE;fx,fy,cx,cy,k1,k2,p1,p2,k3"``) as its nine numbers, or None
    when absent or not nine finite numbers."""
    if not text:
        return None
    values = text.split(";", 1)[-1].split(",")
    try:
        numbers = tuple(float(v) for v in values)
    except ValueError:
        return None
    if len(numbers) != 9 or not all(math.isfinite(v) for v in numbers) or numbers[0] <= 0:
        return None
    return numbers


def _rtk(xmp: dict) -> tuple[int | None, tuple[float, float, float] | None]:
    flag = _float(xmp, "RtkFlag")
    stds = [_float(xmp, key) for key in ("RtkStdLon", "RtkStdLat", "RtkStdHgt")]
    std = tuple(stds) if all(v is not None and v >= 0 for v in stds) else None
    return (None if flag is None else int(round(flag))), std


def _register_dji_namespace() -> None:
    try:
        pyexiv2.registerNs(*DJI_XMP_NAMESPACE)
    except RuntimeError:  # registered already
        pass


def read_photo(path: Path) -> PhotoRecord:
    """One photo's position, attitude and camera; ``PhotoError`` when its metadata lacks them.

    Raises:
        PhotoError: no GPS position, a position outside [-90, 90] x [-180, 180], no focal length,
            or metadata exiv2 cannot read (the message says which).
    """
    _register_dji_namespace()
    try:
        with pyexiv2.Image(str(path)) as image:
            exif, xmp = image.read_exif(), image.read_xmp()
        with Image.open(path) as pil:
            width, height = pil.size
    except (RuntimeError, OSError, ValueError) as exc:
        raise PhotoError(f"unreadable metadata ({exc})") from exc
    if "Exif.GPSInfo.GPSLatitude" not in exif or "Exif.GPSInfo.GPSLongitude" not in exif:
        raise PhotoError("no GPS position")
    try:
        lat = _dms(exif["Exif.GPSInfo.GPSLatitude"]) * (
            -1 if exif.get("Exif.GPSInfo.GPSLatitudeRef") == "S" else 1
        )
        lon = _dms(exif["Exif.GPSInfo.GPSLongitude"]) * (
            -1 if exif.get("Exif.GPSInfo.GPSLongitudeRef") == "W" else 1
        )
        alt = None
        if "Exif.GPSInfo.GPSAltitude" in exif:
            alt = _rational(exif["Exif.GPSInfo.GPSAltitude"])
            if str(exif.get("Exif.GPSInfo.GPSAltitudeRef", "0")).strip() == "1":
                alt = -alt
        focal35 = exif.get("Exif.Photo.FocalLengthIn35mmFilm")
        if "Exif.Photo.FocalLength" in exif and "Exif.Photo.FocalPlaneXResolution" in exif:
            # The focal length in pixels of the sensor's own resolution: exact to the rational's digits.
            unit = str(exif.get("Exif.Photo.FocalPlaneResolutionUnit", "2")).strip()
            px_per_mm = _rational(exif["Exif.Photo.FocalPlaneXResolution"]) / FOCAL_PLANE_UNIT_MM.get(
                unit, 25.4
            )
            focal_px = _rational(exif["Exif.Photo.FocalLength"]) * px_per_mm
        elif focal35 is not None and float(focal35) > 0:
            # The 35 mm equivalent is whole millimetres on the frame's diagonal: ~2 % at 24 mm.
            focal_px = float(focal35) / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height)
        else:
            raise PhotoError(
                "no focal length (FocalLength with FocalPlaneXResolution, or FocalLengthIn35mmFilm)"
            )
        heading = _float(xmp, "GimbalYawDegree")
        if heading is None:
            heading = _float(xmp, "FlightYawDegree")
        rtk_flag, rtk_std = _rtk(xmp)
        center = (_float(xmp, "CalibratedOpticalCenterX"), _float(xmp, "CalibratedOpticalCenterY"))
        calibrated_focal = _float(xmp, "CalibratedFocalLength")
        record = PhotoRecord(
            name=path.name,
            latitude_deg=lat,
            longitude_deg=lon,
            gps_altitude_m=alt,
            relative_altitude_m=_float(xmp, "RelativeAltitude"),
            absolute_altitude_m=_float(xmp, "AbsoluteAltitude"),
            heading_deg=heading,
            pitch_deg=_float(xmp, "GimbalPitchDegree"),
            focal_px=focal_px,
            width=int(width),
            height=int(height),
            camera=f"{exif.get('Exif.Image.Make', '?')} {exif.get('Exif.Image.Model', '?')}".strip(),
            rtk_flag=rtk_flag,
            rtk_std_m=rtk_std,
            calibrated_focal_px=calibrated_focal if calibrated_focal and calibrated_focal > 0 else None,
            calibrated_center_px=center if None not in center else None,
            dewarp=parse_dewarp(_text(xmp, "DewarpData")),
            roll_deg=_float(xmp, "GimbalRollDegree"),
        )
    except (KeyError, ValueError, ZeroDivisionError) as exc:
        if isinstance(exc, PhotoError):
            raise
        raise PhotoError(f"corrupt metadata ({type(exc).__name__}: {exc})") from exc
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise PhotoError(f"GPS position {lat:.6f}, {lon:.6f} outside [-90, 90] x [-180, 180]")
    if not math.isfinite(focal_px) or focal_px <= 0:
        raise PhotoError(f"focal length {focal_px} px")
    return record


def read_photos(folder: Path, min_photos: int = 3) -> PhotoReport:
    """Every photo of ``folder`` (JPEG), the unusable ones left out with the reason.

    Raises:
        PhotoError: no photos, fewer than ``min_photos`` usable ones, or photos of several cameras
            (one line naming them).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise PhotoError(f"{folder}: no such folder")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
    if not paths:
        raise PhotoError(f"{folder}: no photos (JPEG files {', '.join(PHOTO_SUFFIXES)})")
    report = PhotoReport()
    for path in paths:
        try:
            report.records.append(read_photo(path))
        except PhotoError as exc:
            report.left_out[path.name] = str(exc)
    if report.left_out:
        summary = report.as_dict()["left_out"]
        log.warning(
            "%d of %d photos left out: %s",
            len(report.left_out),
            len(paths),
            "; ".join(
                f"{reason}: {', '.join(names[:3])}{' ...' if len(names) > 3 else ''}"
                for reason, names in summary.items()
            ),
        )
    if len(report.records) < min_photos:
        raise PhotoError(
            f"{folder}: {len(report.records)} of {len(paths)} photos usable, at least {min_photos} needed "
            f"({'; '.join(f'{n}: {r}' for n, r in list(report.left_out.items())[:3])})"
            + (
                f"; to try with fewer, give photos.min_photos={len(report.records)}"
                if len(report.records) >= MIN_PHOTOS_FLOOR
                else ""
            )
        )
    cameras: dict[tuple, list[str]] = {}
    for r in report.records:
        cameras.setdefault((r.camera, r.width, r.height, round(r.focal_px, 1)), []).append(r.name)
    if len(cameras) > 1:
        described = "; ".join(
            f"{cam[0]} {cam[1]}x{cam[2]} f={cam[3]} px: {len(names)} ({names[0]} ...)"
            for cam, names in cameras.items()
        )
        raise PhotoError(f"{folder}: photos of {len(cameras)} cameras, one flight needs one: {described}")
    return report


def takeoff_height_known(records: list[PhotoRecord]) -> bool:
    """Whether the photos say the take-off height (DJI ``RelativeAltitude`` beside an altitude)."""
    return any(
        r.relative_altitude_m is not None
        and (r.absolute_altitude_m is not None or r.gps_altitude_m is not None)
        for r in records
    )


def takeoff_origin(records: list[PhotoRecord], origin: SurveyOrigin | None = None) -> SurveyOrigin:
    """The local frame's origin: ``origin`` when given, else the first photo's horizontal position
    at the take-off height (median of ``AbsoluteAltitude - RelativeAltitude``, or of the GPS altitude
    minus ``RelativeAltitude``), +x east.

    Photos without a take-off height (no ``RelativeAltitude``: GPS altitude above sea level only)
    get a provisional origin at the photos' median altitude; ``pipeline.photo_survey`` moves it down
    to the ground the reconstruction finds under the flight (``ground_origin``).

    Raises:
        PhotoError: no origin given and the photos carry no altitude at all.
    """
    if origin is not None:
        return origin
    first = records[0]
    if takeoff_height_known(records):
        heights = [
            (r.absolute_altitude_m if r.absolute_altitude_m is not None else r.gps_altitude_m)
            - r.relative_altitude_m
            for r in records
            if r.relative_altitude_m is not None
            and (r.absolute_altitude_m is not None or r.gps_altitude_m is not None)
        ]
        return SurveyOrigin(first.latitude_deg, first.longitude_deg, float(np.median(heights)), "amsl", 90.0)
    altitudes = [
        r.absolute_altitude_m if r.absolute_altitude_m is not None else r.gps_altitude_m
        for r in records
        if r.absolute_altitude_m is not None or r.gps_altitude_m is not None
    ]
    if not altitudes:
        raise PhotoError(
            "the photos carry no altitude (EXIF GPSAltitude or DJI RelativeAltitude): give the take-off "
            f"point, photos.origin={origin_hint(first, 0.0)} with its height above sea level for 0.0"
        )
    return SurveyOrigin(first.latitude_deg, first.longitude_deg, float(np.median(altitudes)), "amsl", 90.0)


def origin_hint(record: PhotoRecord, height_m: float | None = None) -> str:
    """``photos.origin`` as Hydra takes it from a shell, typed as printed: ``[LAT,LON,HEIGHT_M]``."""
    height = "HEIGHT_M" if height_m is None else f"{height_m:.1f}"
    return f"[{record.latitude_deg:.6f},{record.longitude_deg:.6f},{height}]"


def ground_origin(origin: SurveyOrigin, ground_z_m: float) -> SurveyOrigin:
    """``origin`` moved straight down (or up) by ``ground_z_m`` (m, local z of the ground): the same
    horizontal frame, its z = 0 on that ground."""
    return SurveyOrigin(
        origin.latitude_deg,
        origin.longitude_deg,
        origin.height_m + float(ground_z_m),
        origin.height_reference,
        origin.x_axis_heading_deg,
    )


def parse_origin(value) -> SurveyOrigin:
    """``photos.origin`` as typed: a list ``[LAT,LON,HEIGHT_M]`` (Hydra's form, as printed) or a
    string ``"LAT,LON,HEIGHT_M"``; heights above mean sea level.

    Raises:
        PhotoError: not two to four numbers (naming the form that works).
    """
    if isinstance(value, str):
        parts = [p for p in value.replace("[", "").replace("]", "").split(",") if p.strip()]
    else:
        parts = list(value)
    try:
        numbers = [float(p) for p in parts]
    except (TypeError, ValueError):
        numbers = []
    if len(numbers) != 3 or not all(math.isfinite(v) for v in numbers):
        raise PhotoError(
            f"photos.origin={value!r}: expected latitude, longitude and height (m above sea level) of "
            "the take-off point, typed photos.origin=[47.397742,8.545594,488.0]"
        )
    lat, lon, height = numbers
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise PhotoError(f"photos.origin={value!r}: latitude or longitude off the globe")
    return SurveyOrigin(lat, lon, height, "amsl", 90.0)


def local_viewpoints(records: list[PhotoRecord], origin: SurveyOrigin) -> np.ndarray:
    """(N, 5) x, y, z (m, local ENU at ``origin``), yaw, pitch (deg) of the photos."""
    lat = np.array([r.latitude_deg for r in records])
    lon = np.array([r.longitude_deg for r in records])
    # Barometric height above take-off where logged (it is what the flight controller flies), else GPS.
    height = np.array(
        [
            origin.height_m + r.relative_altitude_m
            if r.relative_altitude_m is not None
            else (r.absolute_altitude_m if r.absolute_altitude_m is not None else r.gps_altitude_m)
            for r in records
        ],
        dtype=float,
    )
    if not np.isfinite(height).all():
        missing = [r.name for r, h in zip(records, height, strict=True) if not np.isfinite(h)]
        raise PhotoError(f"no altitude (GPS or RelativeAltitude) in {', '.join(missing[:3])}")
    xyz = origin.local_from_geodetic(lat, lon, height)
    heading = np.array([r.heading_deg if r.heading_deg is not None else 0.0 for r in records])
    pitch = np.array([r.pitch_deg if r.pitch_deg is not None else NADIR_PITCH_DEG for r in records])
    return np.column_stack([xyz, origin.yaw_from_heading(heading), np.clip(pitch, -90.0, 90.0)])


def photo_intrinsics(records: list[PhotoRecord], colmap_camera: dict | None = None) -> Intrinsics:
    """The survey camera at the photos' own size (what the planner plans for): the calibrated focal
    length where ``colmap_camera`` carries one, else the EXIF one."""
    first = records[0]
    focal = float(colmap_camera["params"][0]) if colmap_camera is not None else first.focal_px
    return Intrinsics(first.width, first.height, math.degrees(2.0 * math.atan(first.width / (2.0 * focal))))


# COLMAP camera parameters that are pixels (scaled with the image); the rest are unitless.
PIXEL_PARAMS = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 3,
    "RADIAL": 3,
    "OPENCV": 4,
    "FULL_OPENCV": 4,
}


def scaled_camera(colmap_camera: dict, scale: float) -> dict:
    """``colmap_camera`` for the image scaled by ``scale`` (focal lengths and principal point in
    pixels scale, distortion coefficients on normalised coordinates do not)."""
    n = PIXEL_PARAMS[colmap_camera["model"]]
    params = [float(v) * scale if i < n else float(v) for i, v in enumerate(colmap_camera["params"])]
    return {**colmap_camera, "params": params}


def _downscaled(source: Path, target: Path, max_size: int) -> float:
    """Write ``source`` (a JPEG) with its longest side at most ``max_size`` px; return the scale
    (JPEG DCT scaling on read, then a Lanczos resize to the exact size)."""
    with Image.open(source) as image:
        width, height = image.size
        scale = max_size / max(width, height)
        size = (round(width * scale), round(height * scale))
        image.draft("RGB", size)
        image.convert("RGB").resize(size, Image.LANCZOS).save(target, quality=95)
    return size[0] / width


def write_photo_flight(
    folder: Path,
    out_dir: Path,
    report: PhotoReport,
    origin: SurveyOrigin,
    colmap_camera: dict | None = None,
    max_image_size: int | None = None,
) -> Path:
    """Link the usable photos into ``out_dir`` and write their ``cameras.json``; returns ``out_dir``.

    ``colmap_camera``: the camera SfM starts from (``model``, ``params``: ``pipeline.photo_setup``);
    None: a pinhole at the EXIF focal length. ``max_image_size``: photos larger than this (px,
    longest side) are written downscaled to it, with the camera scaled alike (the proxy needs the
    survey's detail, not the photos'); None: linked as they are.
    """
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    records = report.records
    first = records[0]
    scale = 1.0
    downscale = max_image_size is not None and max(first.width, first.height) > int(max_image_size)
    for r in records:
        source, target = Path(folder) / r.name, out_dir / r.name
        if downscale:
            scale = _downscaled(source, target, int(max_image_size))
            continue
        try:
            os.link(source, target)
        except OSError:
            shutil.copyfile(source, target)
    intrinsics = photo_intrinsics(records, colmap_camera)
    if downscale:
        intrinsics = Intrinsics(round(first.width * scale), round(first.height * scale), intrinsics.hfov_deg)
    header = {
        "scene": f"photos:{Path(folder).name}",
        "source": str(Path(folder).resolve()),
        "positions": "measured",  # GNSS fixes from the photos: priors as they are, no simulated noise
        "origin": {
            "latitude_deg": origin.latitude_deg,
            "longitude_deg": origin.longitude_deg,
            "height_m": origin.height_m,
            "height_reference": origin.height_reference,
            "x_axis_heading_deg": origin.x_axis_heading_deg,
        },
        "camera": first.camera,
        "image_scale": scale,
    }
    if colmap_camera is not None:
        camera = scaled_camera(colmap_camera, scale)
        header["colmap_camera"] = {"model": camera["model"], "params": list(camera["params"])}
    write_cameras(
        out_dir,
        [r.name for r in records],
        local_viewpoints(records, origin),
        intrinsics,
        ["photo"] * len(records),
        header,
    )
    return out_dir
