"""The prior check drops a pair matched across repeated bays and keeps the true pairs."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from reconstruct.pair_check import (
    PairCheckSettings,
    logged_attitudes,
    prior_disagreement,
    reject_pairs_against_priors,
)

SETTINGS = PairCheckSettings(True, 2.0, 10.0, 20.0, 1.0)
FOCAL, WIDTH, HEIGHT = 800.0, 1024, 768


def _facing_north(yaw_deg: float = 0.0) -> np.ndarray:
    """cam_from_world of a level camera looking along +y (turned by yaw about z): x right, y down."""
    look = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return look @ Rotation.from_euler("z", -yaw_deg, degrees=True).as_matrix()


def _project(points: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    cam = (points - centre) @ rotation.T
    return FOCAL * cam[:, :2] / cam[:, 2:] + np.array([WIDTH / 2, HEIGHT / 2])


def test_prior_disagreement_measures_rotation_and_direction_in_degrees():
    rotations = np.stack([_facing_north(), _facing_north(12.0)])
    positions = np.array([[0.0, 0, 10], [4.0, 0, 10]])
    true_r = rotations[1] @ rotations[0].T
    true_t = rotations[1] @ (positions[0] - positions[1])
    turned = Rotation.from_euler("x", 15, degrees=True).as_matrix()
    est_r = np.stack([true_r, turned @ true_r])
    # The second estimate's baseline points 30 deg off the true one (in camera 2's frame).
    est_t = np.stack([3.0 * true_t, Rotation.from_euler("y", 30, degrees=True).apply(true_t)])
    rot, direction, baseline = prior_disagreement(
        est_r, est_t, rotations, positions, np.array([[0, 1], [0, 1]])
    )
    np.testing.assert_allclose(rot, [0.0, 15.0], atol=1e-5)
    np.testing.assert_allclose(direction, [0.0, 30.0], atol=1e-5)
    np.testing.assert_allclose(baseline, [4.0, 4.0])


def test_logged_attitudes_are_off_by_the_set_error():
    rotations = np.repeat(_facing_north()[None], 4000, axis=0)
    logged = logged_attitudes(rotations, 2.0, seed=0)
    angle = Rotation.from_matrix(np.einsum("nij,nkj->nik", logged, rotations)).magnitude()
    # The angle of a 3-D isotropic Gaussian rotation vector: RMS sigma * sqrt(3).
    assert np.degrees(np.sqrt(np.mean(angle**2))) == pytest.approx(2.0 * np.sqrt(3), rel=0.05)
    np.testing.assert_array_equal(logged, logged_attitudes(rotations, 2.0, seed=0))


def test_a_pair_matched_across_repeated_bays_is_dropped(tmp_path):
    """A facade 20 m north with bays 6 m apart. Views 0 and 1 (3 m apart) match the same bay; view 2
    (3 m right of and 3 m above view 0) matched view 0's bay against the next one: its keypoints are
    the projections of the points 6 m along, as if it flew 3 m left. RANSAC accepts both pairs; only
    the priors tell them apart (the baselines differ by 90 deg)."""
    rng = np.random.default_rng(3)
    facade = np.column_stack(
        [rng.uniform(-5, 5, 400), 20 + rng.uniform(-1.5, 1.5, 400), rng.uniform(2, 14, 400)]
    )
    rotations = np.stack([_facing_north(), _facing_north(-4.0), _facing_north(4.0)])
    positions = np.array([[0.0, 0, 8], [3.0, 0, 8], [3.0, 0, 11]])
    bay = np.array([6.0, 0, 0])
    seen = [facade, facade, facade + bay]  # what each view's keypoints show of view 0's points
    keypoints = [_project(p, r, c) for p, r, c in zip(seen, rotations, positions, strict=True)]

    camera = pycolmap.Camera(
        model="PINHOLE", width=WIDTH, height=HEIGHT, params=[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2], camera_id=1
    )
    options = pycolmap.TwoViewGeometryOptions()
    options.compute_relative_pose = True
    options.ransac.random_seed = 0
    matches = np.repeat(np.arange(len(facade), dtype=np.uint32)[:, None], 2, axis=1)
    names = ("a.jpg", "b.jpg", "c.jpg")
    database = tmp_path / "database.db"
    with pycolmap.Database.open(database) as db:
        db.write_camera(camera, use_camera_id=True)
        for i, name in enumerate(names):
            db.write_image(pycolmap.Image(name=name, camera_id=1, image_id=i + 1), use_image_id=True)
            db.write_keypoints(i + 1, keypoints[i].astype(np.float32))
        for j in (1, 2):
            geometry = pycolmap.estimate_calibrated_two_view_geometry(
                camera, keypoints[0], camera, keypoints[j], matches, options
            )
            assert geometry.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            assert len(geometry.inlier_matches) > 0.95 * len(facade)  # both pass RANSAC
            db.write_two_view_geometry(1, j + 1, geometry)

    checked = reject_pairs_against_priors(database, names, rotations, positions, SETTINGS)
    assert checked == {"n_pairs_checked": 2, "n_pairs_rejected": 1, "n_pairs_unposed": 0}
    with pycolmap.Database.open(database) as db:
        assert db.exists_two_view_geometry(1, 2)
        assert not db.exists_two_view_geometry(1, 3)


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="prior_check.max_direction_deg"):
        PairCheckSettings.from_config(
            {
                "enabled": True,
                "attitude_sigma_deg": 2,
                "max_rotation_deg": 10,
                "max_direction_deg": 0,
                "min_baseline_m": 1,
            }
        )
    assert not PairCheckSettings.from_config(None).enabled
