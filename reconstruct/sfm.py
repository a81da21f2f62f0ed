"""Structure from motion with pycolmap: SIFT extraction, matching, mapping, GNSS pose priors.

Each stage is a plain function on a COLMAP database; ``sfm_options`` is the one place where the
``reconstruct.sfm`` config becomes pycolmap option objects.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from reconstruct.errors import ReconstructionError
from reconstruct.flight import Flight
from reconstruct.pair_check import PairCheckSettings, logged_attitudes, reject_pairs_against_priors
from reconstruct.sfm_settings import SfmSettings
from reconstruct.timing import stage_time
from scene.io import write_text_atomic

log = logging.getLogger(__name__)

PAIRS_FILE = "pairs.txt"


@dataclass
class SfmOptions:
    """pycolmap option objects for every SfM stage (built by ``sfm_options``)."""

    extraction: pycolmap.FeatureExtractionOptions
    matching: pycolmap.FeatureMatchingOptions
    verification: pycolmap.TwoViewGeometryOptions
    exhaustive: pycolmap.ExhaustivePairingOptions
    spatial: pycolmap.SpatialPairingOptions
    sequential: pycolmap.SequentialPairingOptions
    incremental: pycolmap.IncrementalPipelineOptions
    global_: pycolmap.GlobalPipelineOptions
    global_prior_ba: bool
    prior_ba: pycolmap.BundleAdjustmentOptions
    prior_ba_prior: pycolmap.PosePriorBundleAdjustmentOptions
    matching_method: str
    exhaustive_max_images: int
    mapping_method: str
    pose_prior_max_neighbors: int
    pose_prior_max_distance_m: float
    pose_prior_max_axis_angle_deg: float
    prior_check: PairCheckSettings


@dataclass
class SfmResult:
    """Every model SfM recovered (each in its own arbitrary frame, largest first) and, per stage
    (``extraction``, ``matching``, ``mapping``), its wall and CPU seconds."""

    models: list[pycolmap.Reconstruction]
    matching_method: str
    times_s: dict = field(default_factory=dict)
    cpu_s: dict = field(default_factory=dict)
    n_image_pairs: int = 0
    n_pairs_rejected: int = 0  # verified pairs the prior check dropped (``reconstruct.pair_check``)

    @property
    def reconstruction(self) -> pycolmap.Reconstruction:
        """The model with most registered images."""
        return self.models[0]

    @property
    def n_models(self) -> int:
        return len(self.models)


def sfm_options(settings: SfmSettings, seed: int = 0, deterministic: bool = False) -> SfmOptions:
    """Map the ``reconstruct.sfm`` settings onto pycolmap options (the one place this is done).

    ``deterministic`` runs the mapper (and its bundle adjustments) and the matcher on one thread:
    Ceres' threaded solvers sum in an order that changes from run to run, and the mapper's next-image
    choice follows those last bits; the threaded matcher, loaded by a second process, once gave one
    image's pairs other matches from the same descriptors (tests/test_cache.py, two builders at
    once). Extraction gives the same database on any thread count (image ids fixed by
    ``extract_features``), so it keeps every core.
    """
    if not isinstance(settings, SfmSettings):
        raise TypeError(
            f"sfm_options takes SfmSettings (SfmSettings.from_config), not {type(settings).__name__}"
        )
    ecfg, mcfg, pcfg = settings.extraction, settings.matching, settings.mapping
    threads = settings.num_threads
    mapper_threads = 1 if deterministic else threads
    matching_method, mapping_method = mcfg.method, pcfg.method
    growth = pcfg.global_ba_growth_ratio

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.max_image_size = ecfg.max_image_size
    extraction.sift.max_num_features = ecfg.max_num_features
    extraction.sift.first_octave = ecfg.first_octave

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = mapper_threads
    matching.guided_matching = mcfg.guided_matching
    matching.sift.max_ratio = mcfg.max_ratio

    prior_check = PairCheckSettings.from_config(mcfg.prior_check)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = int(seed)

    exhaustive = pycolmap.ExhaustivePairingOptions()
    spatial = pycolmap.SpatialPairingOptions()
    # Survey flights are 3-D (oblique rings, facades): neighbours by full 3-D distance.
    spatial.ignore_z = False
    spatial.max_num_neighbors = mcfg.spatial_max_num_neighbors
    max_distance = mcfg.spatial_max_distance_m
    spatial.max_distance = max_distance if max_distance > 0 else 1e12
    spatial.num_threads = threads
    sequential = pycolmap.SequentialPairingOptions()
    sequential.overlap = mcfg.sequential_overlap
    sequential.num_threads = threads

    incremental = pycolmap.IncrementalPipelineOptions()
    incremental.num_threads = mapper_threads
    incremental.mapper.num_threads = mapper_threads
    incremental.random_seed = int(seed)
    incremental.min_model_size = pcfg.min_model_size
    incremental.ba_refine_focal_length = pcfg.refine_focal_length
    incremental.ba_refine_principal_point = pcfg.refine_principal_point
    incremental.ba_refine_extra_params = pcfg.refine_extra_params
    incremental.mapper.abs_pose_refine_focal_length = pcfg.refine_focal_length
    incremental.mapper.abs_pose_refine_extra_params = pcfg.refine_extra_params
    incremental.ba_global_frames_ratio = growth
    incremental.ba_global_points_ratio = growth
    incremental.ba_global_max_num_iterations = pcfg.global_ba_max_iterations
    incremental.ba_global_max_refinements = pcfg.global_ba_max_refinements
    incremental.mapper.ba_global_ignore_redundant_points3D = pcfg.global_ba_skip_redundant_points
    incremental.mapper.ba_local_num_images = pcfg.local_ba_num_images
    incremental.ba_local_max_num_iterations = pcfg.local_ba_max_iterations
    incremental.ba_local_max_refinements = pcfg.local_ba_max_refinements
    incremental.mapper.abs_pose_min_num_inliers = pcfg.abs_pose_min_num_inliers
    incremental.mapper.abs_pose_min_inlier_ratio = pcfg.abs_pose_min_inlier_ratio
    incremental.use_prior_position = pcfg.use_prior_position
    incremental.use_robust_loss_on_prior_position = (
        pcfg.use_prior_position and pcfg.robust_loss_on_prior_position
    )

    global_ = pycolmap.GlobalPipelineOptions()
    global_.num_threads = mapper_threads
    global_.mapper.num_threads = mapper_threads
    global_.random_seed = int(seed)
    global_.mapper.random_seed = int(seed)
    global_.mapper.bundle_adjustment.refine_focal_length = pcfg.refine_focal_length
    global_.mapper.bundle_adjustment.refine_principal_point = pcfg.refine_principal_point
    global_.mapper.bundle_adjustment.refine_extra_params = pcfg.refine_extra_params

    # After the global mapper (which has no GNSS term): one bundle adjustment with the priors.
    prior_ba = pycolmap.BundleAdjustmentOptions()
    prior_ba.refine_focal_length = pcfg.refine_focal_length
    prior_ba.refine_principal_point = pcfg.refine_principal_point
    prior_ba.refine_extra_params = pcfg.refine_extra_params
    prior_ba.ceres.solver_options.max_num_iterations = pcfg.global_prior_ba_max_iterations
    prior_ba.ceres.solver_options.num_threads = mapper_threads
    prior_ba_prior = pycolmap.PosePriorBundleAdjustmentOptions()
    prior_ba_prior.alignment_ransac.random_seed = int(seed)
    if pcfg.robust_loss_on_prior_position:
        prior_ba_prior.ceres.prior_position_loss_function_type = pycolmap.LossFunctionType.CAUCHY

    return SfmOptions(
        extraction=extraction,
        matching=matching,
        verification=verification,
        exhaustive=exhaustive,
        spatial=spatial,
        sequential=sequential,
        incremental=incremental,
        global_=global_,
        global_prior_ba=pcfg.global_prior_ba,
        prior_ba=prior_ba,
        prior_ba_prior=prior_ba_prior,
        matching_method=matching_method,
        exhaustive_max_images=mcfg.exhaustive_max_images,
        mapping_method=mapping_method,
        pose_prior_max_neighbors=mcfg.pose_prior_max_neighbors,
        pose_prior_max_distance_m=mcfg.pose_prior_max_distance_m,
        pose_prior_max_axis_angle_deg=mcfg.pose_prior_max_axis_angle_deg,
        prior_check=prior_check,
    )


def extract_features(database_path: Path, flight: Flight, options: SfmOptions) -> dict[str, int]:
    """Import the flight's images with the known camera (the PINHOLE of a rendered flight, or a real
    flight's ``colmap_camera``) and extract SIFT into the database.

    Returns:
        keypoint count per image name.
    """
    intr = flight.intrinsics
    reader = pycolmap.ImageReaderOptions()
    if flight.colmap_camera:
        reader.camera_model = str(flight.colmap_camera["model"])
        reader.camera_params = ",".join(repr(float(v)) for v in flight.colmap_camera["params"])
    else:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(
            repr(float(v)) for v in (intr.focal_px, intr.focal_px, intr.cx, intr.cy)
        )
    # Images enter the database one by one in flight order first: the extractor's worker threads
    # would otherwise insert them as they finish, so image ids (and every tie the mapper breaks by
    # id) changed from run to run. The extractor then fills in the keypoints of the existing rows.
    pycolmap.Database.open(database_path).close()  # import_images needs the file to exist
    pycolmap.import_images(
        database_path,
        flight.image_dir,
        camera_mode=pycolmap.CameraMode.SINGLE,
        image_names=list(flight.names),
        options=reader,
    )
    log.info("extracting SIFT features from %d images", len(flight))
    pycolmap.extract_features(
        database_path,
        flight.image_dir,
        image_names=list(flight.names),
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=options.extraction,
        device=pycolmap.Device.auto,
    )
    with pycolmap.Database.open(database_path) as db:
        return {image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()}


def write_pose_priors(database_path: Path, names, positions: np.ndarray, sigma_m: float) -> int:
    """Write GNSS position priors (metres, Cartesian world frame) for the named images; return the count.

    ``sigma_m`` sets the isotropic position covariance (floored at 1 mm so that it stays invertible).
    """
    position_by_name = {str(n): np.asarray(p, dtype=float) for n, p in zip(names, positions, strict=True)}
    std = max(float(sigma_m), 1e-3)
    count = 0
    with pycolmap.Database.open(database_path) as db:
        db.clear_pose_priors()
        for image in db.read_all_images():
            if image.name not in position_by_name:
                continue
            prior = pycolmap.PosePrior()
            prior.position = position_by_name[image.name]
            prior.position_covariance = np.eye(3) * std**2
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            prior.corr_data_id = image.data_id
            db.write_pose_prior(prior)
            count += 1
    return count


def pose_prior_pairs(
    positions: np.ndarray,
    axes: np.ndarray,
    max_neighbors: int,
    max_distance_m: float,
    max_axis_angle_deg: float,
) -> np.ndarray:
    """Image pairs the survey's priors say can see the same surface, as (P, 2) index pairs i < j.

    Each image pairs with its ``max_neighbors`` nearest images by prior position (metres) among
    those whose optical axes (unit (N, 3), from the gimbal's attitude) differ by at most
    ``max_axis_angle_deg`` and, with ``max_distance_m`` > 0, lie within that distance: spatial
    pairing without the views back to back across a corner or a roof ridge, which share nothing.
    """
    positions, axes = np.asarray(positions, float), np.asarray(axes, float)
    n = len(positions)
    if n < 2:
        return np.zeros((0, 2), int)
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    allowed = axes @ axes.T >= np.cos(np.radians(max_axis_angle_deg))
    if max_distance_m > 0:
        allowed &= distance <= max_distance_m
    np.fill_diagonal(allowed, False)
    ranked = np.where(allowed, distance, np.inf)
    k = min(int(max_neighbors), n - 1)
    nearest = np.argpartition(ranked, k - 1, axis=1)[:, :k]
    rows = np.repeat(np.arange(n), k)
    cols = nearest.ravel()
    keep = np.isfinite(ranked[rows, cols])
    pairs = np.sort(np.stack([rows[keep], cols[keep]], axis=1), axis=1)
    return np.unique(pairs, axis=0)


def match_features(
    database_path: Path, flight: Flight, gnss_positions: np.ndarray, options: SfmOptions
) -> tuple[str, int]:
    """Match features and verify the pairs geometrically; return the pairing method used and the
    number of image pairs matched.

    ``auto`` pairs exhaustively up to ``exhaustive_max_images`` images, then spatially (neighbours
    by GNSS prior position, full 3-D distance). ``pose_prior`` pairs by GNSS position and the
    camera's attitude (``pose_prior_pairs``; a survey drone logs its gimbal's attitude with every
    photo, here the flight's attitude).
    """
    n_images = len(flight)
    method = options.matching_method
    if method == "auto":
        method = "exhaustive" if n_images <= options.exhaustive_max_images else "spatial"
    log.info("matching %d images (%s pairing)", n_images, method)
    common = {
        "matching_options": options.matching,
        "verification_options": options.verification,
        "device": pycolmap.Device.auto,
    }
    if method == "exhaustive":
        pycolmap.match_exhaustive(database_path, pairing_options=options.exhaustive, **common)
    elif method == "spatial":
        pycolmap.match_spatial(database_path, pairing_options=options.spatial, **common)
    elif method == "pose_prior":
        pairs = pose_prior_pairs(
            gnss_positions,
            flight.rotations[:, 2, :],  # optical axis in the world: third row of cam_from_world
            options.pose_prior_max_neighbors,
            options.pose_prior_max_distance_m,
            options.pose_prior_max_axis_angle_deg,
        )
        pairs_file = Path(database_path).with_name(PAIRS_FILE)
        write_text_atomic(pairs_file, "".join(f"{flight.names[i]} {flight.names[j]}\n" for i, j in pairs))
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(database_path, pairing_options=imported, **common)
    else:
        pycolmap.match_sequential(database_path, pairing_options=options.sequential, **common)
    with pycolmap.Database.open(database_path) as db:
        n_pairs = int(db.num_matched_image_pairs())
    return method, n_pairs


def check_pairs(
    database_path: Path, flight: Flight, gnss_positions: np.ndarray, options: SfmOptions, seed: int
) -> int:
    """With ``matching.prior_check`` on, drop the verified pairs that contradict the GNSS positions
    ((N, 3) metres, flight order) and the logged attitudes (``reconstruct.pair_check``); return how
    many were dropped (0 when off)."""
    if not options.prior_check.enabled:
        return 0
    attitudes = logged_attitudes(flight.rotations, options.prior_check.attitude_sigma_deg, seed)
    checked = reject_pairs_against_priors(
        database_path, flight.names, attitudes, gnss_positions, options.prior_check
    )
    return checked["n_pairs_rejected"]


def map_reconstruction(
    database_path: Path, image_dir: Path, options: SfmOptions
) -> list[pycolmap.Reconstruction]:
    """Run the mapper (incremental or global); return every model it found, most registered images
    first. Raise ReconstructionError when no model is found.
    """
    log.info("mapping (%s)", options.mapping_method)
    with tempfile.TemporaryDirectory(prefix="mapper_", dir=Path(database_path).parent) as tmp:
        if options.mapping_method == "incremental":
            models = pycolmap.incremental_mapping(database_path, image_dir, tmp, options=options.incremental)
        else:
            models = pycolmap.global_mapping(database_path, image_dir, tmp, options=options.global_)
            if options.global_prior_ba:
                for model in models.values():
                    prior_bundle_adjustment(model, database_path, options)
    if not models:
        raise ReconstructionError(
            "the mapper found no model (no image pair could be initialised)",
            {"stage": "mapping", "n_registered": 0, "registered_fraction": 0.0},
        )
    # Ties keep the mapper's order (its model index), so the choice does not depend on dict order.
    return [models[k] for k in sorted(models, key=lambda k: (-models[k].num_reg_images(), k))]


def prior_bundle_adjustment(
    reconstruction: pycolmap.Reconstruction, database_path: Path, options: SfmOptions
) -> None:
    """Bundle-adjust ``reconstruction`` in place with the database's GNSS position priors (COLMAP's
    pose-prior bundle adjuster: it aligns the model to the priors, then adds their residuals), as the
    incremental mapper does with ``use_prior_position``. A model with fewer than 3 priors is left as
    it is (the priors cannot fix its frame)."""
    with pycolmap.Database.open(database_path) as db:
        priors = db.read_all_pose_priors()
    data_ids = {image.data_id for image in reconstruction.images.values() if image.has_pose}
    priors = [p for p in priors if p.corr_data_id in data_ids]
    if len(priors) < 3:
        log.info(
            "prior bundle adjustment skipped: %d priors in a model of %d images", len(priors), len(data_ids)
        )
        return
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    adjuster = pycolmap.create_pose_prior_bundle_adjuster(
        options.prior_ba, options.prior_ba_prior, config, priors, reconstruction
    )
    summary = adjuster.solve()
    if not summary.is_solution_usable():
        raise ReconstructionError(
            f"the bundle adjustment with the GNSS priors failed: {summary.brief_report()}",
            {"stage": "mapping"},
        )
    log.info("prior bundle adjustment of %d images: %s", len(data_ids), summary.brief_report())


def run_sfm(
    flight: Flight,
    work_dir: Path,
    gnss_positions: np.ndarray,
    gnss_sigma_m: float,
    settings: SfmSettings,
    seed: int,
    deterministic: bool = False,
) -> SfmResult:
    """Extraction, pose priors, matching and mapping into ``work_dir/database.db``.

    Args:
        flight: the images and the known camera.
        work_dir: output folder; the database is rebuilt from scratch.
        gnss_positions: (N, 3) simulated GNSS positions in metres, one per image of ``flight``.
        gnss_sigma_m: their standard deviation in metres (the prior covariance).
        settings: ``reconstruct.sfm``, typed.
        seed: seed of COLMAP's RANSAC and mapper.
        deterministic: the same model, bit for bit, from the same inputs (see ``sfm_options``).

    Returns:
        Every model (arbitrary frames, largest first) and the wall and CPU seconds of
        ``extraction``, ``matching`` and ``mapping``.
    """
    options = sfm_options(settings, seed, deterministic)
    pycolmap.set_random_seed(int(seed))
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database_path = work_dir / "database.db"
    for stale in (database_path, work_dir / "database.db-wal", work_dir / "database.db-shm"):
        stale.unlink(missing_ok=True)
    times: dict[str, float] = {}
    cpu: dict[str, float] = {}

    with stage_time() as clock:
        keypoints = extract_features(database_path, flight, options)
    times["extraction"], cpu["extraction"] = clock.wall_s, clock.cpu_s
    n_with_features = sum(1 for n in keypoints.values() if n > 0)
    log.info(
        "extraction: %.1f s, %d of %d images have features (median %d keypoints)",
        times["extraction"],
        n_with_features,
        len(flight),
        int(np.median(list(keypoints.values()) or [0])),
    )
    if n_with_features < 2:
        raise ReconstructionError(
            f"{flight.image_dir}: only {n_with_features} of {len(flight)} images have SIFT features",
            {
                "stage": "extraction",
                "n_images": len(flight),
                "n_images_with_features": n_with_features,
                "n_registered": 0,
                "registered_fraction": 0.0,
            },
        )
    write_pose_priors(database_path, flight.names, gnss_positions, gnss_sigma_m)

    with stage_time() as clock:
        method, n_pairs = match_features(database_path, flight, gnss_positions, options)
        n_rejected = check_pairs(database_path, flight, gnss_positions, options, seed)
    times["matching"], cpu["matching"] = clock.wall_s, clock.cpu_s
    log.info("matching: %d pairs in %.1f s (%.1f s CPU)", n_pairs, times["matching"], cpu["matching"])

    with stage_time() as clock:
        models = map_reconstruction(database_path, flight.image_dir, options)
    times["mapping"], cpu["mapping"] = clock.wall_s, clock.cpu_s
    log.info(
        "mapping: %.1f s (%.1f s CPU), %d model(s) of %s images (flight: %d)",
        times["mapping"],
        cpu["mapping"],
        len(models),
        "+".join(str(m.num_reg_images()) for m in models),
        len(flight),
    )
    shutil.rmtree(work_dir / "mapper", ignore_errors=True)
    return SfmResult(models, method, times, cpu, n_pairs, n_rejected)
