"""Hand-made COLMAP models for the dense-stage tests: known cameras that all see known points."""

from __future__ import annotations

import numpy as np
import pycolmap


def shared_point_model(names, rotations, translations, points, intr) -> pycolmap.Reconstruction:
    """A model whose cameras (``cam_from_world`` per name) all observe every 3-D point of ``points``
    (the dense stage picks overlapping views by shared points)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(intr.to_colmap())
    for i, (name, rotation, translation) in enumerate(zip(names, rotations, translations, strict=True)):
        cam = np.asarray(points) @ np.asarray(rotation).T + translation
        keypoints = cam[:, :2] / cam[:, 2:] * intr.focal_px + [intr.cx, intr.cy]
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(rotation)), np.asarray(translation))
        )
    for k, xyz in enumerate(points):
        track = pycolmap.Track()
        for i in range(len(names)):
            track.add_element(i + 1, k)
        rec.add_point3D(np.asarray(xyz, float), track)
    return rec
