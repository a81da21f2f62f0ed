"""Round trip of the photo workflow: a rendered exploratory flight written as a drone's JPEGs, run
through ``uavplan plan-photos``, and compared with the simulated pipeline on the same images.

    uavplan-study photo-roundtrip cache/exploration/<key> --out study/photo_roundtrip \\
        --gnss-sigma 0.02 -- scene=tomb planner=ours

Each of the entry's images becomes a JPEG (quality 95) with EXIF GPS latitude, longitude and
altitude of its true position (from ``survey.origin``) plus GNSS noise (``--gnss-sigma``, metres,
each axis), the camera's focal length and sensor resolution, and DJI-style XMP (``RelativeAltitude``,
``AbsoluteAltitude``, ``GimbalPitchDegree``, ``GimbalYawDegree``, ``FlightYawDegree``). Then
``uavplan plan-photos`` runs on that folder alone, with the known origin. Printed and written to
``--out/roundtrip.json``:

- the photo proxy's distance to the simulated proxy (median and p90 over its vertices, metres);
- the forecast per surface class of the planner on each proxy (percentage points apart);
- every exported waypoint read back independently (Litchi CSV through pyproj, QGroundControl JSON)
  against its plan position (metres);
- the times: the photo job end to end against the simulated exploration's reconstruction plus
  planning of the same images.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# GNSS noise (m) below which a rendered flight's photos are written as an RTK drone's (RtkFlag 50).
RTK_MAX_SIGMA_M = 0.1


def _rational(value: float, denominator: int = 10000) -> str:
    f = Fraction(value).limit_denominator(denominator)
    return f"{f.numerator}/{f.denominator}"


def _dms(value: float) -> str:
    value = abs(float(value))
    degrees = int(value)
    minutes = int((value - degrees) * 60)
    seconds = (value - degrees - minutes / 60.0) * 3600.0
    return f"{degrees}/1 {minutes}/1 {round(seconds * 10000)}/10000"


def write_photo(
    path: Path,
    rgb: np.ndarray,
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float,
    relative_altitude_m: float | None,
    heading_deg: float,
    pitch_deg: float,
    focal_mm: float,
    pixels_per_mm: float,
    extra_xmp: dict | None = None,
) -> Path:
    """Write ``rgb`` as a JPEG with a drone's EXIF GPS and camera and DJI XMP attitude tags
    (``extra_xmp``: more ``drone-dji`` tags by name, e.g. ``{"RtkFlag": "50"}``)."""
    import pyexiv2
    from PIL import Image

    from pipeline.photos import DJI_XMP_NAMESPACE

    Image.fromarray(np.asarray(rgb, np.uint8)).save(path, quality=95)
    try:
        pyexiv2.registerNs(*DJI_XMP_NAMESPACE)
    except RuntimeError:
        pass
    with pyexiv2.Image(str(path)) as image:
        image.modify_exif(
            {
                "Exif.Image.Make": "DJI",
                "Exif.Image.Model": "uavplan render",
                "Exif.GPSInfo.GPSLatitudeRef": "N" if latitude_deg >= 0 else "S",
                "Exif.GPSInfo.GPSLatitude": _dms(latitude_deg),
                "Exif.GPSInfo.GPSLongitudeRef": "E" if longitude_deg >= 0 else "W",
                "Exif.GPSInfo.GPSLongitude": _dms(longitude_deg),
                "Exif.GPSInfo.GPSAltitudeRef": "0" if altitude_m >= 0 else "1",
                "Exif.GPSInfo.GPSAltitude": _rational(abs(altitude_m), 1000),
                "Exif.Photo.FocalLength": _rational(focal_mm, 1000),
                "Exif.Photo.FocalPlaneXResolution": _rational(pixels_per_mm, 1000),
                "Exif.Photo.FocalPlaneYResolution": _rational(pixels_per_mm, 1000),
                "Exif.Photo.FocalPlaneResolutionUnit": "4",  # millimetres
            }
        )
        xmp = {
            "Xmp.drone-dji.AbsoluteAltitude": f"{altitude_m:+.3f}",
            "Xmp.drone-dji.GimbalPitchDegree": f"{pitch_deg:+.2f}",
            "Xmp.drone-dji.GimbalYawDegree": f"{((heading_deg + 180.0) % 360.0) - 180.0:+.2f}",
            "Xmp.drone-dji.FlightYawDegree": f"{((heading_deg + 180.0) % 360.0) - 180.0:+.2f}",
        }
        if relative_altitude_m is not None:
            xmp["Xmp.drone-dji.RelativeAltitude"] = f"{relative_altitude_m:+.3f}"
        for key, value in (extra_xmp or {}).items():
            xmp[f"Xmp.drone-dji.{key}"] = str(value)
        image.modify_xmp(xmp)
    return path


def photos_from_flight(
    image_dir: Path, out_dir: Path, origin, gnss_sigma_m: float, seed: int = 0, sensor_width_mm: float = 6.3
) -> Path:
    """Write a rendered flight (``image_dir`` with ``cameras.json``) as a drone's JPEGs in ``out_dir``.

    Positions are the true ones plus Gaussian noise of ``gnss_sigma_m`` per axis; the barometric
    ``RelativeAltitude`` is the true height above the origin with the same noise. Below
    ``RTK_MAX_SIGMA_M`` the photos are an RTK drone's: DJI XMP ``RtkFlag`` 50 (fixed) and
    ``RtkStdLon/Lat/Hgt`` of that sigma.
    """
    from PIL import Image

    from scene.cameras_file import read_cameras

    cameras = read_cameras(image_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    noisy = cameras.viewpoints[:, :3] + rng.normal(0.0, gnss_sigma_m, (len(cameras), 3))
    lat, lon, height = origin.geodetic_from_local(noisy)
    heading = origin.heading_from_yaw(cameras.viewpoints[:, 3])
    pixels_per_mm = cameras.intrinsics.width / sensor_width_mm
    focal_mm = cameras.intrinsics.focal_px / pixels_per_mm
    rtk = None
    if gnss_sigma_m < RTK_MAX_SIGMA_M:
        std = f"{gnss_sigma_m:.4f}"
        rtk = {"RtkFlag": "50", "RtkStdLon": std, "RtkStdLat": std, "RtkStdHgt": std}
    for i, name in enumerate(cameras.names):
        with Image.open(Path(image_dir) / name) as image:
            rgb = np.asarray(image.convert("RGB"))
        write_photo(
            out_dir / (Path(name).stem + ".JPG"),
            rgb,
            float(lat[i]),
            float(lon[i]),
            float(height[i]),
            float(noisy[i, 2]),
            float(heading[i]),
            float(cameras.viewpoints[i, 4]),
            focal_mm,
            pixels_per_mm,
            rtk,
        )
    return out_dir


def surface_distance(mesh_a, mesh_b, n_samples: int = 20000, seed: int = 0) -> np.ndarray:
    """Distances (m) from ``n_samples`` points on ``mesh_a`` to the surface of ``mesh_b``."""
    import trimesh

    points = trimesh.sample.sample_surface(mesh_a, n_samples, seed=seed)[0]
    return trimesh.proximity.closest_point(mesh_b, points)[1]


def read_back_waypoints(run_dir: Path, origin) -> dict[str, np.ndarray]:
    """Every exported mission's waypoints in the local frame, read with other code than wrote them:
    Litchi's CSV through pyproj's transverse Mercator at the origin, QGroundControl's JSON items."""
    import csv

    from pyproj import Transformer

    to_local = Transformer.from_crs(
        "EPSG:4326",
        f"+proj=tmerc +lat_0={origin.latitude_deg} +lon_0={origin.longitude_deg} +k=1 +ellps=WGS84",
        always_xy=True,
    )
    out = {}
    rows = []
    for path in sorted((run_dir / "missions").glob("mission*.csv")):
        with path.open() as handle:
            rows += [
                (float(r["longitude"]), float(r["latitude"]), float(r["altitude(m)"]))
                for r in csv.DictReader(handle)
            ]
    lon, lat, alt = np.array(rows).T
    east, north = to_local.transform(lon, lat)
    out["litchi"] = np.column_stack([east, north, alt])
    items = []
    for path in sorted((run_dir / "missions").glob("mission*.plan")):
        for item in json.loads(path.read_text())["mission"]["items"]:
            if item.get("command") == 16:  # MAV_CMD_NAV_WAYPOINT
                items.append(item["params"][4:7])
    lat, lon, alt = np.array(items, float).T
    east, north = to_local.transform(lon, lat)
    out["qgc"] = np.column_stack([east, north, alt])
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from pipeline.proxy import load_proxy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("entry", type=Path, help="an exploration cache entry (images/, proxy.ply, recon/)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--gnss-sigma", type=float, default=0.02, help="GNSS noise per axis (m)")
    parser.add_argument("--seed", type=int, default=0)
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser.epilog = "uavplan overrides after --: scene=tomb planner=ours"
    args = parser.parse_args(argv)
    args.overrides = overrides
    from hydra import compose, initialize_config_dir

    from mission.geo import SurveyOrigin
    from pipeline.forecast import predicted_coverage
    from pipeline.settings import planner_setup
    from scene.camera import Intrinsics
    from scene.config import plain

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose(config_name="config", overrides=list(args.overrides))
    origin = SurveyOrigin.from_config(plain(cfg.survey.origin))
    folder = photos_from_flight(
        args.entry / "images", args.out / "photos", origin, args.gnss_sigma, args.seed
    )
    run_dir = args.out / "run"
    origin_text = f"{origin.latitude_deg},{origin.longitude_deg},{origin.height_m}"
    # The site: the scene's structure box, as the simulated pipeline cuts its proxy to it.
    from scene.registry import load_scene

    box = load_scene(cfg.scene, cache_dir=cfg.cache_dir).structure_bounds
    lat, lon, _ = origin.geodetic_from_local([box.lo, box.hi])
    roi_text = f"{min(lat)},{min(lon)},{max(lat)},{max(lon)}"
    start = time.perf_counter()
    done = subprocess.run(
        [
            str(Path(sys.executable).parent / "uavplan"),
            "plan-photos",
            str(folder),
            f"photos.origin=[{origin_text}]",
            f"photos.roi=[{roi_text}]",
            f"hydra.run.dir={run_dir}",
            *args.overrides,
        ],
        cwd=ROOT,
    )
    photo_s = time.perf_counter() - start
    if done.returncode != 0:
        print("error: plan-photos failed (see above)", file=sys.stderr)
        return 2
    report = json.loads((run_dir / "report.json").read_text())
    photo_proxy, sim_proxy = load_proxy(run_dir), load_proxy(args.entry)
    distance = surface_distance(photo_proxy, sim_proxy)
    # The simulated cell's forecast: the same planner on the simulated proxy.
    import hydra

    params, _ = planner_setup(cfg)
    intrinsics = Intrinsics(**cfg.camera)
    start = time.perf_counter()
    sim_plan = hydra.utils.get_method(cfg.planner._target_)(sim_proxy, intrinsics, params, int(cfg.seed))
    sim_plan_s = time.perf_counter() - start
    from evaluate.settings import EvaluationSettings

    evaluation = EvaluationSettings.from_config(cfg.evaluate)
    d_t = float(cfg.survey.target_gsd_m) * intrinsics.focal_px
    sim_forecast = predicted_coverage(sim_proxy, sim_plan.viewpoints, intrinsics, d_t, evaluation)
    photo_plan = json.loads((run_dir / "plan" / "plan.json").read_text())
    photo_forecast = {k: v for k, v in photo_plan["predicted_coverage"].items() if k.startswith("predicted")}
    from scene.plan import read_viewpoints

    planned = read_viewpoints(run_dir / "plan" / "viewpoints.csv")[0][:, :3]
    takeoff_z = 0.0  # missions' heights are above the take-off point under the first view (z = 0)
    waypoints = {}
    for fmt, read in read_back_waypoints(run_dir, origin).items():
        read = read.copy()
        read[:, 2] += takeoff_z
        waypoints[fmt] = float(np.max(np.linalg.norm(read - planned[: len(read)], axis=1)))
    sim_recon = json.loads((args.entry / "COMPLETE.json").read_text())
    sim_recon_s = (
        sim_recon.get("align_time_s", 0.0)
        + sim_recon.get("dense_time_s", 0.0)
        + sim_recon.get("proxy_time_s", 0.0)
    )
    result = {
        "photos": report["photos"],
        "registration": report["registration"],
        "proxy_distance_median_m": float(np.median(distance)),
        "proxy_distance_p90_m": float(np.percentile(distance, 90)),
        "forecast_photo": photo_forecast,
        "forecast_simulated": sim_forecast,
        "forecast_difference_pts": {k: abs(photo_forecast[k] - sim_forecast[k]) for k in sim_forecast},
        "waypoint_error_max_m": waypoints,
        "photo_job_s": photo_s,
        "simulated_reconstruction_plus_planning_s": sim_recon_s + sim_plan_s,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "roundtrip.json").write_text(json.dumps(result, indent=1, default=float))
    print(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
