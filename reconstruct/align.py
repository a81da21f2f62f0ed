"""Similarity alignment of an SfM model to GNSS positions, and pose errors against the true poses."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from reconstruct.errors import ReconstructionError
from reconstruct.flight import Flight
from reconstruct.settings import AlignSettings

log = logging.getLogger(__name__)


def align_to_gnss(
    reconstruction: pycolmap.Reconstruction,
    names,
    gnss_positions: np.ndarray,
    gnss_sigma_m: float,
    settings: AlignSettings,
    seed: int = 0,
) -> pycolmap.Sim3d:
    """Robustly fit the similarity world_from_model to the GNSS positions and apply it in place.

    LO-RANSAC on camera centres (``pycolmap.align_reconstruction_to_locations``) with an inlier
    threshold of ``max_error_sigmas * gnss_sigma_m`` metres, floored at ``min_error_m``.

    Args:
        reconstruction: the SfM model; transformed in place into the world frame.
        names: image names, one per row of ``gnss_positions``.
        gnss_positions: (N, 3) GNSS camera positions in metres.
        gnss_sigma_m: GNSS noise standard deviation in metres.
        settings: ``reconstruct.align``, typed.
        seed: RANSAC seed.

    Returns:
        The applied ``Sim3d`` (world_from_model).
    """
    position_by_name = {str(n): np.asarray(p, float) for n, p in zip(names, gnss_positions, strict=True)}
    reg_names = [reconstruction.image(i).name for i in reconstruction.reg_image_ids()]
    reg_names = [n for n in reg_names if n in position_by_name]
    min_common = settings.min_common_images
    if len(reg_names) < max(min_common, 3):
        raise ReconstructionError(
            f"only {len(reg_names)} registered images have GNSS positions; "
            f"alignment needs {max(min_common, 3)}",
            {"stage": "align"},
        )
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = max(settings.max_error_sigmas * float(gnss_sigma_m), settings.min_error_m)
    ransac.random_seed = int(seed)
    locations = np.array([position_by_name[n] for n in reg_names])
    world_from_model = pycolmap.align_reconstruction_to_locations(
        reconstruction, reg_names, locations, min_common, ransac
    )
    if world_from_model is None:
        raise ReconstructionError(
            f"similarity alignment to GNSS failed (RANSAC threshold {ransac.max_error:.3f} m)",
            {"stage": "align"},
        )
    # Least squares (Umeyama) over all RANSAC inliers: the robust estimate alone leaves an error of
    # the order of the GNSS noise in the model's rotation, the full fit averages it down.
    centers = np.array([reconstruction.find_image_with_name(n).projection_center() for n in reg_names])
    residual = np.linalg.norm(_apply_sim3d(world_from_model, centers) - locations, axis=1)
    inliers = residual <= ransac.max_error
    refined = pycolmap.estimate_sim3d(centers[inliers], locations[inliers]) if inliers.sum() >= 3 else None
    if refined is not None:
        world_from_model = refined
    reconstruction.transform(world_from_model)
    log.info(
        "aligned to GNSS: scale %.4f, %d/%d inliers within %.3f m",
        world_from_model.scale,
        int(inliers.sum()),
        len(inliers),
        ransac.max_error,
    )
    return world_from_model


def deregister_gnss_outliers(
    reconstruction: pycolmap.Reconstruction, names, gnss_positions: np.ndarray, max_error_m: float
) -> list[str]:
    """De-register the aligned cameras farther than ``max_error_m`` metres from their GNSS position.

    After the similarity alignment, a camera that far from its own GNSS fix was registered at a
    wrong place (repeated texture, a false loop): its depth map would only add outliers. A surveyor
    with RTK positions would drop it the same way. Returns the names of the de-registered images.
    """
    position_by_name = {str(n): np.asarray(p, float) for n, p in zip(names, gnss_positions, strict=True)}
    dropped = []
    for image_id in list(reconstruction.reg_image_ids()):
        image = reconstruction.image(image_id)
        gnss = position_by_name.get(image.name)
        if gnss is not None and np.linalg.norm(image.projection_center() - gnss) > max_error_m:
            dropped.append(image.name)
            reconstruction.deregister_frame(image.frame_id)
    if dropped:
        log.info(
            "de-registered %d cameras farther than %.2f m from their GNSS fix", len(dropped), max_error_m
        )
    return dropped


def merge_model(
    target: pycolmap.Reconstruction, source: pycolmap.Reconstruction, image_ids=None
) -> list[str]:
    """Add the registered images of ``source`` (``image_ids`` of them, default all) that ``target``
    lacks, with their 3-D points, to ``target``; into an empty ``target`` this cuts out a sub-model.

    Both models must already be in the same (world) frame and come from one database (image, frame,
    camera and rig ids agree). A point keeps only its observations in the added images (in at least
    2 of them); images both models hold stay as ``target`` has them. Returns the added images' names.
    """
    wanted = set(source.reg_image_ids()) if image_ids is None else set(image_ids)
    added = []
    for image_id in sorted(wanted):
        if target.exists_image(image_id):
            continue
        image = source.image(image_id)
        source_frame = source.frame(image.frame_id)
        if not target.exists_camera(image.camera_id):
            target.add_camera(source.camera(image.camera_id))
        if not target.exists_rig(source_frame.rig_id):
            target.add_rig(source.rig(source_frame.rig_id))
        frame = pycolmap.Frame()
        frame.frame_id = source_frame.frame_id
        frame.rig_id = source_frame.rig_id
        for data_id in source_frame.data_ids:
            frame.add_data_id(data_id)
        frame.rig_from_world = source_frame.rig_from_world
        target.add_frame(frame)
        copy = pycolmap.Image(
            name=image.name,
            points2D=pycolmap.Point2DList([pycolmap.Point2D(p.xy) for p in image.points2D]),
            camera_id=image.camera_id,
            image_id=image_id,
        )
        copy.frame_id = image.frame_id
        target.add_image(copy)
        target.register_frame(frame.frame_id)
        added.append(image.name)
    added_ids = {target.find_image_with_name(name).image_id for name in added}
    for point in source.points3D.values():
        elements = [e for e in point.track.elements if e.image_id in added_ids]
        if len({e.image_id for e in elements}) < 2:
            continue
        track = pycolmap.Track()
        for element in elements:
            track.add_element(element.image_id, element.point2D_idx)
        target.add_point3D(point.xyz, track, point.color)
    return added


def georeference_models(
    models: list[pycolmap.Reconstruction],
    names,
    gnss_positions: np.ndarray,
    gnss_sigma_m: float,
    settings: AlignSettings,
    seed: int = 0,
) -> tuple[pycolmap.Reconstruction, dict]:
    """Align every model SfM found to its own GNSS positions and merge them into the largest.

    The largest model must align (else ReconstructionError, as before merging existed). Another model
    is merged when it holds at least ``merge_min_images`` registered images, its similarity fit
    succeeds, and that many remain after the GNSS outlier check; otherwise it is dropped and
    reported, never merged on a guess. Cameras farther than ``deregister_error_sigmas`` GNSS sigmas
    (floored at ``min_error_m``) from their fix are de-registered in every model.

    Returns:
        The merged model (world frame) and a report: ``n_models``, ``n_models_merged`` (models that
        added images), ``n_images_merged`` (registered images the merged models added), ``n_images_dropped``
        (images registered only in dropped models), ``model_sizes`` ("215+32"), ``n_gnss_outliers``.
    """
    if not models:
        raise ReconstructionError("no model to georeference", {"stage": "align"})
    max_error = max(settings.deregister_error_sigmas * gnss_sigma_m, settings.min_error_m)
    min_images = max(settings.merge_min_images, settings.min_common_images, 3)
    target = models[0]
    align_to_gnss(target, names, gnss_positions, gnss_sigma_m, settings, seed)
    outliers = deregister_gnss_outliers(target, names, gnss_positions, max_error)
    report = {
        "n_models": len(models),
        "n_models_merged": 0,
        "n_images_merged": 0,
        "n_images_dropped": 0,
        "model_sizes": "+".join(str(m.num_reg_images()) for m in models),
    }
    dropped_names: set[str] = set()
    for index, model in enumerate(models[1:], start=2):
        size = model.num_reg_images()
        model_names = {model.image(i).name for i in model.reg_image_ids()}
        reason = None
        if size < min_images:
            reason = f"{size} images < align.merge_min_images {min_images}"
        else:
            try:
                align_to_gnss(model, names, gnss_positions, gnss_sigma_m, settings, seed)
            except ReconstructionError as exc:
                reason = f"alignment failed ({exc})"
        if reason is None:
            outliers += deregister_gnss_outliers(model, names, gnss_positions, max_error)
            if model.num_reg_images() < min_images:
                reason = f"{model.num_reg_images()} images left after the GNSS check"
        if reason is not None:
            log.info("model %d of %d (%d images) dropped: %s", index, len(models), size, reason)
            dropped_names |= model_names
            continue
        added = merge_model(target, model)
        # A model whose images the target already holds (COLMAP may rebuild a part twice) adds nothing.
        report["n_models_merged"] += bool(added)
        report["n_images_merged"] += len(added)
        log.info("model %d of %d merged: %d images added", index, len(models), len(added))
    registered = {target.image(i).name for i in target.reg_image_ids()}
    report["n_images_dropped"] = len(dropped_names - registered)
    report["n_gnss_outliers"] = len(set(outliers) - registered)
    return target, report


def _apply_sim3d(sim: pycolmap.Sim3d, points: np.ndarray) -> np.ndarray:
    matrix = np.asarray(sim.matrix())
    return points @ matrix[:, :3].T + matrix[:, 3]


def rotation_angles_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """Angles in degrees (N,) of the rotations ``rot_a @ rot_b^T`` for stacks (N, 3, 3)."""
    rel = np.einsum("nij,nkj->nik", rot_a, rot_b)
    cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_errors(reconstruction: pycolmap.Reconstruction, flight: Flight) -> dict:
    """Registered fraction and errors of the registered cameras against the flight's true poses.

    Returns:
        ``n_images``, ``n_registered``, ``registered_fraction``, camera position error in metres
        (``position_error_median_m``, ``_p90_m``, ``_max_m``) and rotation error in degrees
        (``rotation_error_median_deg``, ``_p90_deg``, ``_max_deg``); errors are NaN-free (None when
        nothing registered).
    """
    index = {name: i for i, name in enumerate(flight.names)}
    est_rot, true_idx, est_center = [], [], []
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        if image.name not in index:
            continue
        cam_from_world = image.cam_from_world()
        est_rot.append(cam_from_world.rotation.matrix())
        est_center.append(image.projection_center())
        true_idx.append(index[image.name])
    n_images, n_reg = len(flight), len(true_idx)
    record = {
        "n_images": n_images,
        "n_registered": n_reg,
        "registered_fraction": n_reg / n_images if n_images else 0.0,
    }
    keys = (
        "position_error_median_m",
        "position_error_p90_m",
        "position_error_max_m",
        "rotation_error_median_deg",
        "rotation_error_p90_deg",
        "rotation_error_max_deg",
    )
    if n_reg == 0:
        return record | dict.fromkeys(keys)
    true_idx = np.asarray(true_idx)
    position_err = np.linalg.norm(np.asarray(est_center) - flight.positions[true_idx], axis=1)
    rotation_err = rotation_angles_deg(np.asarray(est_rot), flight.rotations[true_idx])
    values = (
        np.median(position_err),
        np.percentile(position_err, 90),
        position_err.max(),
        np.median(rotation_err),
        np.percentile(rotation_err, 90),
        rotation_err.max(),
    )
    return record | {k: float(v) for k, v in zip(keys, values, strict=True)}
