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
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from scene.config import plain
from scene.io import write_json_atomic

log = logging.getLogger("plan_photos")

MISSION_FILES = {"qgc": "mission.plan", "litchi": "mission.csv", "wpml": "mission.kmz"}


def plan_from_photos(cfg: DictConfig, run_dir: Path) -> dict:
    """Run the whole job on ``cfg.photos.dir`` into ``run_dir``; returns the report it writes.

    Raises:
        pipeline.photos.PhotoError: the photos cannot make a flight (named in the message).
        pipeline.settings.SettingsError: a bad setting (before any photo is reconstructed).
        reconstruct.errors.ReconstructionError, scene.plan.PlanningError: a stage failed.
    """
    from drone.model import DroneSettings
    from evaluate.settings import EvaluationSettings
    from mission.export import export_mission
    from mission.geo import SurveyOrigin
    from pipeline.cell import plan_stage
    from pipeline.photos import read_photos, takeoff_origin, write_photo_flight
    from pipeline.proxy import PROXY_FILE, load_proxy
    from pipeline.settings import SettingsError, check_planner, planner_setup
    from reconstruct.dense_settings import DenseSettings
    from reconstruct.flight import read_flight
    from reconstruct.pipeline import build_proxy
    from reconstruct.sfm_settings import SfmSettings

    start = time.perf_counter()
    run_dir = Path(run_dir)
    folder = Path(str(cfg.photos.dir))
    try:  # every setting before the first photo is read
        params, budget = planner_setup(cfg)
        SfmSettings.from_config(cfg.reconstruct.sfm)
        DenseSettings.from_config(cfg.reconstruct.dense)
        evaluation = EvaluationSettings.from_config(cfg.evaluate)
        drone = DroneSettings.from_config(plain(cfg.drone))
        origin = SurveyOrigin.parse(str(cfg.photos.origin)) if cfg.photos.get("origin") else None
    except ValueError as exc:
        raise SettingsError(str(exc)) from exc

    report = read_photos(folder, int(cfg.photos.min_photos))
    origin = takeoff_origin(report.records, origin)
    image_dir = write_photo_flight(folder, run_dir / "images", report, origin)
    intrinsics = read_flight(image_dir).intrinsics
    try:
        check_planner(str(cfg.planner._target_), params, intrinsics)
    except ValueError as exc:
        raise SettingsError(str(exc)) from exc
    log.info(
        "%d photos in a local frame at %.6f, %.6f, %.1f m",
        len(report.records),
        origin.latitude_deg,
        origin.longitude_deg,
        origin.height_m,
    )

    seed = int(cfg.seed)
    roi = site_box(str(cfg.photos.roi), origin) if cfg.photos.get("roi") else None
    mesh, recon = build_proxy(image_dir, run_dir / "recon", cfg.reconstruct, seed, roi=roi)
    mesh.export(run_dir / PROXY_FILE)
    proxy = load_proxy(run_dir)
    plan, plan_record = plan_stage(
        proxy,
        intrinsics,
        str(cfg.planner._target_),
        params,
        seed,
        drone,
        evaluation,
        float(cfg.survey.target_gsd_m),
        run_dir / "plan",
        str(cfg.survey.get("flight_order", "planner")),
    )
    missions = {}
    for fmt, name in MISSION_FILES.items():
        _, paths = export_mission(
            np.asarray(plan.viewpoints), origin, drone, fmt, run_dir / "missions" / name
        )
        missions[fmt] = [str(p) for p in paths]

    registered = _registered_names(Path(recon["sparse_dir"]))
    lo, hi = mesh.bounds
    result = {
        "photos": {**report.as_dict(), "folder": str(folder.resolve()), "camera": report.records[0].camera},
        "origin": {
            "latitude_deg": origin.latitude_deg,
            "longitude_deg": origin.longitude_deg,
            "height_m": origin.height_m,
            "x_axis_heading_deg": origin.x_axis_heading_deg,
        },
        "registration": {
            "n_registered": int(recon["n_registered"]),
            "not_registered": sorted({r.name for r in report.records} - registered),
            # The aligned cameras against their own GNSS fixes: how well the model fits the fixes.
            "gnss_residual_median_m": recon.get("position_error_median_m"),
            "gnss_residual_p90_m": recon.get("position_error_p90_m"),
        },
        "proxy": {
            "extent_m": (hi - lo).round(2).tolist(),
            "bounds_m": [lo.round(2).tolist(), hi.round(2).tolist()],
            "n_faces": len(mesh.faces),
        },
        "plan": {**budget, **plan_record, "planner": cfg.planner.name},
        "missions": missions,
        "time_s": time.perf_counter() - start,
    }
    write_json_atomic(run_dir / "report.json", result)
    log.info(
        "plan-photos: %d of %d photos registered (GNSS residual median %.3f m); proxy %s m; %d views, "
        "%.1f min, %d batteries; missions in %s",
        result["registration"]["n_registered"],
        result["photos"]["n_photos"],
        result["registration"]["gnss_residual_median_m"] or float("nan"),
        result["proxy"]["extent_m"],
        plan_record["n_viewpoints"],
        plan_record["flight_time_s"] / 60.0,
        plan_record["n_batteries"],
        run_dir / "missions",
    )
    return result


def site_box(text: str, origin):
    """The local box (``scene.base.Box``, metres; all heights) of a ``SOUTH,WEST,NORTH,EAST`` site."""
    from pipeline.photos import PhotoError
    from scene.base import Box

    try:
        south, west, north, east = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise PhotoError(f"photos.roi={text!r}: expected SOUTH,WEST,NORTH,EAST in degrees") from exc
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
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse_dir))
    return {rec.image(i).name for i in rec.reg_image_ids()}
