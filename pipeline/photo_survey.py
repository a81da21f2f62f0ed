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
import time
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
from pipeline.photo_gate import progress, reconstruct_with_gate
from pipeline.photo_setup import photo_reconstruct_config
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
from reconstruct.dense_settings import DenseSettings
from reconstruct.flight import read_flight
from reconstruct.proxy import oriented_cloud
from reconstruct.settings import ReconstructSettings
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
    mesh, recon, sanity = reconstruct_with_gate(
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
    try:  # every value resolved: the whole group checked before the reconstruction
        ReconstructSettings.from_config(recon_cfg)
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
