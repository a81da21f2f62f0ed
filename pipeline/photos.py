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


def _register_dji_namespace() -> None:
    import pyexiv2

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
    import pyexiv2
    from PIL import Image

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


def takeoff_origin(records: list[PhotoRecord], origin: SurveyOrigin | None = None) -> SurveyOrigin:
    """The local frame's origin: ``origin`` when given, else the first photo's horizontal position
    at the take-off height (median of ``AbsoluteAltitude - RelativeAltitude``, or of the GPS altitude
    minus ``RelativeAltitude``), +x east.

    Raises:
        PhotoError: no origin given and the photos do not say the take-off height.
    """
    if origin is not None:
        return origin
    heights = [
        (r.absolute_altitude_m if r.absolute_altitude_m is not None else r.gps_altitude_m)
        - r.relative_altitude_m
        for r in records
        if r.relative_altitude_m is not None
        and (r.absolute_altitude_m is not None or r.gps_altitude_m is not None)
    ]
    if not heights:
        raise PhotoError(
            "the photos carry no RelativeAltitude (DJI XMP) to find the take-off height: "
            "give photos.origin=LAT,LON,HEIGHT_M"
        )
    first = records[0]
    return SurveyOrigin(first.latitude_deg, first.longitude_deg, float(np.median(heights)), "amsl", 90.0)


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


def write_photo_flight(folder: Path, out_dir: Path, report: PhotoReport, origin: SurveyOrigin) -> Path:
    """Link the usable photos into ``out_dir`` and write their ``cameras.json``; returns ``out_dir``."""
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    records = report.records
    for r in records:
        source, target = Path(folder) / r.name, out_dir / r.name
        try:
            os.link(source, target)
        except OSError:
            shutil.copyfile(source, target)
    first = records[0]
    hfov = math.degrees(2.0 * math.atan(first.width / (2.0 * first.focal_px)))
    intrinsics = Intrinsics(first.width, first.height, hfov)
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
    }
    write_cameras(
        out_dir,
        [r.name for r in records],
        local_viewpoints(records, origin),
        intrinsics,
        ["photo"] * len(records),
        header,
    )
    return out_dir
