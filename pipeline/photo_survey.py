"""From a real exploratory flight to the second flight: photos in, a flyable mission out.

    uavplan plan-photos IMAGES_DIR planner=ours [overrides]      # conf/photos.yaml

photos (EXIF/XMP, ``pipeline.photos``) -> local ENU flight at take-off -> pycolmap SfM with the GNSS
fixes as priors -> the same alignment, dense stage and Poisson proxy as a simulated cell ->
the planner on that proxy, the plan check, the forecast -> QGroundControl, Litchi and DJI WPML
missions in the photos' own coordinates. The run directory::

    images/          links to the photos used + cameras.json (their local poses)
    recon/           COLMAP database, sparse model, dense.ply (local ENU, metres, Z up)
    proxy.ply        the proxy the plan is made on
    plan/            viewpoints.csv, plan.json (forecast per surface class, flight time)
    missions/        mission.plan (QGroundControl), mission.csv (Litchi), mission.kmz (DJI WPML)
    report.json      what the photos allowed: photos left out and why, photos SfM did not register,
                     the proxy's extent, the GNSS residuals after alignment, the origin
"""

from __future__ import annotations

import logging
import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import trimesh
from omegaconf import DictConfig

from drone.model import DroneSettings
from evaluate.settings import EvaluationSettings
from mission.controllers import ControllerError, caps_for
from mission.export import export_mission
from mission.geo import SurveyOrigin
from pipeline.cell import plan_stage
from pipeline.photo_figure import write_flight_figure
from pipeline.photo_setup import level_to_gimbal, photo_reconstruct_config, sanity_failures
from pipeline.photos import (
    PhotoError,
    PhotoReport,
    ground_origin,
    local_viewpoints,
    parse_origin,
    photo_intrinsics,
    read_photos,
    takeoff_height_known,
    takeoff_origin,
    write_photo_flight,
)
from pipeline.proxy import CLOUD_VOXEL_M, PROXY_FILE, load_proxy
from pipeline.settings import SettingsError, check_planner, planner_setup
from reconstruct.align import pose_errors
from reconstruct.dense_settings import DenseSettings
from reconstruct.errors import ReconstructionError
from reconstruct.flight import read_flight
from reconstruct.pipeline import build_proxy
from reconstruct.proxy import oriented_cloud
from reconstruct.sfm_settings import SfmSettings
from reconstruct.timing import cpu_seconds
from scene.base import Box
from scene.camera import Intrinsics
from scene.config import plain
from scene.io import write_json_atomic
from scene.proxy_mesh import PROXY_CLOUD_KEY, PROXY_VIEWS_KEY

log = logging.getLogger("plan_photos")

# A ground further than this fraction of the photos' height from the take-off height is reported.
DEPTH_CHECK_FRACTION = 0.05
MISSION_FILES = {"qgc": "mission.plan", "litchi": "mission.csv", "wpml": "mission.kmz"}


@dataclass(frozen=True)
class _JobSettings:
    """Every setting the job uses, checked and typed before the first photo is read."""

    folder: Path
    photos: dict  # ``cfg.photos`` as plain values
    reconstruct: dict  # ``cfg.reconstruct`` as plain values (``auto`` resolved once the photos are read)
    min_photos: int
    planner_target: str
    planner_name: str
    params: DictConfig  # the planner's parameters (``pipeline.settings.planner_setup``)
    budget: dict
    evaluation: EvaluationSettings
    drone: DroneSettings
    given_origin: SurveyOrigin | None
    seed: int
    target_gsd_m: float
    flight_order: str


@dataclass(frozen=True)
class _PhotoFlight:
    """The photos read into a local flight, with what was resolved from them."""

    report: PhotoReport
    origin: SurveyOrigin  # provisional where ``height_known`` is False
    height_known: bool
    caps: dict
    recon_cfg: dict
    used: dict
    image_dir: Path
    intrinsics: Intrinsics
    roi: Box | None
    attitude_logged: bool


def plan_from_photos(cfg: DictConfig, run_dir: Path) -> dict:
    """Run the whole job on ``cfg.photos.dir`` into ``run_dir``; returns the report it writes.

    Raises:
        pipeline.photos.PhotoError: the photos cannot make a flight, or the model they gave fails the
            sanity gate (named in the message, with the setting that changes it).
        pipeline.settings.SettingsError: a bad setting (before any photo is reconstructed).
        reconstruct.errors.ReconstructionError, scene.plan.PlanningError: a stage failed.
    """
    start, cpu_start = time.perf_counter(), cpu_seconds()
    run_dir = Path(run_dir)
    job = _checked_settings(cfg)
    flight = _read_flight(job, run_dir)
    mesh, recon, sanity = _reconstruct_with_gate(
        flight.image_dir, run_dir, flight.recon_cfg, job.seed, flight.roi, job.photos, flight.attitude_logged
    )
    origin, ground, ground_record = _settle_ground(flight, recon, mesh)
    mesh.export(run_dir / PROXY_FILE)
    proxy = _photo_proxy(
        run_dir, Path(recon["sparse_dir"]).parent, flight.image_dir, 0.0 if flight.height_known else ground
    )
    plan, plan_record, missions = _plan_and_export(job, flight, proxy, origin, run_dir)
    registered = _registered_names(Path(recon["sparse_dir"]))
    result = _report(
        job, flight, origin, ground_record, recon, sanity, mesh, plan, plan_record, missions, registered
    )
    _write_report(result, run_dir, proxy, flight.image_dir, plan, plan_record, registered, start, cpu_start)
    return result


def _checked_settings(cfg: DictConfig) -> _JobSettings:
    """Every setting checked before the first photo is read, as the typed values the job uses.

    Raises:
        pipeline.settings.SettingsError: a planner, budget, dense, evaluation or drone setting, the
            given origin or the roi's form (the message names it).
    """
    folder = Path(str(cfg.photos.dir))
    photos_cfg = plain(cfg.photos)
    try:  # every setting before the first photo is read
        params, budget = planner_setup(cfg)
        DenseSettings.from_config(cfg.reconstruct.dense)
        evaluation = EvaluationSettings.from_config(cfg.evaluate)
        drone = DroneSettings.from_config(plain(cfg.drone))
        given_origin = parse_origin(photos_cfg["origin"]) if photos_cfg.get("origin") is not None else None
        if photos_cfg.get("roi") is not None:  # its form, before any photo is read
            site_box(photos_cfg["roi"], given_origin or parse_origin([0.0, 0.0, 0.0]))
    except ValueError as exc:
        raise SettingsError(str(exc)) from exc
    return _JobSettings(
        folder=folder,
        photos=photos_cfg,
        reconstruct=plain(cfg.reconstruct),
        min_photos=int(cfg.photos.min_photos),
        planner_target=str(cfg.planner._target_),
        planner_name=cfg.planner.name,
        params=params,
        budget=budget,
        evaluation=evaluation,
        drone=drone,
        given_origin=given_origin,
        seed=int(cfg.seed),
        target_gsd_m=float(cfg.survey.target_gsd_m),
        flight_order=str(cfg.survey.get("flight_order", "planner")),
    )


def _read_flight(job: _JobSettings, run_dir: Path) -> _PhotoFlight:
    """Read the photos, resolve the reconstruction's config, the camera, the mission caps and the
    origin from them, and write them as a local flight into ``run_dir / "images"``."""
    photos_cfg = job.photos
    report = read_photos(job.folder, job.min_photos)
    try:
        caps = caps_for(report.records[0].camera, str(photos_cfg["controller"]), photos_cfg["max_waypoints"])
    except ControllerError as exc:
        raise SettingsError(str(exc)) from exc
    height_known = job.given_origin is not None or takeoff_height_known(report.records)
    origin = takeoff_origin(report.records, job.given_origin)
    recon_cfg, used = photo_reconstruct_config(
        job.reconstruct, photos_cfg, report.records, local_viewpoints(report.records, origin)
    )
    try:
        SfmSettings.from_config(recon_cfg["sfm"])
    except ValueError as exc:
        raise SettingsError(str(exc)) from exc
    used["origin"] = {
        "source": "photos.origin"
        if job.given_origin is not None
        else ("RelativeAltitude" if height_known else "the ground under the flight (reconstruction)"),
    }
    used["mission_caps"] = caps
    _log_settings(used, len(report.records), report.records[0].camera)
    image_dir = write_photo_flight(
        job.folder, run_dir / "images", report, origin, used["camera"], photos_cfg.get("proxy_image_size")
    )
    intrinsics = photo_intrinsics(report.records, used["camera"])  # the photos' own size: the plan's
    try:
        check_planner(job.planner_target, job.params, intrinsics)
    except ValueError as exc:
        raise SettingsError(str(exc)) from exc
    log.info(
        "%d photos in a local frame at %.6f, %.6f, %.1f m%s",
        len(report.records),
        origin.latitude_deg,
        origin.longitude_deg,
        origin.height_m,
        ""
        if height_known
        else " (provisional: the photos' altitude; moved to the ground once reconstructed)",
    )
    return _PhotoFlight(
        report=report,
        origin=origin,
        height_known=height_known,
        caps=caps,
        recon_cfg=recon_cfg,
        used=used,
        image_dir=image_dir,
        intrinsics=intrinsics,
        roi=site_box(photos_cfg["roi"], origin) if photos_cfg.get("roi") is not None else None,
        attitude_logged=all(r.pitch_deg is not None and r.heading_deg is not None for r in report.records),
    )


def _settle_ground(flight: _PhotoFlight, recon: dict, mesh) -> tuple[SurveyOrigin, float, dict]:
    """The ground under the flight after the reconstruction: checked against the take-off height
    where the photos gave one, else the origin (and ``mesh``, in place) moved onto it. Returns the
    origin, the ground's local z and the report's ``ground`` record."""
    origin = flight.origin
    ground = _ground_height(Path(recon["sparse_dir"]), Path(recon["dense_ply"]))
    ground_record = {"ground_z_m": round(ground, 3)}
    photo_height = float(np.median(local_viewpoints(flight.report.records, origin)[:, 2]))
    if flight.height_known and abs(ground) > DEPTH_CHECK_FRACTION * max(photo_height, 1.0):
        # With the camera held, the focal length sets the scene's depth below the fixed centres: a
        # ground this far from the take-off height says the focal length may be off by about as much
        # (or the take-off point was not on the ground under the flight).
        ground_record["depth_check"] = (
            f"the ground under the flight lies {ground:+.1f} m from the take-off height, "
            f"{100 * abs(ground) / photo_height:.0f} % of the photos' {photo_height:.0f} m: the camera's "
            "focal length may be off by about as much, or the take-off point was not on this ground"
        )
        log.warning("depth check: %s", ground_record["depth_check"])
    if not flight.height_known:
        # No take-off height in the photos: z = 0 (and the ceiling) on the ground under the flight.
        origin = ground_origin(origin, ground)
        mesh.apply_translation([0.0, 0.0, -ground])
        ground_record |= {
            "takeoff_height_m": round(origin.height_m, 3),
            "note": "no RelativeAltitude: the take-off point is the ground the reconstruction found "
            "under the flight (its 10th height percentile), the ceiling is measured from it",
        }
        log.info(
            "take-off height from the reconstruction: the ground under the flight at %.1f m above sea "
            "level (%.1f m below the photos' median altitude)",
            origin.height_m,
            -ground,
        )
    return origin, ground, ground_record


def _plan_and_export(job: _JobSettings, flight: _PhotoFlight, proxy, origin: SurveyOrigin, run_dir: Path):
    """The planner on ``proxy`` into ``run_dir / "plan"``, and its missions in ``origin``'s
    coordinates into ``run_dir / "missions"``. Returns (plan, plan record, mission files by format)."""
    with progress("planning"):
        plan, plan_record = plan_stage(
            proxy,
            flight.intrinsics,
            job.planner_target,
            job.params,
            job.seed,
            job.drone,
            job.evaluation,
            job.target_gsd_m,
            run_dir / "plan",
            job.flight_order,
        )
    missions = {}
    for fmt, name in MISSION_FILES.items():
        _, paths = export_mission(
            np.asarray(plan.viewpoints), origin, job.drone, fmt, run_dir / "missions" / name, flight.caps[fmt]
        )
        missions[fmt] = [str(p) for p in paths]
    return plan, plan_record, missions


def _report(
    job: _JobSettings,
    flight: _PhotoFlight,
    origin: SurveyOrigin,
    ground_record: dict,
    recon: dict,
    sanity: dict,
    mesh,
    plan,
    plan_record: dict,
    missions: dict,
    registered: set[str],
) -> dict:
    """``report.json``'s content, less ``figure``, ``time_s`` and ``cpu_s`` (``_write_report``)."""
    report, used = flight.report, flight.used
    lo, hi = mesh.bounds
    heights = np.asarray(plan.viewpoints)[:, 2]
    return {
        "photos": {
            **report.as_dict(),
            "folder": str(job.folder.resolve()),
            "camera": report.records[0].camera,
        },
        "settings_used": used,
        "origin": {
            "latitude_deg": origin.latitude_deg,
            "longitude_deg": origin.longitude_deg,
            "height_m": origin.height_m,
            "x_axis_heading_deg": origin.x_axis_heading_deg,
            "source": used["origin"]["source"],
        },
        "ground": ground_record,
        "registration": {
            "n_registered": int(recon["n_registered"]),
            "not_registered": sorted({r.name for r in report.records} - registered),
            # The aligned cameras against their own GNSS fixes: how well the model fits the fixes.
            "gnss_residual_median_m": recon.get("position_error_median_m"),
            "gnss_residual_p90_m": recon.get("position_error_p90_m"),
            # Without a logged attitude the photos' rotations are placeholders: nothing to compare.
            "rotation_to_gimbal_median_deg": recon.get("rotation_error_median_deg")
            if flight.attitude_logged
            else None,
            "mapping": flight.recon_cfg["sfm"]["mapping"]["method"],
        },
        "sanity": sanity,
        "proxy": {
            "extent_m": (hi - lo).round(2).tolist(),
            "bounds_m": [lo.round(2).tolist(), hi.round(2).tolist()],
            "n_faces": len(mesh.faces),
        },
        "plan": {**job.budget, **plan_record, "planner": job.planner_name},
        "waypoints": {
            "height_min_m": round(float(heights.min()), 2),
            "height_max_m": round(float(heights.max()), 2),
            "ceiling_m": job.drone.ceiling_m,
            "floor_m": job.drone.min_height_m,
        },
        "missions": missions,
    }


def _write_report(
    result: dict,
    run_dir: Path,
    proxy,
    image_dir: Path,
    plan,
    plan_record: dict,
    registered: set[str],
    start: float,
    cpu_start: float,
) -> None:
    """Draw ``flight.png`` (a failure to draw it is logged, not raised), add the figure and the
    times to ``result``, write it as ``report.json`` and log the run's summary."""
    try:
        result["figure"] = str(
            write_flight_figure(
                run_dir / "flight.png", proxy, read_flight(image_dir), plan, registered, result
            )
        )
    except Exception as exc:  # the picture is for the crew; a failure to draw it stops nothing
        log.warning("flight.png not drawn: %s", exc)
    result["time_s"] = time.perf_counter() - start
    result["cpu_s"] = cpu_seconds() - cpu_start
    write_json_atomic(run_dir / "report.json", result)
    heights = np.asarray(plan.viewpoints)[:, 2]
    log.info(
        "plan-photos: %d of %d photos registered (GNSS residual median %.3f m); proxy %s m; %d views at "
        "%.1f-%.1f m above take-off, %.1f min, %d batteries; missions in %s; %.0f s (%.0f s CPU)",
        result["registration"]["n_registered"],
        result["photos"]["n_photos"],
        result["registration"]["gnss_residual_median_m"] or float("nan"),
        result["proxy"]["extent_m"],
        plan_record["n_viewpoints"],
        heights.min(),
        heights.max(),
        plan_record["flight_time_s"] / 60.0,
        plan_record["n_batteries"],
        run_dir / "missions",
        result["time_s"],
        result["cpu_s"],
    )


def _log_settings(used: dict, n_photos: int, camera: str) -> None:
    """The values the run uses, printed before the first photo is reconstructed."""
    gnss, cam, refine = used["gnss"], used["camera"], used["refine"]
    log.info("%d photos of %s", n_photos, camera)
    log.info(
        "GNSS: %s, sigma %.3f m from %s (%s)", gnss["name"], gnss["sigma_m"], gnss["source"], gnss["why"]
    )
    log.info(
        "camera: %s %s from %s (%s)",
        cam["model"],
        [round(v, 4) for v in cam["params"]],
        cam["source"],
        cam["why"],
    )
    log.info(
        "camera refinement: focal %s, distortion %s (%s)",
        refine["refine_focal_length"]["value"],
        refine["refine_extra_params"]["value"],
        refine["why"],
    )
    log.info(
        "take-off height from %s; waypoints per mission file %s",
        used["origin"]["source"],
        used["mission_caps"],
    )


def _reconstruct_with_gate(image_dir, run_dir, recon_cfg, seed, roi, photos_cfg, attitude_logged):
    """``build_proxy`` behind the sanity gate: a model that fails it is mapped again with the other
    mapper (incremental <-> global), and refused when that fails too. Returns (mesh, record, the
    gate's record)."""
    sigma = float(recon_cfg["gnss"]["sigma_m"])
    tries = []

    level = bool(photos_cfg.get("level_with_gimbal", True)) and attitude_logged
    flight = read_flight(image_dir) if level else None

    def gate(record):
        if level:
            # The aligned model levelled by the gimbal's gravity-held attitude, before the gate and
            # the dense stage (pipeline.photo_setup.level_to_gimbal); the errors measured again.
            tilt = level_to_gimbal(Path(record["sparse_dir"]), flight, float(photos_cfg["max_rotation_deg"]))
            if tilt is not None:
                rec = pycolmap.Reconstruction(str(record["sparse_dir"]))
                record.update(pose_errors(rec, flight))
                record["gimbal_tilt_removed_deg"] = tilt
                log.info(
                    "levelled by the gimbal: %.2f deg of tilt removed; cameras %.3f m (median) from their "
                    "fixes, %.2f deg from the gimbal",
                    tilt,
                    record["position_error_median_m"],
                    record["rotation_error_median_deg"],
                )
        failures = sanity_failures(
            record,
            sigma,
            float(photos_cfg["max_residual_sigmas"]),
            float(photos_cfg["max_rotation_deg"]),
            attitude_logged,
            float(photos_cfg["min_residual_limit_m"]),
        )
        if failures:
            raise ReconstructionError("; ".join(failures), {"stage": "sanity"})

    first = recon_cfg["sfm"]["mapping"]["method"]
    other = "global" if first == "incremental" else "incremental"
    for attempt, method in enumerate((first, other)):
        cfg_try = {**recon_cfg, "sfm": {**recon_cfg["sfm"], "mapping": {**recon_cfg["sfm"]["mapping"]}}}
        cfg_try["sfm"]["mapping"]["method"] = method
        out = run_dir / ("recon" if attempt == 0 else f"recon_{method}")
        try:
            with progress("reconstruction"):
                mesh, recon = build_proxy(image_dir, out, cfg_try, seed, roi=roi, sparse_check=gate)
        except ReconstructionError as exc:
            if exc.record.get("stage") != "sanity":
                raise registration_refusal(exc, recon_cfg) from exc
            tries.append(
                {
                    "mapping": method,
                    "failed": str(exc),
                    "residual_m": exc.record.get("position_error_median_m"),
                    "rotation_deg": exc.record.get("rotation_error_median_deg"),
                }
            )
            log.warning(
                "sanity gate: the %s model fails (%s)%s",
                method,
                exc,
                "; mapping again with the " + other + " mapper" if attempt == 0 else "",
            )
            continue
        tries.append({"mapping": method, "passed": True})
        recon_cfg["sfm"]["mapping"]["method"] = method
        return (
            mesh,
            recon,
            {
                "max_residual_sigmas": float(photos_cfg["max_residual_sigmas"]),
                "max_rotation_deg": float(photos_cfg["max_rotation_deg"]),
                "min_residual_limit_m": float(photos_cfg["min_residual_limit_m"]),
                "attitude_checked": attitude_logged,
                "levelled_by_gimbal": level,
                "gimbal_tilt_removed_deg": recon.get("gimbal_tilt_removed_deg"),
                "tries": tries,
            },
        )
    last = tries[-1]
    raise PhotoError(
        gate_refusal(
            last["failed"],
            last.get("residual_m"),
            sigma,
            float(photos_cfg["max_residual_sigmas"]),
            last.get("rotation_deg"),
            float(photos_cfg["max_rotation_deg"]),
        )
    )


def registration_refusal(exc, recon_cfg: dict) -> Exception:
    """A reconstruction that registered too few photos, refused in one line with the setting that
    would take what it registered (typed as it runs); any other failure as it was."""
    fraction = exc.record.get("registered_fraction")
    if fraction is None or exc.record.get("stage") not in ("mapping", "align", "proxy") or fraction <= 0:
        return exc
    floor = math.floor(float(fraction) * 100.0) / 100.0
    sigma = float(recon_cfg["gnss"]["sigma_m"])
    hint = "; if the photos' GNSS is consumer grade, give reconstruct.gnss.sigma_m=2.0" if sigma < 1.0 else ""
    fix = f"reconstruct.proxy.min_registered_fraction={floor:.2f}"
    if exc.record.get("stage") != "proxy":
        fix = f"reconstruct.min_registered_fraction={floor:.2f} {fix}"
    return PhotoError(f"{exc}{hint}; to plan on the part registered, give {fix}")


def gate_refusal(
    failure: str,
    residual_m: float | None,
    sigma_m: float,
    max_sigmas: float,
    rotation_deg: float | None = None,
    max_rotation_deg: float = 5.0,
) -> str:
    """The sanity gate's refusal, one line: what failed with both mappers and the setting that would
    let such a model through, typed as it runs (a GNSS class that was wrong, or an attitude the
    gimbal did not log truly); a setting to use only when the photos' tags are known to be so."""
    fixes, whys = [], []
    if residual_m is not None and residual_m > max_sigmas * sigma_m:
        fixes.append(f"reconstruct.gnss.sigma_m={math.ceil(residual_m / max_sigmas * 10.0) / 10.0:.1f}")
        whys.append("the photos' GNSS is that poor")
    if rotation_deg is not None and rotation_deg > max_rotation_deg:
        fixes.append(f"photos.max_rotation_deg={math.ceil(rotation_deg + 1.0):.0f}")
        whys.append("the gimbal's logged attitude is that far off")
    if not fixes:
        fixes, whys = ["photos.camera=exif"], ["to start from the EXIF camera"]
    fix, why = (
        " ".join(fixes),
        "if " + " and ".join(whys) if whys[0] != "to start from the EXIF camera" else whys[0],
    )
    return (
        f"no model fit to plan on (with both mappers): {failure}; check the photos' GNSS tags, "
        f"or give {fix} {why}"
    )


@contextmanager
def progress(what: str, every_s: float = 20.0):
    """Log every ``every_s`` seconds how long ``what`` has run and the stage it last reported (the
    reconstruction's stages log when they start and end; extraction and matching run minutes
    without a word)."""
    last = {"message": "starting"}

    class Latest(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            last["message"] = record.getMessage()[:100]

    handler = Latest(logging.INFO)
    watched = [logging.getLogger(name) for name in ("reconstruct", "pipeline", "planner", "run")]
    for logger in watched:
        logger.addHandler(handler)
    done = threading.Event()
    start = time.perf_counter()

    def beat() -> None:
        while not done.wait(every_s):
            log.info("%s: %.0f s so far (last: %s)", what, time.perf_counter() - start, last["message"])

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        for logger in watched:
            logger.removeHandler(handler)


def _photo_proxy(run_dir: Path, recon_dir: Path, image_dir: Path, shift_z: float):
    """The proxy as ``pipeline.proxy.load_proxy`` gives it, its cloud from the reconstruction that
    passed the gate (``recon_dir``), moved down by ``shift_z`` (m) with the mesh where the take-off
    height came from the ground; the registered views go with it only where nothing moved."""
    if recon_dir == run_dir / "recon" and shift_z == 0.0:
        return load_proxy(run_dir)
    proxy = trimesh.load(run_dir / PROXY_FILE, force="mesh", process=False)
    dense_ply = recon_dir / "dense.ply"
    if dense_ply.is_file():
        box = Box.from_points(proxy.vertices + np.array([0.0, 0.0, shift_z]))
        cloud = dict(oriented_cloud(dense_ply, box.expanded(1.0, 1.0, 1.0), CLOUD_VOXEL_M))
        cloud["points"] = np.asarray(cloud["points"]) - np.array([0.0, 0.0, shift_z])
        proxy.metadata[PROXY_CLOUD_KEY] = cloud
    if shift_z == 0.0:
        proxy.metadata[PROXY_VIEWS_KEY] = {"recon_dir": recon_dir, "image_dir": image_dir}
    return proxy


def _ground_height(sparse_dir: Path, dense_ply: Path) -> float:
    """The ground under the flight (m, local z): the 10th height percentile of the dense cloud's
    points below the cameras' horizontal extent (the sparse points' where the cloud is empty)."""
    rec = pycolmap.Reconstruction(str(sparse_dir))
    centres = np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()])
    try:
        points = np.asarray(trimesh.load(dense_ply).vertices)
    except Exception:  # noqa: BLE001 - any unreadable cloud: fall back on the sparse points
        points = np.zeros((0, 3))
    if len(points) == 0:
        points = np.array([p.xyz for p in rec.points3D.values()])
    lo, hi = centres[:, :2].min(0), centres[:, :2].max(0)
    inside = np.all((points[:, :2] >= lo) & (points[:, :2] <= hi), axis=1)
    below = points[inside] if inside.sum() >= 100 else points
    return float(np.percentile(below[:, 2], 10.0))


def site_box(text, origin):
    """The local box (``scene.base.Box``, metres; all heights) of a ``[SOUTH,WEST,NORTH,EAST]`` site
    (a list, as Hydra takes it typed, or a string)."""
    parts = text.replace("[", "").replace("]", "").split(",") if isinstance(text, str) else list(text)
    try:
        south, west, north, east = (float(v) for v in parts)
    except (TypeError, ValueError) as exc:
        raise PhotoError(
            f"photos.roi={text!r}: expected [SOUTH,WEST,NORTH,EAST] in degrees, typed "
            "photos.roi=[47.3975,8.5452,47.3981,8.5461]"
        ) from exc
    if not (-90 <= south < north <= 90 and -180 <= west < east <= 180):
        raise PhotoError(
            f"photos.roi={text!r}: need -90 <= south < north <= 90 and -180 <= west < east <= 180"
        )
    corners = origin.local_from_geodetic(
        [south, south, north, north], [west, east, west, east], [origin.height_m] * 4
    )
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return Box((float(lo[0]), float(lo[1]), -1e4), (float(hi[0]), float(hi[1]), 1e4))


def _registered_names(sparse_dir: Path) -> set[str]:
    rec = pycolmap.Reconstruction(str(sparse_dir))
    return {rec.image(i).name for i in rec.reg_image_ids()}
