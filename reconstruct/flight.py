"""A rendered flight as the reconstruction sees it: images, the known camera, simulated GNSS.

The flight's images and poses come from ``IMAGE_DIR/cameras.json`` (``scene.cameras_file``). The
true poses are used only to simulate GNSS positions and to score the recovered poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reconstruct.errors import ReconstructionError
from scene.camera import Intrinsics
from scene.cameras_file import CAMERAS_FILE, CamerasFileError, read_cameras


@dataclass(frozen=True)
class Flight:
    """The images of one flight and their true poses.

    Attributes:
        image_dir: folder of the images and ``cameras.json``.
        intrinsics: the (known) survey camera.
        names: image file names (relative to ``image_dir``), in flight order.
        rotations: (N, 3, 3) true ``cam_from_world`` rotations.
        translations: (N, 3) true ``cam_from_world`` translations in metres.
        kinds: N viewpoint labels.
        gnss_measured: the positions are a real flight's GNSS fixes (``cameras.json`` says
            ``"positions": "measured"``): they are the priors as they are, nothing is simulated.
        colmap_camera: a real camera's COLMAP model and parameters (``cameras.json``'s
            ``colmap_camera``: ``model``, ``params``), or None: the PINHOLE of ``intrinsics``.
    """

    image_dir: Path
    intrinsics: Intrinsics
    names: tuple[str, ...]
    rotations: np.ndarray
    translations: np.ndarray
    kinds: tuple[str, ...]
    gnss_measured: bool = False
    colmap_camera: dict | None = None

    @property
    def positions(self) -> np.ndarray:
        """True camera centres (N, 3) in world metres."""
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)

    def __len__(self) -> int:
        return len(self.names)


def read_flight(image_dir: str | Path) -> Flight:
    """Read ``image_dir/cameras.json``; raise ReconstructionError naming the file on bad content."""
    image_dir = Path(image_dir)
    path = image_dir / CAMERAS_FILE
    if not path.is_file():
        raise ReconstructionError(
            f"{path}: missing (the renderer writes it beside the images)", {"stage": "input"}
        )
    try:
        cameras = read_cameras(image_dir)
    except CamerasFileError as exc:
        raise ReconstructionError(str(exc), {"stage": "input"}) from exc
    missing = [name for name in cameras.names if not (image_dir / name).is_file()]
    if missing:
        raise ReconstructionError(
            f"{image_dir}: {len(missing)} image(s) listed in {CAMERAS_FILE} are missing, e.g. {missing[0]}",
            {"stage": "input", "n_images": len(cameras)},
        )
    return Flight(
        image_dir,
        cameras.intrinsics,
        cameras.names,
        cameras.rotations,
        cameras.translations,
        cameras.kinds,
        gnss_measured=cameras.extra.get("positions") == "measured",
        colmap_camera=cameras.extra.get("colmap_camera"),
    )


def simulate_gnss(positions: np.ndarray, sigma_m: float, seed: int) -> np.ndarray:
    """GNSS-like camera positions (N, 3): true positions (m) + isotropic Gaussian noise of ``sigma_m``."""
    sigma_m = float(sigma_m)
    if not (sigma_m >= 0.0 and math.isfinite(sigma_m)):
        raise ValueError(f"reconstruct.gnss.sigma_m must be a finite value >= 0, got {sigma_m}")
    rng = np.random.default_rng(seed)
    positions = np.asarray(positions, dtype=float)
    return positions + rng.normal(0.0, sigma_m, size=positions.shape)
