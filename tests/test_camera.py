"""Round trips and projections of the camera module."""

import numpy as np
import pytest

from scene.camera import (
    _MJCAM_FROM_CVCAM,
    Intrinsics,
    Viewpoint,
    cam_from_world,
    forward_vectors,
    look_at,
    matrix_from_quat,
    mujoco_camera_pose,
    project_points,
    quat_from_matrix,
    viewpoint_from_cam_from_world,
    world_from_cam_rotation,
)

POSES = [
    Viewpoint(1.0, 2.0, 30.0, 0.0, -90.0),
    Viewpoint(-5.0, 3.0, 12.0, 37.0, -45.0),
    Viewpoint(0.0, -20.0, 5.0, 90.0, 0.0),
    Viewpoint(10.0, 10.0, 8.0, -135.0, 20.0),
    Viewpoint(3.0, 4.0, 2.0, 179.0, -10.0),
]


def viewpoint_from_mujoco_camera(pos, quat, roll_tol_deg: float = 0.5) -> Viewpoint:
    """Inverse of ``mujoco_camera_pose`` (the renderer needs only the forward way)."""
    world_from_mjcam = matrix_from_quat(quat)
    world_from_cvcam = world_from_mjcam @ _MJCAM_FROM_CVCAM
    rot = world_from_cvcam.T
    return viewpoint_from_cam_from_world(rot, -rot @ np.asarray(pos, float), roll_tol_deg)


def test_intrinsics_focal_and_fov():
    cam = Intrinsics(1024, 768, 90.0)
    assert cam.focal_px == pytest.approx(512.0)
    assert cam.vfov_deg == pytest.approx(2 * np.degrees(np.arctan(384 / 512)))
    assert cam.distance_for_gsd(0.01) == pytest.approx(5.12)
    with pytest.raises(ValueError, match="hfov_deg"):
        Intrinsics(10, 10, 180.0)


def test_rotation_is_proper_and_axes_follow_convention():
    rot = world_from_cam_rotation(0.0, 0.0)
    np.testing.assert_allclose(rot[:, 2], [1, 0, 0], atol=1e-12)  # forward +x
    np.testing.assert_allclose(rot[:, 0], [0, -1, 0], atol=1e-12)  # right is -y
    np.testing.assert_allclose(rot[:, 1], [0, 0, -1], atol=1e-12)  # image down is world down
    rots = world_from_cam_rotation(np.linspace(-180, 180, 13), np.linspace(-90, 30, 13))
    for r in rots:
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(forward_vectors(90.0, -90.0), [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("vp", POSES)
def test_colmap_round_trip(vp):
    rot, t = cam_from_world(vp)
    back = viewpoint_from_cam_from_world(rot, t)
    np.testing.assert_allclose(back.as_array(), vp.as_array(), atol=1e-9)
    # the camera centre maps to the origin of the camera frame
    np.testing.assert_allclose(rot @ vp.position + t, 0, atol=1e-9)


@pytest.mark.parametrize("vp", POSES)
def test_mujoco_round_trip(vp):
    pos, quat = mujoco_camera_pose(vp)
    back = viewpoint_from_mujoco_camera(pos, quat)
    np.testing.assert_allclose(back.as_array(), vp.as_array(), atol=1e-9)
    # MuJoCo cameras look along their -z axis
    np.testing.assert_allclose(
        -matrix_from_quat(quat)[:, 2], forward_vectors(vp.yaw_deg, vp.pitch_deg), atol=1e-12
    )


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        np.testing.assert_allclose(quat_from_matrix(matrix_from_quat(q)), q, atol=1e-12)


def test_rolled_pose_is_refused():
    rot, t = cam_from_world(POSES[1])
    roll = np.array([[np.cos(0.1), -np.sin(0.1), 0], [np.sin(0.1), np.cos(0.1), 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="roll"):
        viewpoint_from_cam_from_world(roll @ rot, roll @ t)


def test_look_at_projects_target_to_principal_point():
    cam = Intrinsics(640, 480, 60.0)
    target = np.array([3.0, -2.0, 1.5])
    vp = look_at([20.0, 5.0, 12.0], target)
    pix, depth = project_points(target[None], vp, cam)
    np.testing.assert_allclose(pix[0, 0], [320.0, 240.0], atol=1e-9)
    assert depth[0, 0] == pytest.approx(np.linalg.norm(target - vp.position))


def test_projection_matches_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    cam = Intrinsics(800, 600, 70.0)
    rng = np.random.default_rng(1)
    vp = POSES[1]
    pts = vp.position + 10 * forward_vectors(vp.yaw_deg, vp.pitch_deg) + rng.normal(scale=2.0, size=(20, 3))
    ours, _ = project_points(pts, vp, cam)
    rot, t = cam_from_world(vp)
    rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(rot), t)
    colmap_cam = cam.to_colmap()
    theirs = np.array([colmap_cam.img_from_cam(rigid * p) for p in pts]).reshape(-1, 2)
    np.testing.assert_allclose(ours[0], theirs, atol=1e-6)
    assert isinstance(colmap_cam, pycolmap.Camera)


def test_nan_viewpoint_is_refused():
    with pytest.raises(ValueError, match="non-finite"):
        Viewpoint(0.0, float("nan"), 1.0, 0.0, 0.0)
