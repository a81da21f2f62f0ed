"""``cameras.json``: the one file that says which images a flight has and where each was taken.

The renderer writes it beside its PNGs (last, so a folder without it is an incomplete render), the
photo importer beside a real flight's JPEGs; the reconstruction, the evaluation and the study tools
read it. This module is its one writer and its one reader::

    {"scene": NAME, "intrinsics": {"width", "height", "hfov_deg", "focal_px", "cx", "cy"},
     "backend": "egl" | "osmesa", "render_time_s": S, "build_time_s": S, "images_per_s": R,
     "images": [{"name": "000000.png", "viewpoint": [x, y, z, yaw_deg, pitch_deg], "kind": K,
                 "cam_from_world": {"rotation": 3x3, "translation": 3}}, ...]}

``cam_from_world`` is COLMAP's (``x_cam = R @ x_world + t``, OpenCV camera axes, metres), pixels
follow COLMAP's convention (the centre of the top-left pixel is (0.5, 0.5)). Keys other than
``intrinsics`` and ``images`` describe how the images were made (renderer timings, the photos'
source) and are carried as ``extra``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scene.camera import Intrinsics, cam_from_world, validate_viewpoint_array
from scene.io import write_json_atomic

CAMERAS_FILE = "cameras.json"
DEFAULT_KIND = "view"


class CamerasFileError(ValueError):
    """``cameras.json`` is malformed (the message names the file and what is wrong)."""


@dataclass(frozen=True)
class FlightCameras:
    """The content of a flight folder's ``cameras.json``.

    Attributes:
        names: image file names (relative to the folder), in flight order.
        viewpoints: (V, 5) ``x, y, z`` (m), ``yaw_deg, pitch_deg`` of each image.
        intrinsics: the camera (pinhole, square pixels).
        kinds: V viewpoint labels (``detail``, ``coverage``, ``view``, ...).
        rotations: (V, 3, 3) ``cam_from_world`` rotations as written.
        translations: (V, 3) ``cam_from_world`` translations (m) as written.
        intrinsics_record: the file's ``intrinsics`` mapping as written (``focal_px`` included).
        extra: every other top-level key (``scene``, ``backend``, renderer timings, ...).
    """

    names: tuple[str, ...]
    viewpoints: np.ndarray
    intrinsics: Intrinsics
    kinds: tuple[str, ...]
    rotations: np.ndarray
    translations: np.ndarray
    intrinsics_record: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def backend(self) -> str:
        """The OpenGL back-end that rendered the images ('' for photos)."""
        return str(self.extra.get("backend", ""))

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self):
        # Unpacks as (names, viewpoints, intrinsics, kinds).
        return iter((self.names, self.viewpoints, self.intrinsics, self.kinds))


def write_cameras(
    image_dir: str | Path,
    names: Sequence[str],
    viewpoints,
    intrinsics: Intrinsics,
    kinds: Sequence[str],
    header: Mapping | None = None,
) -> Path:
    """Write ``image_dir/cameras.json`` atomically; returns its path.

    Args:
        image_dir: the flight's folder (the images must already be in it).
        names: V image file names in flight order.
        viewpoints: (V, 5) viewpoints (m, degrees); ``cam_from_world`` is derived from them.
        intrinsics: the camera.
        kinds: V labels.
        header: keys written before ``intrinsics`` (``scene``) and after it (``backend``, timings):
            ``scene`` first, the rest in their order, then ``images``.
    """
    vps = validate_viewpoint_array(viewpoints) if len(names) else np.zeros((0, 5))
    if not (len(names) == len(vps) == len(kinds)):
        raise ValueError(f"cameras.json: {len(names)} names, {len(vps)} viewpoints, {len(kinds)} kinds")
    header = dict(header or {})
    rotations, translations = cam_from_world(vps) if len(vps) else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
    record: dict = {}
    if "scene" in header:
        record["scene"] = header.pop("scene")
    record["intrinsics"] = intrinsics.as_dict()
    record.update(header)
    record["images"] = [
        {
            "name": name,
            "viewpoint": row.tolist(),
            "kind": kind,
            "cam_from_world": {"rotation": rot.tolist(), "translation": t.tolist()},
        }
        for name, row, kind, rot, t in zip(names, vps, kinds, rotations, translations, strict=True)
    ]
    return write_json_atomic(Path(image_dir) / CAMERAS_FILE, record)


def read_cameras(image_dir: str | Path) -> FlightCameras:
    """Read ``image_dir/cameras.json``.

    Raises:
        FileNotFoundError: no ``cameras.json`` (the folder is missing or its render incomplete).
        CamerasFileError: the file is malformed, or its ``focal_px`` disagrees with ``hfov_deg``, or
            it lists an image twice (named in the message).
    """
    path = Path(image_dir) / CAMERAS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (the render is incomplete or never ran)")
    try:
        record = json.loads(path.read_text())
        intr = record["intrinsics"]
        intrinsics = Intrinsics(int(intr["width"]), int(intr["height"]), float(intr["hfov_deg"]))
        images = record["images"]
        names = tuple(str(im["name"]) for im in images)
        viewpoints = np.array([im["viewpoint"] for im in images], dtype=float).reshape(len(images), 5)
        kinds = tuple(str(im.get("kind", DEFAULT_KIND)) for im in images)
        rotations = np.array([im["cam_from_world"]["rotation"] for im in images], dtype=float)
        translations = np.array([im["cam_from_world"]["translation"] for im in images], dtype=float)
        if len(names):
            validate_viewpoint_array(viewpoints)
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
        raise CamerasFileError(f"{path}: malformed ({type(err).__name__}: {err})") from err
    n = len(names)
    if n == 0:
        rotations, translations = np.zeros((0, 3, 3)), np.zeros((0, 3))
    if rotations.shape != (n, 3, 3) or translations.shape != (n, 3):
        raise CamerasFileError(f"{path}: cam_from_world must be 3x3 rotations and 3-vectors")
    if "focal_px" in intr and not math.isclose(float(intr["focal_px"]), intrinsics.focal_px, rel_tol=1e-6):
        raise CamerasFileError(
            f"{path}: focal_px {intr['focal_px']} disagrees with hfov_deg {intrinsics.hfov_deg} "
            f"(expected {intrinsics.focal_px:.6f})"
        )
    if len(set(names)) != n:
        raise CamerasFileError(f"{path}: duplicate image names")
    extra = {k: v for k, v in record.items() if k not in ("intrinsics", "images")}
    return FlightCameras(names, viewpoints, intrinsics, kinds, rotations, translations, dict(intr), extra)
