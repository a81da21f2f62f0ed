"""The reconstruction stage end to end: a rendered flight in, a sparse model, a dense cloud and (for
the exploratory flight) a proxy mesh out, with content-hash caching and COLMAP's log in the output.

    reconstruct_flight(image_dir, out_dir, settings, seed) -> record      # SfM, alignment, dense
    build_proxy(image_dir, cache_dir, settings, seed) -> (mesh, record)   # + Poisson proxy

Each takes the stage's typed settings (``reconstruct.settings.ReconstructSettings``); the content
keys that let a kept result stand in for a run are computed here, around the stages
(``reconstruct.cache_keys``), from the settings as given.

Output folder of ``reconstruct_flight``::

    database.db    COLMAP database (features, matches, GNSS pose priors)
    sparse/        the largest model, aligned to the world frame (COLMAP binary)
    dense/         COLMAP dense workspace (undistorted images, depth and normal maps)
    dense.ply      fused dense cloud in the world frame
    gnss.json      the simulated GNSS positions used as priors
    colmap.log.*   COLMAP's log
    sfm.json       the record up to the aligned sparse model (the stage a killed run resumes from)
    recon.json     the record below plus the content key of the inputs
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import trimesh

from reconstruct.align import georeference_models, pose_errors
from reconstruct.cache_keys import cached_record, flight_content_key
from reconstruct.dense import dense_reconstruct
from reconstruct.errors import ReconstructionError
from reconstruct.flight import Flight, read_flight, simulate_gnss
from reconstruct.proxy import poisson_proxy
from reconstruct.settings import ReconstructSettings
from reconstruct.sfm import run_sfm
from reconstruct.timing import stage_time
from scene.base import Box
from scene.io import write_atomic, write_json_atomic

log = logging.getLogger(__name__)

RECORD_FILE = "recon.json"
# Written once the aligned sparse model is on disk: a run killed later (dense matching of a large
# flight takes an hour on 2 cores) resumes from it when the content key is the same.
SFM_RECORD_FILE = "sfm.json"
PROXY_FILE = "proxy.ply"
PROXY_RECORD_FILE = "proxy.json"


@contextmanager
def colmap_log_to(out_dir: Path) -> Iterator[None]:
    """Route COLMAP's (glog) log into ``out_dir/colmap.log.<timestamp>.<pid>`` for the block.

    Every severity goes into the one INFO file; errors still reach stderr.
    """
    logging_ = pycolmap.logging
    saved = (logging_.logtostderr, logging_.alsologtostderr)
    logging_.logtostderr = False
    logging_.alsologtostderr = False
    for level in (logging_.WARNING, logging_.ERROR, logging_.FATAL):
        logging_.set_log_destination(level, "")
    logging_.set_log_destination(logging_.INFO, str(Path(out_dir) / "colmap.log."))
    try:
        yield
    finally:
        # An empty destination closes the run's file (glog: "don't log this severity to a file").
        logging_.set_log_destination(logging_.INFO, "")
        logging_.logtostderr, logging_.alsologtostderr = saved


def reconstruct_flight(
    image_dir, out_dir, settings: ReconstructSettings, seed: int, ground_truth=None, sparse_check=None
) -> dict:
    """SfM with GNSS priors, similarity alignment to GNSS, dense depth + fusion for one flight.

    Skipped (the stored record is returned, ``cached`` True) when ``out_dir/recon.json`` holds the
    same content key: image bytes, ``cameras.json``, the relevant ``reconstruct`` settings, seed.

    Args:
        image_dir: the renderer's output (images + ``cameras.json``).
        out_dir: output folder (see the module docstring for its layout).
        settings: the ``reconstruct`` settings, typed (``ReconstructSettings.from_config``).
        seed: seed of the GNSS noise, RANSAC and the mapper.
        ground_truth: the ground-truth mesh, for ``dense.backend=oracle`` only.
        sparse_check: called with the record once the aligned sparse model is on disk, before the
            dense stage; it raises ``ReconstructionError`` to stop on a model not worth densifying
            (a real flight's sanity gate, ``pipeline.photo_setup``). None: no check.

    Returns:
        A flat record: ``status``, ``n_images``, ``n_registered``, ``registered_fraction``, pose
        errors (m, deg), ``extraction_time_s``, ``matching_time_s``, ``mapping_time_s``,
        ``align_time_s`` (their sum), ``dense_time_s``, ``n_dense_points``, ``dense_ply``,
        ``sparse_dir``, ``database``, ``colmap_log``, ``cached``.

    Raises:
        ReconstructionError: too few images, no features, too small a registered fraction, failed
            alignment, or no dense points; its ``record`` carries the failure for ``metrics.json``.
    """
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    flight = _checked_flight(image_dir, _typed(settings))
    key = flight_content_key(image_dir, flight, settings.node, seed)
    cached = cached_record(out_dir, key, RECORD_FILE, ("sparse", "dense.ply", "database.db"))
    if cached is not None:
        log.info("reconstruction of %s unchanged: reusing %s", image_dir, out_dir)
        return cached | {"cached": True}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / RECORD_FILE).unlink(missing_ok=True)
    sparse_stage = cached_record(out_dir, key, SFM_RECORD_FILE, ("sparse", "database.db"))
    if sparse_stage is None:
        (out_dir / SFM_RECORD_FILE).unlink(missing_ok=True)
        for old_log in out_dir.glob("colmap.log.*"):
            old_log.unlink()

    gnss, sigma = _write_gnss(flight, out_dir, settings.gnss_sigma_m, seed)
    record: dict = {"status": "running", "n_images": len(flight), "gnss_sigma_m": sigma}
    try:
        with colmap_log_to(out_dir):
            if sparse_stage is None:
                record |= _sparse_stage(flight, out_dir, gnss, sigma, settings, seed, record)
                write_json_atomic(out_dir / SFM_RECORD_FILE, record | {"status": "ok", "content_key": key})
            else:
                log.info(
                    "resuming %s after SfM: reusing its aligned sparse model (%d of %d registered, "
                    "SfM %.0f s)",
                    out_dir,
                    sparse_stage["n_registered"],
                    sparse_stage["n_images"],
                    sparse_stage["align_time_s"],
                )
                record |= _drop(sparse_stage, ("status", "content_key")) | {"resumed_after_sfm": True}
            if sparse_check is not None:
                sparse_check(record)
            record |= _dense_stage(
                flight.image_dir, out_dir / "sparse", out_dir, settings, record, ground_truth, seed
            )
    except ReconstructionError as exc:
        exc.record = record | {"status": "failed", "cached": False} | exc.record
        write_json_atomic(out_dir / RECORD_FILE, exc.record | {"content_key": key})
        raise
    record |= {"status": "ok", "cached": False, "colmap_log": _newest_log(out_dir), "content_key": key}
    record["deterministic"] = settings.deterministic
    write_json_atomic(out_dir / RECORD_FILE, record)
    return record


def sfm_flight(image_dir, out_dir, settings: ReconstructSettings, seed: int) -> dict:
    """The SfM stage alone, uncached (``uavplan stage sfm``): SfM with GNSS priors and the
    alignment to them. Writes ``out_dir/``: ``database.db``, ``gnss.json``, ``sparse/`` (aligned,
    world metres), ``colmap.log.*``.

    Returns:
        the record ``reconstruct_flight`` keeps in ``sfm.json`` (registration, pose errors, times).

    Raises:
        ReconstructionError: as ``reconstruct_flight``'s SfM half.
    """
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    flight = _checked_flight(image_dir, _typed(settings))
    out_dir.mkdir(parents=True, exist_ok=True)
    gnss, sigma = _write_gnss(flight, out_dir, settings.gnss_sigma_m, seed)
    record: dict = {"status": "running", "n_images": len(flight), "gnss_sigma_m": sigma}
    with colmap_log_to(out_dir):
        return _sparse_stage(flight, out_dir, gnss, sigma, settings, seed, record) | {"status": "ok"}


def dense_flight(
    image_dir, sparse_dir, out_dir, settings: ReconstructSettings, seed: int, ground_truth=None
) -> dict:
    """The dense stage alone, uncached (``uavplan stage dense``): depth maps and fusion of the
    aligned model ``sparse_dir`` over the images of ``image_dir``, into ``out_dir/dense.ply`` (world
    metres) and ``out_dir/dense/`` (the workspace).

    Returns:
        the dense fields of ``reconstruct_flight``'s record (``dense_ply``, ``n_dense_points``, ...).

    Raises:
        ReconstructionError: no dense points.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return _dense_stage(Path(image_dir), Path(sparse_dir), out_dir, _typed(settings), {}, ground_truth, seed)


def _typed(settings) -> ReconstructSettings:
    """``settings``, refused unless typed: the stage reads no config mapping."""
    if not isinstance(settings, ReconstructSettings):
        raise TypeError(
            f"the reconstruction takes ReconstructSettings (ReconstructSettings.from_config), "
            f"not {type(settings).__name__}"
        )
    return settings


def _checked_flight(image_dir: Path, settings: ReconstructSettings) -> Flight:
    """The rendered (or photographed) flight in ``image_dir``, refused below ``min_images``."""
    flight = read_flight(image_dir)
    min_images = settings.min_images
    if len(flight) < max(min_images, 2):
        raise ReconstructionError(
            f"{image_dir}: {len(flight)} images, the reconstruction needs at least {max(min_images, 2)}",
            {"stage": "input", "n_images": len(flight), "n_registered": 0, "registered_fraction": 0.0},
        )
    return flight


def _write_gnss(flight: Flight, out_dir: Path, sigma: float, seed: int) -> tuple[np.ndarray, float]:
    """The GNSS priors (m, world frame) and their sigma (m), written to ``out_dir/gnss.json``.

    A real flight's fixes are the priors; a rendered one's true positions get noise of ``sigma`` (m)."""
    gnss = flight.positions if flight.gnss_measured else simulate_gnss(flight.positions, sigma, seed)
    write_json_atomic(
        out_dir / "gnss.json",
        {
            "sigma_m": sigma,
            "seed": int(seed),
            "positions": dict(zip(flight.names, gnss.tolist(), strict=True)),
        },
    )
    return gnss, sigma


def _drop(record: dict, keys) -> dict:
    return {k: v for k, v in record.items() if k not in keys}


def _sparse_stage(
    flight: Flight,
    out_dir: Path,
    gnss: np.ndarray,
    sigma: float,
    settings: ReconstructSettings,
    seed: int,
    record: dict,
) -> dict:
    """SfM, georeferencing and the GNSS check; writes ``sparse/``. Returns the record so far."""
    sfm = run_sfm(flight, out_dir, gnss, sigma, settings.sfm, seed, settings.deterministic)
    record |= {f"{k}_time_s": v for k, v in sfm.times_s.items()}
    record |= {f"{k}_cpu_s": v for k, v in sfm.cpu_s.items()}
    record |= {
        "align_time_s": sum(sfm.times_s.values()),
        "align_cpu_s": sum(sfm.cpu_s.values()),
        "matching_method": sfm.matching_method,
        "n_image_pairs": sfm.n_image_pairs,
        "n_pairs_rejected_by_priors": sfm.n_pairs_rejected,
        "database": str(out_dir / "database.db"),
    }
    min_fraction = settings.min_registered_fraction
    n_mapped = len({m.image(i).name for m in sfm.models for i in m.reg_image_ids()})
    record |= {
        "n_models": sfm.n_models,
        "n_registered": n_mapped,
        "registered_fraction": n_mapped / len(flight),
    }
    if n_mapped / len(flight) < min_fraction:
        raise ReconstructionError(
            f"{flight.image_dir}: only {n_mapped} of {len(flight)} images registered in "
            f"{sfm.n_models} model(s) ({n_mapped / len(flight):.1%} < reconstruct.min_registered_fraction "
            f"{min_fraction:.0%})",
            {"stage": "mapping"},
        )
    with stage_time() as clock:
        rec, merge_report = georeference_models(sfm.models, flight.names, gnss, sigma, settings.align, seed)
    record["similarity_time_s"] = clock.wall_s
    record |= merge_report | {"n_registered_before_gnss_check": n_mapped}
    record |= pose_errors(rec, flight)
    n_reg = record["n_registered"]
    if record["registered_fraction"] < min_fraction:
        raise ReconstructionError(
            f"{flight.image_dir}: {n_reg} of {len(flight)} images registered after merging "
            f"{merge_report['n_models_merged'] + 1} of {sfm.n_models} model(s) and de-registering "
            f"{merge_report['n_gnss_outliers']} GNSS outliers ({record['registered_fraction']:.1%} < "
            f"reconstruct.min_registered_fraction {min_fraction:.0%})",
            {"stage": "align"},
        )
    log.info(
        "registered %d/%d, camera position error median %.3f m (p90 %.3f m), rotation %.3f deg",
        n_reg,
        len(flight),
        record["position_error_median_m"],
        record["position_error_p90_m"],
        record["rotation_error_median_deg"],
    )
    sparse_dir = out_dir / "sparse"
    _write_model_atomic(rec, sparse_dir)
    record["sparse_dir"] = str(sparse_dir)
    record["n_sparse_points"] = int(rec.num_points3D())
    return record


def _dense_stage(
    image_dir: Path,
    sparse_dir: Path,
    out_dir: Path,
    settings: ReconstructSettings,
    record: dict,
    ground_truth=None,
    seed: int = 0,
) -> dict:
    """Depth maps and fusion on the aligned model in ``sparse_dir``. Returns the record so far."""
    with stage_time() as clock:
        dense = dense_reconstruct(
            sparse_dir,
            image_dir,
            out_dir,
            settings.dense,
            settings.deterministic,
            ground_truth=ground_truth,
            seed=seed,
        )
    record |= {
        "dense_backend": dense["backend"],
        "dense_time_s": dense["dense_time_s"],
        "dense_cpu_s": clock.cpu_s,
        "n_depth_maps": dense["n_depth_maps"],
        "n_dense_points": dense["n_dense_points"],
        "fusion_n_chunks": dense["fusion_n_chunks"],
        "fusion_max_memory_gb": dense["fusion_max_memory_gb"],
    }
    if dense["dense_path"] is None or dense["n_dense_points"] == 0:
        raise ReconstructionError(f"{image_dir}: dense reconstruction produced no points", {"stage": "dense"})
    record["dense_ply"] = dense["dense_path"]
    if not settings.keep_dense_workspace:
        record["dense_workspace_freed_mb"] = _remove_tree(out_dir / "dense") / 1e6
    log.info(
        "dense: %d points from %d depth maps in %.1f s",
        dense["n_dense_points"],
        dense["n_depth_maps"],
        dense["dense_time_s"],
    )
    return record


def _remove_tree(path: Path) -> int:
    """Delete ``path`` (a folder) and return the bytes its files held."""
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    shutil.rmtree(path)
    log.info("removed %s (%.0f MB)", path, size / 1e6)
    return size


def _write_model_atomic(rec: pycolmap.Reconstruction, sparse_dir: Path) -> None:
    tmp = sparse_dir.with_name(sparse_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rec.write(tmp)
    shutil.rmtree(sparse_dir, ignore_errors=True)
    tmp.rename(sparse_dir)


def _newest_log(out_dir: Path) -> str | None:
    logs = sorted(out_dir.glob("colmap.log.*"), key=lambda p: p.stat().st_mtime)
    return str(logs[-1]) if logs else None


def oracle_flight(
    recon_dir, image_dir, out_dir, settings: ReconstructSettings, seed: int, ground_truth
) -> dict:
    """The matcher's ceiling beside a finished reconstruction: the ``oracle`` back-end's depth maps
    at the registered cameras of ``recon_dir/sparse``, fused by the same fusion into
    ``out_dir/dense.ply`` (``reconstruct.oracle_beside``).

    Returns:
        ``dense_ply``, ``dense_time_s``, ``dense_cpu_s``, ``n_depth_maps``, ``n_dense_points``.
    """
    out_dir = Path(out_dir)
    settings = _typed(settings)
    with stage_time() as clock:
        dense = dense_reconstruct(
            Path(recon_dir) / "sparse",
            image_dir,
            out_dir,
            replace(settings.dense, backend="oracle"),
            settings.deterministic,
            ground_truth=ground_truth,
            seed=seed,
        )
    if not settings.keep_dense_workspace:
        _remove_tree(out_dir / "dense")
    if dense["dense_path"] is None:
        raise ReconstructionError(f"{out_dir}: the oracle produced no depth map", {"stage": "oracle"})
    log.info(
        "oracle: %d points from %d depth maps in %.1f s",
        dense["n_dense_points"],
        dense["n_depth_maps"],
        dense["dense_time_s"],
    )
    return {
        "dense_ply": dense["dense_path"],
        "dense_time_s": dense["dense_time_s"],
        "dense_cpu_s": clock.cpu_s,
        "n_depth_maps": dense["n_depth_maps"],
        "n_dense_points": dense["n_dense_points"],
    }


def proxy_bounds(sparse_dir: Path, margin_m: float) -> Box:
    """Region a proxy is cut to: the registered cameras' box, grown by ``margin_m`` sideways and
    reaching down to the lowest sparse point (the ground) minus the margin.
    """
    rec = pycolmap.Reconstruction(sparse_dir)
    centers = np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()])
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else centers
    lo = np.minimum(centers.min(0), np.percentile(points, 1.0, axis=0))
    hi = centers.max(0)
    return Box(tuple(lo.tolist()), tuple(hi.tolist())).expanded(margin_m, margin_m, margin_m)


def _roi_key(roi: Box | None, roi_margin_m: float | None) -> list | None:
    """The region of interest as it enters the proxy's content key (None when it cuts nothing)."""
    if roi is None or roi_margin_m is None:
        return None
    return [list(roi.lo), list(roi.hi)]


def build_proxy(
    image_dir, cache_dir, settings: ReconstructSettings, seed: int, roi: Box | None = None, sparse_check=None
) -> tuple[trimesh.Trimesh, dict]:
    """Reconstruct the exploratory flight and mesh its dense cloud into the planners' proxy.

    Both steps are cached under ``cache_dir`` (``recon.json``, ``proxy.json`` keyed by content), so
    every planner of a scene shares one proxy. A flight whose registered fraction is below
    ``proxy.min_registered_fraction`` raises: no proxy is built from a partial model.

    Args:
        image_dir: the exploratory flight's images + ``cameras.json``.
        cache_dir: output folder of the reconstruction and the proxy.
        settings: the ``reconstruct`` settings (the exploratory flight runs them with ``proxy.dense``).
        seed: seed of the reconstruction.
        roi: the survey's region of interest (the box the exploratory flight was planned on). With
            ``proxy.roi_margin_m`` set, the proxy is cut to it grown by that margin sideways, so the
            planners do not spend views on the ground the exploratory flight saw around the site.
        sparse_check: as ``reconstruct_flight``'s (a real flight's sanity gate).

    Returns:
        (proxy mesh in world metres, record of the reconstruction + ``proxy_faces``,
        ``proxy_time_s``, ``proxy_path``).
    """
    cache_dir = Path(cache_dir)
    proxy = _typed(settings).proxy
    recon = reconstruct_flight(
        image_dir, cache_dir, settings.for_exploration(), seed, sparse_check=sparse_check
    )
    min_fraction = proxy.min_registered_fraction
    if recon["registered_fraction"] < min_fraction:
        raise ReconstructionError(
            f"{image_dir}: exploratory flight registered {recon['registered_fraction']:.1%} < "
            f"reconstruct.proxy.min_registered_fraction {min_fraction:.0%}; "
            "refusing a proxy from a partial model",
            recon | {"status": "failed", "stage": "proxy"},
        )
    key = hashlib.sha256(
        json.dumps(
            {
                "recon": recon["content_key"],
                "proxy": settings.node["proxy"],
                "roi": _roi_key(roi, proxy.roi_margin_m),
            },
            sort_keys=True,
        ).encode()
    ).hexdigest()
    cached = cached_record(cache_dir, key, PROXY_RECORD_FILE, (PROXY_FILE,))
    if cached is not None:
        log.info("proxy unchanged: reusing %s", cache_dir / PROXY_FILE)
        mesh = trimesh.load(cache_dir / PROXY_FILE, force="mesh", process=False)
        return mesh, recon | cached | {"proxy_cached": True}
    start = time.perf_counter()
    bounds = proxy_bounds(Path(recon["sparse_dir"]), proxy.crop_margin_m)
    if roi is not None and proxy.roi_margin_m is not None:
        site = roi.expanded(proxy.roi_margin_m)
        lo, hi = bounds.lo_array.copy(), bounds.hi_array.copy()
        lo[:2], hi[:2] = np.maximum(lo[:2], site.lo_array[:2]), np.minimum(hi[:2], site.hi_array[:2])
        if np.any(lo >= hi):
            raise ReconstructionError(
                f"the region of interest {roi} does not overlap the exploratory reconstruction {bounds}",
                recon | {"status": "failed", "stage": "proxy"},
            )
        bounds = Box(tuple(lo.tolist()), tuple(hi.tolist()))
    mesh = poisson_proxy(recon["dense_ply"], bounds, proxy, settings.deterministic)
    write_atomic(cache_dir / PROXY_FILE, lambda p: mesh.export(p))
    proxy_record = {
        "status": "ok",
        "proxy_faces": len(mesh.faces),
        "proxy_time_s": time.perf_counter() - start,
        "proxy_path": str(cache_dir / PROXY_FILE),
    }
    write_json_atomic(cache_dir / PROXY_RECORD_FILE, proxy_record | {"content_key": key})
    log.info("proxy: %d faces in %.1f s", len(mesh.faces), proxy_record["proxy_time_s"])
    return mesh, recon | proxy_record | {"proxy_cached": False}
