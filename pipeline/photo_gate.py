"""The photo workflow's sanity gate around the reconstruction (``uavplan plan-photos``): a model
whose cameras disagree with their GNSS fixes or the gimbal's attitude is mapped again with the other
mapper, then refused in one line with the setting that would let it through; and the progress the
long stages report while they run."""

from __future__ import annotations

import logging
import math
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pycolmap

from pipeline.photo_setup import level_to_gimbal, sanity_failures
from pipeline.photos import PhotoError
from reconstruct.align import pose_errors
from reconstruct.errors import ReconstructionError
from reconstruct.flight import read_flight
from reconstruct.pipeline import build_proxy
from reconstruct.settings import ReconstructSettings

log = logging.getLogger("plan_photos")


def reconstruct_with_gate(image_dir, run_dir, recon_cfg, seed, roi, photos_cfg, attitude_logged):
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
                settings = ReconstructSettings.from_config(cfg_try)
                mesh, recon = build_proxy(image_dir, out, settings, seed, roi=roi, sparse_check=gate)
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
