"""What a real flight's photos say about its own reconstruction: the GNSS class and its sigma, the
camera and whether to refine it, and the sanity gate on the aligned model.

Every value that ``conf/reconstruct/photos.yaml`` leaves at ``auto`` is taken from the photos here;
a value the user gives (a group choice such as ``reconstruct=consumer_gnss``, or a typed
``reconstruct.gnss.sigma_m=0.5``) is kept as given, and ``settings_used`` says which is which.

- GNSS class: DJI XMP ``RtkFlag`` 50 (RTK fixed) or 34 (float) with ``RtkStdLon/Lat/Hgt``: sigma is
  the RMS of the three (median over the photos), at least ``photos.rtk_min_sigma_m``; a fixed or
  float flag without them: 5 cm / 0.5 m; anything else (single point, no tags: a consumer drone):
  ``photos.consumer_sigma_m`` (2 m).
- Camera: DJI's factory calibration where the photos carry it (``DewarpData``: COLMAP's
  FULL_OPENCV with fx, fy, the principal point at ``CalibratedOpticalCenterX/Y`` plus DewarpData's
  offsets, k1, k2, p1, p2, k3; ``CalibratedFocalLength`` alone: a PINHOLE); otherwise the EXIF focal
  length with one radial term (COLMAP's SIMPLE_RADIAL: a drone's fixed lens bends a few pixels at the
  corners, one coefficient takes most of it, and more would not be fixed by a short flight).
- Refinement rule: the focal length and the distortion are refined only when the flight holds
  oblique views (gimbal pitch above -80 deg) from at least two headings 60 deg apart, at least
  ``MIN_OBLIQUE`` of them: with GNSS holding the centres, a nadir-only flight leaves the focal length
  and the scene's depth coupled (20 nadir photos' ground moved from 24 to 182 m below them,
  results/photos.md), and oblique views from two sides separate them. DJI's calibration is held.
- Sanity gate: the aligned camera centres a median of more than ``photos.max_residual_sigmas``
  sigmas from their fixes, or the cameras turned a median of more than ``photos.max_rotation_deg``
  from the gimbal's logged attitude, make a model no plan is made on.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence

import numpy as np
import pycolmap

from pipeline.photos import PhotoError, PhotoRecord

RTK_FIXED, RTK_FLOAT = 50, 34
# Sigma (m) of an RTK solution whose photos log no standard deviations.
RTK_DEFAULT_SIGMA_M = {RTK_FIXED: 0.05, RTK_FLOAT: 0.5}
# The refinement rule: oblique views (pitch above this), from two headings this far apart, this many.
OBLIQUE_PITCH_DEG = -80.0
MIN_HEADING_SPREAD_DEG = 60.0
MIN_OBLIQUE = 4


def gnss_class(records: Sequence[PhotoRecord], consumer_sigma_m: float, rtk_min_sigma_m: float) -> dict:
    """The GNSS class of a flight's photos: ``name`` (``rtk_fixed``, ``rtk_float``, ``consumer``),
    ``sigma_m`` and ``why`` (the tags it came from)."""
    flags = [r.rtk_flag for r in records if r.rtk_flag is not None]
    n = len(records)
    fixed = sum(f == RTK_FIXED for f in flags)
    floating = sum(f == RTK_FLOAT for f in flags)
    # The flight's class is the class most of its photos share: one photo out of fix does not make
    # the flight consumer grade, and a few fixed ones do not make it RTK.
    if fixed + floating > n / 2:
        flag = RTK_FIXED if fixed >= floating else RTK_FLOAT
        name = "rtk_fixed" if flag == RTK_FIXED else "rtk_float"
        stds = [r.rtk_std_m for r in records if r.rtk_flag in (RTK_FIXED, RTK_FLOAT) and r.rtk_std_m]
        if stds:
            rms = np.sqrt(np.mean(np.square(np.asarray(stds, float)), axis=1))
            sigma = max(float(np.median(rms)), float(rtk_min_sigma_m))
            why = (
                f"DJI XMP RtkFlag {flag} in {fixed + floating} of {n} photos, RtkStdLon/Lat/Hgt RMS median "
                f"{float(np.median(rms)):.3f} m (at least photos.rtk_min_sigma_m = {rtk_min_sigma_m} m)"
            )
        else:
            sigma = RTK_DEFAULT_SIGMA_M[flag]
            why = f"DJI XMP RtkFlag {flag} in {fixed + floating} of {n} photos, no RtkStd tags"
        return {"name": name, "sigma_m": sigma, "why": why}
    why = (
        "no DJI RTK tags (RtkFlag)"
        if not flags
        else f"RtkFlag 50/34 in only {fixed + floating} of {n} photos"
    )
    return {"name": "consumer", "sigma_m": float(consumer_sigma_m), "why": f"{why}: consumer grade"}


def camera_from_photos(records: Sequence[PhotoRecord], mode: str = "auto") -> dict:
    """The COLMAP camera of the flight: ``model``, ``params`` (COLMAP's order, pixels),
    ``source`` (``xmp_dewarp``, ``xmp_calibrated_focal``, ``exif``), ``why``, ``refinable`` (False
    for DJI's calibration: held).

    Args:
        mode: ``auto`` (XMP where present, else EXIF with one radial term), ``xmp`` (XMP or an error),
            ``exif`` (a PINHOLE at the EXIF focal length, the former behaviour).

    Raises:
        PhotoError: ``mode`` unknown, or ``xmp`` and the photos carry no DJI calibration.
    """
    if mode not in ("auto", "xmp", "exif"):
        raise PhotoError(f"photos.camera={mode!r}: expected auto, xmp or exif")
    first = records[0]
    w, h = first.width, first.height
    if mode != "exif":
        dewarped = [r for r in records if r.dewarp is not None]
        if dewarped:
            fx, fy, dcx, dcy, k1, k2, p1, p2, k3 = dewarped[0].dewarp
            cx0, cy0 = dewarped[0].calibrated_center_px or (w / 2.0, h / 2.0)
            return {
                "model": "FULL_OPENCV",
                "params": [fx, fy, cx0 + dcx, cy0 + dcy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0],
                "source": "xmp_dewarp",
                "why": "DJI XMP DewarpData (factory calibration: focal, centre, k1 k2 p1 p2 k3), held",
                "refinable": False,
            }
        calibrated = [r for r in records if r.calibrated_focal_px is not None]
        if calibrated:
            f = calibrated[0].calibrated_focal_px
            cx, cy = calibrated[0].calibrated_center_px or (w / 2.0, h / 2.0)
            return {
                "model": "PINHOLE",
                "params": [f, f, cx, cy],
                "source": "xmp_calibrated_focal",
                "why": "DJI XMP CalibratedFocalLength and CalibratedOpticalCenterX/Y (no DewarpData), held",
                "refinable": False,
            }
        if mode == "xmp":
            raise PhotoError(
                "photos.camera=xmp: the photos carry no DJI calibration (DewarpData or "
                "CalibratedFocalLength); give photos.camera=auto"
            )
        return {
            "model": "SIMPLE_RADIAL",
            "params": [first.focal_px, w / 2.0, h / 2.0, 0.0],
            "source": "exif",
            "why": (
                f"EXIF focal length ({first.focal_px:.1f} px) with one radial term k (COLMAP SIMPLE_RADIAL, "
                "k = 0 to start): no DJI calibration in the XMP"
            ),
            "refinable": True,
        }
    return {
        "model": "PINHOLE",
        "params": [first.focal_px, first.focal_px, w / 2.0, h / 2.0],
        "source": "exif",
        "why": f"photos.camera=exif: a pinhole at the EXIF focal length ({first.focal_px:.1f} px), held",
        "refinable": False,
    }


def refinement_allowed(viewpoints: np.ndarray) -> tuple[bool, str]:
    """The rule (module doc) on the flight's local viewpoints (N, 5): (refine?, why)."""
    vps = np.asarray(viewpoints, float)
    oblique = vps[vps[:, 4] > OBLIQUE_PITCH_DEG]
    if len(oblique) < MIN_OBLIQUE:
        return False, (
            f"{len(oblique)} of {len(vps)} photos oblique (gimbal pitch above {OBLIQUE_PITCH_DEG:.0f} deg), "
            f"{MIN_OBLIQUE} needed: focal length and depth stay coupled, camera held"
        )
    yaw = np.radians(oblique[:, 3])
    spread = np.degrees(np.max(np.abs(np.angle(np.exp(1j * (yaw[:, None] - yaw[None, :]))))))
    if spread < MIN_HEADING_SPREAD_DEG:
        return False, (
            f"oblique photos from headings within {spread:.0f} deg of each other "
            f"(< {MIN_HEADING_SPREAD_DEG:.0f}): camera held"
        )
    return True, (
        f"{len(oblique)} oblique photos from headings {spread:.0f} deg apart: focal length and "
        "distortion refined"
    )


def photo_reconstruct_config(
    reconstruct: Mapping, photos: Mapping, records: Sequence[PhotoRecord], viewpoints: np.ndarray
) -> tuple[dict, dict]:
    """The ``reconstruct`` config with every ``auto`` resolved from the photos, and what was used.

    Returns:
        (the resolved config, ``settings_used``: ``gnss`` (class, sigma, ``source``: ``photos`` or
        ``reconstruct.gnss.sigma_m``), ``camera`` (model, params, source, why), ``refine`` (focal,
        extra params, why)).
    """
    cfg = copy.deepcopy(dict(reconstruct))
    cfg["gnss"] = dict(cfg["gnss"])
    cfg["sfm"] = {**cfg["sfm"], "mapping": dict(cfg["sfm"]["mapping"])}
    klass = gnss_class(records, float(photos["consumer_sigma_m"]), float(photos["rtk_min_sigma_m"]))
    given = cfg["gnss"]["sigma_m"]
    if str(given) == "auto":
        cfg["gnss"]["sigma_m"] = klass["sigma_m"]
        gnss = {**klass, "source": "the photos (reconstruct.gnss.sigma_m: auto)"}
    else:
        sigma = float(given)
        if not (math.isfinite(sigma) and sigma > 0):
            raise PhotoError(f"reconstruct.gnss.sigma_m={given!r}: expected a positive number of metres")
        cfg["gnss"]["sigma_m"] = sigma
        gnss = {**klass, "sigma_m": sigma, "source": "yours (reconstruct.gnss.sigma_m)"}
    camera = camera_from_photos(records, str(photos.get("camera", "auto")))
    allowed, why = refinement_allowed(viewpoints)
    if not any(r.pitch_deg is not None for r in records):
        # Pitch taken as nadir for lack of a logged one: the rule cannot see an oblique flight.
        allowed, why = False, "no gimbal pitch in the photos (no DJI XMP): camera held"
    mapping = cfg["sfm"]["mapping"]
    refine = {}
    for key in ("refine_focal_length", "refine_extra_params"):
        value = mapping.get(key, False)
        if str(value) == "auto":
            mapping[key] = bool(allowed and camera["refinable"])
            refine[key] = {"value": mapping[key], "source": "the rule"}
        else:
            mapping[key] = bool(value)
            refine[key] = {"value": mapping[key], "source": f"yours (reconstruct.sfm.mapping.{key})"}
    if camera["model"] == "SIMPLE_RADIAL" and not mapping["refine_extra_params"]:
        # k held at 0 is a pinhole (and COLMAP's undistorter keeps a zero-k SIMPLE_RADIAL as it is,
        # which the dense stage does not take).
        f, cx, cy, _ = camera["params"]
        camera = {
            **camera,
            "model": "PINHOLE",
            "params": [f, f, cx, cy],
            "why": f"EXIF focal length ({f:.1f} px) as a pinhole: no DJI calibration in the XMP, and "
            "the radial term is held at k = 0",
        }
    if not camera["refinable"] and not allowed:
        refine["why"] = f"{camera['why']}; {why}"
    elif not camera["refinable"]:
        refine["why"] = camera["why"]
    else:
        refine["why"] = why
    return cfg, {"gnss": gnss, "camera": camera, "refine": refine}


def sanity_failures(
    record: Mapping,
    sigma_m: float,
    max_residual_sigmas: float,
    max_rotation_deg: float,
    attitude_logged: bool = True,
    min_residual_limit_m: float = 0.0,
) -> list[str]:
    """Why an aligned model is not to be planned on (empty: it passes the gate).

    ``record``: the reconstruction's record (``position_error_median_m``: the aligned centres
    against their own GNSS fixes; ``rotation_error_median_deg``: against the gimbal's attitude).
    The residual limit is ``max_residual_sigmas`` x ``sigma_m``, at least ``min_residual_limit_m``
    (an RTK fix's logged deviations leave out the antenna-to-camera offset and the shutter's timing).
    """
    failures = []
    residual = record.get("position_error_median_m")
    limit = max(float(max_residual_sigmas) * float(sigma_m), float(min_residual_limit_m))
    if residual is None or not math.isfinite(float(residual)):
        failures.append("no camera could be compared with its GNSS fix")
    elif float(residual) > limit:
        failures.append(
            f"camera centres a median {float(residual):.2f} m from their GNSS fixes, more than "
            f"photos.max_residual_sigmas = {max_residual_sigmas:g} x {sigma_m:g} m"
            + (
                f" (at least photos.min_residual_limit_m = {min_residual_limit_m:g} m)"
                if limit > float(max_residual_sigmas) * float(sigma_m)
                else ""
            )
        )
    rotation = record.get("rotation_error_median_deg")
    if attitude_logged and rotation is not None and float(rotation) > float(max_rotation_deg):
        failures.append(
            f"cameras turned a median {float(rotation):.1f} deg from the gimbal's logged attitude, more "
            f"than photos.max_rotation_deg = {max_rotation_deg:g}"
        )
    return failures


def model_residuals(centres: np.ndarray, fixes: np.ndarray) -> dict:
    """A least-squares similarity of ``centres`` (N, 3) onto ``fixes`` (N, 3) (Umeyama) and the
    residuals' median and p90 (m): what the alignment leaves between a model and its fixes."""
    src, dst = np.asarray(centres, float), np.asarray(fixes, float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, s, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.eye(3)
    if np.linalg.det(u @ vt) < 0:
        d[2, 2] = -1.0
    rot = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / max((a**2).sum() / len(src), 1e-12)
    aligned = scale * a @ rot.T + mu_d
    residual = np.linalg.norm(aligned - dst, axis=1)
    return {
        "position_error_median_m": float(np.median(residual)),
        "position_error_p90_m": float(np.percentile(residual, 90)),
    }


def gimbal_tilt(model_rotations: np.ndarray, gimbal_rotations: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) that levels a model whose cameras (``cam_from_world``, (N, 3, 3)) the
    gimbal logged as ``gimbal_rotations``: the world rotation between the two, averaged over the
    cameras (chordal mean), reduced to its tilt (the smallest rotation taking the model's vertical
    to the gimbal's). The gimbal's pitch and roll are held to gravity, its yaw to a compass: only
    the tilt is taken from it; the heading stays the GNSS fixes'."""
    errors = np.einsum(
        "nji,njk->nik", np.asarray(gimbal_rotations, float), np.asarray(model_rotations, float)
    )
    u, _, vt = np.linalg.svd(errors.sum(axis=0))
    world = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt  # true from model: p_true = W p_model
    up = np.array([0.0, 0.0, 1.0])
    vertical = world.T @ up  # the true vertical in the model's frame
    axis = np.cross(vertical, up)
    sin, cos = np.linalg.norm(axis), float(vertical @ up)
    if sin < 1e-12:
        return np.eye(3)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - cos) / sin**2)


def level_to_gimbal(sparse_dir, flight, max_tilt_deg: float) -> float | None:
    """Level the aligned model in ``sparse_dir`` (in place, about its cameras' centroid) by the
    gimbal's logged attitude (``flight.rotations``, ``gimbal_tilt``); return the tilt removed
    (deg), or None where it exceeds ``max_tilt_deg`` (left for the sanity gate to judge).

    Why: the similarity to consumer GNSS fixes (metres of noise) leaves the model's tilt uncertain
    by about sigma / (spread sqrt(N)): 2.2 deg on 100 rendered photos of a 60 m site at 2.5 m noise,
    which put the cameras 0.75 m (median) from the truth; levelled, 0.37 m and 0.3 deg
    (results/photos.md). The gimbal's pitch and roll, held to gravity, know the vertical better."""
    rec = pycolmap.Reconstruction(str(sparse_dir))
    index = {n: i for i, n in enumerate(flight.names)}
    ids = [i for i in rec.reg_image_ids() if rec.image(i).name in index]
    if len(ids) < 3:
        return None
    model = np.array([rec.image(i).cam_from_world().rotation.matrix() for i in ids])
    gimbal = np.array([flight.rotations[index[rec.image(i).name]] for i in ids])
    tilt = gimbal_tilt(model, gimbal)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(tilt) - 1.0) / 2.0, -1.0, 1.0))))
    if angle > max_tilt_deg:
        return None
    centre = np.mean([rec.image(i).projection_center() for i in ids], axis=0)
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(tilt), centre - tilt @ centre))
    rec.write(str(sparse_dir))
    return angle
