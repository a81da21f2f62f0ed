"""Round trip of the photo workflow: a rendered exploratory flight written as a drone's JPEGs, run
through ``uavplan plan-photos``, and compared with the simulated pipeline on the same images.

    uavplan-diagnose photo-roundtrip cache/exploration/<key> --out study/photo_roundtrip \\
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


def radial_warp(rgb: np.ndarray, k1: float, focal_px: float) -> np.ndarray:
    """``rgb`` (a pinhole rendering, principal point at the centre) as a lens with radial distortion
    ``k1`` would have taken it (COLMAP's SIMPLE_RADIAL: x_d = x_u (1 + k1 |x_u|^2) on normalised
    coordinates); pixels whose ray falls outside the rendering are black."""
    import cv2

    h, w = rgb.shape[:2]
    cx, cy = w / 2.0, h / 2.0
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (xs + 0.5 - cx) / focal_px, (ys + 0.5 - cy) / focal_px
    xu, yu = xd.copy(), yd.copy()
    for _ in range(20):  # x_u = x_d / (1 + k1 r_u^2), a contraction for |k1| r^2 << 1
        factor = 1.0 + k1 * (xu * xu + yu * yu)
        xu, yu = xd / factor, yd / factor
    map_x = (xu * focal_px + cx - 0.5).astype(np.float32)
    map_y = (yu * focal_px + cy - 0.5).astype(np.float32)
    return cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def strip_xmp(folder: Path) -> None:
    """Remove every photo's XMP (the DJI tags: RelativeAltitude, the gimbal's attitude) in place."""
    import pyexiv2

    for path in sorted(Path(folder).glob("*.JPG")):
        with pyexiv2.Image(str(path)) as image:
            image.clear_xmp()


def _run_plan_photos(folder: Path, run_dir: Path, overrides: list[str]) -> tuple[int, float, float]:
    """``uavplan plan-photos folder`` into ``run_dir``: (exit code, wall s, CPU s of the child)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(
        [
            str(Path(sys.executable).parent / "uavplan"),
            "plan-photos",
            str(folder),
            f"hydra.run.dir={run_dir}",
            *overrides,
        ],
        cwd=ROOT,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return done.returncode, wall, cpu


def truth_errors(run_dir: Path, truth_dir: Path) -> dict:
    """The run's aligned cameras against the rendered flight's true poses (same local frame: the run
    was given the survey origin): centre distance (m) and rotation angle (deg), median and p90."""
    import pycolmap

    from reconstruct.align import rotation_angles_deg
    from scene.cameras_file import read_cameras

    report = json.loads((run_dir / "report.json").read_text())
    tries = report["sanity"]["tries"]
    recon_dir = run_dir / "recon" if len(tries) == 1 else run_dir / f"recon_{tries[-1]['mapping']}"
    truth = read_cameras(truth_dir)
    index = {Path(n).stem: i for i, n in enumerate(truth.names)}
    rec = pycolmap.Reconstruction(str(recon_dir / "sparse"))
    centre_err, rot_est, rot_true = [], [], []
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        i = index[Path(image.name).stem]
        true_centre = -truth.rotations[i].T @ truth.translations[i]
        centre_err.append(float(np.linalg.norm(image.projection_center() - true_centre)))
        rot_est.append(image.cam_from_world().rotation.matrix())
        rot_true.append(truth.rotations[i])
    rotation = rotation_angles_deg(np.asarray(rot_est), np.asarray(rot_true))
    camera = next(iter(rec.cameras.values()))
    return {
        "centre_error_median_m": float(np.median(centre_err)),
        "centre_error_p90_m": float(np.percentile(centre_err, 90)),
        "rotation_error_median_deg": float(np.median(rotation)),
        "rotation_error_p90_deg": float(np.percentile(rotation, 90)),
        "camera_model": str(camera.model),
        "camera_params": [float(v) for v in camera.params],
    }


def lens_roundtrip(args, cfg, origin) -> dict:
    """A rendered flight written as a real drone's photos (issue 69's target): ``--views`` of the
    entry's exploratory views rendered at ``--render-size``, warped with radial distortion ``--k1``
    after rendering, consumer GNSS noise, EXIF + XMP; ``plan-photos`` on them with the survey origin
    (cameras against the truth), then on the same photos with their XMP removed and nothing typed."""
    from render import RenderSettings, render_flight
    from scene.camera import Intrinsics
    from scene.cameras_file import read_cameras
    from scene.registry import load_scene

    width, height = (int(v) for v in args.render_size.lower().split("x"))
    entry = read_cameras(args.entry / "images")
    keep = np.unique(np.linspace(0, len(entry) - 1, min(args.views, len(entry))).round().astype(int))
    scene = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
    intrinsics = Intrinsics(width, height, float(cfg.camera.hfov_deg))
    render_dir = args.out / "render"
    # What was rendered and warped into render_dir: a later run with the same entry, views, size and
    # k1 takes the images as they are (12 MP renders cost minutes; the target times photos to plan).
    rendered = {
        "entry": str(Path(args.entry).resolve()),
        "views": [int(i) for i in keep],
        "size": [width, height],
        "k1": float(args.k1),
    }
    marker = render_dir / "lens_render.json"
    start = time.perf_counter()
    if marker.exists() and json.loads(marker.read_text()) == rendered:
        print(f"the render in {render_dir} is this one's ({len(keep)} views): kept", file=sys.stderr)
    else:
        marker.unlink(missing_ok=True)
        render_flight(
            scene, entry.viewpoints[keep], intrinsics, render_dir, RenderSettings.from_config(cfg.render)
        )
        if args.k1:
            from PIL import Image

            for name in read_cameras(render_dir).names:
                with Image.open(render_dir / name) as image:
                    rgb = np.asarray(image.convert("RGB"))
                Image.fromarray(radial_warp(rgb, args.k1, intrinsics.focal_px)).save(render_dir / name)
        marker.write_text(json.dumps(rendered))
    render_s = time.perf_counter() - start
    folder = photos_from_flight(render_dir, args.out / "photos", origin, args.gnss_sigma, args.seed)
    origin_text = f"{origin.latitude_deg},{origin.longitude_deg},{origin.height_m}"
    box = scene.structure_bounds
    lat, lon, _ = origin.geodetic_from_local([box.lo, box.hi])
    roi = f"photos.roi=[{min(lat)},{min(lon)},{max(lat)},{max(lon)}]"
    code, wall, cpu = _run_plan_photos(
        folder, args.out / "run", [f"photos.origin=[{origin_text}]", roi, *args.overrides]
    )
    result: dict = {
        "views": int(len(keep)),
        "render_size": [width, height],
        "k1": args.k1,
        "gnss_sigma_m": args.gnss_sigma,
        "render_s": render_s,
        "with_xmp": {"exit": code, "wall_s": wall, "cpu_s": cpu},
    }
    if code == 0:
        report = json.loads((args.out / "run" / "report.json").read_text())
        result["with_xmp"] |= {
            "registered": report["registration"]["n_registered"],
            "settings_used": {k: report["settings_used"][k] for k in ("gnss", "camera", "refine")},
            "waypoint_height_max_m": report["waypoints"]["height_max_m"],
            **truth_errors(args.out / "run", render_dir),
        }
    bare = args.out / "photos_no_xmp"
    if bare.exists():
        import shutil

        shutil.rmtree(bare)
    import shutil

    shutil.copytree(folder, bare)
    strip_xmp(bare)
    code, wall, cpu = _run_plan_photos(bare, args.out / "run_no_xmp", list(args.overrides))
    result["without_xmp"] = {"exit": code, "wall_s": wall, "cpu_s": cpu}
    if code == 0:
        report = json.loads((args.out / "run_no_xmp" / "report.json").read_text())
        result["without_xmp"] |= {
            "registered": report["registration"]["n_registered"],
            "ground": report["ground"],
            "waypoint_height_min_m": report["waypoints"]["height_min_m"],
            "waypoint_height_max_m": report["waypoints"]["height_max_m"],
        }
    return result


def main(argv: Sequence[str] | None = None) -> int:
    from pipeline.proxy import load_proxy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("entry", type=Path, help="an exploration cache entry (images/, proxy.ply, recon/)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--gnss-sigma", type=float, default=0.02, help="GNSS noise per axis (m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--render-size",
        default=None,
        help="WxH: re-render the entry's views at this size as a real drone's photos (with --k1, "
        "--views; the lens round trip, issue 69) instead of comparing with the simulated proxy",
    )
    parser.add_argument("--k1", type=float, default=0.0, help="radial distortion applied after rendering")
    parser.add_argument("--views", type=int, default=100, help="views of the entry to render (evenly spaced)")
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
    if args.render_size:
        result = lens_roundtrip(args, cfg, origin)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "lens_roundtrip.json").write_text(json.dumps(result, indent=1, default=float))
        print(json.dumps(result, indent=1, default=float))
        return 0
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
