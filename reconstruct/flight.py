"""A rendered flight as the reconstruction sees it: images, the known camera, simulated GNSS.

The renderer writes ``IMAGE_DIR/cameras.json``::

    {"intrinsics": {"width", "height", "hfov_deg", "focal_px", "cx", "cy"},
     "images": [{"name", "viewpoint": [x, y, z, yaw_deg, pitch_deg], "kind",
                 "cam_from_world": {"rotation": 3x3, "translation": 3}}, ...], ...}

The true poses are used only to simulate GNSS positions and to score the recovered poses.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reconstruct.errors import ReconstructionError
from scene.camera import Intrinsics

CAMERAS_FILE = "cameras.json"


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
    """

    image_dir: Path
    intrinsics: Intrinsics
    names: tuple[str, ...]
    rotations: np.ndarray
    translations: np.ndarray
    kinds: tuple[str, ...]

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
        record = json.loads(path.read_text())
        intr = record["intrinsics"]
        intrinsics = Intrinsics(int(intr["width"]), int(intr["height"]), float(intr["hfov_deg"]))
        images = record["images"]
        names = tuple(str(im["name"]) for im in images)
        rotations = np.array([im["cam_from_world"]["rotation"] for im in images], dtype=float)
        translations = np.array([im["cam_from_world"]["translation"] for im in images], dtype=float)
        kinds = tuple(str(im.get("kind", "")) for im in images)
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise ReconstructionError(
            f"{path}: malformed ({type(exc).__name__}: {exc})", {"stage": "input"}
        ) from exc
    if "focal_px" in intr and not math.isclose(float(intr["focal_px"]), intrinsics.focal_px, rel_tol=1e-6):
        raise ReconstructionError(
            f"{path}: focal_px {intr['focal_px']} disagrees with hfov_deg {intrinsics.hfov_deg} "
            f"(expected {intrinsics.focal_px:.6f})",
            {"stage": "input"},
        )
    n = len(names)
    if n == 0:
        rotations, translations = np.zeros((0, 3, 3)), np.zeros((0, 3))
    if rotations.shape != (n, 3, 3) or translations.shape != (n, 3):
        raise ReconstructionError(
            f"{path}: cam_from_world must be 3x3 rotations and 3-vectors", {"stage": "input"}
        )
    if len(set(names)) != n:
        raise ReconstructionError(f"{path}: duplicate image names", {"stage": "input"})
    missing = [name for name in names if not (image_dir / name).is_file()]
    if missing:
        raise ReconstructionError(
            f"{image_dir}: {len(missing)} image(s) listed in {CAMERAS_FILE} are missing, e.g. {missing[0]}",
            {"stage": "input", "n_images": n},
        )
    return Flight(image_dir, intrinsics, names, rotations.reshape(n, 3, 3), translations.reshape(n, 3), kinds)


def simulate_gnss(positions: np.ndarray, sigma_m: float, seed: int) -> np.ndarray:
    """GNSS-like camera positions (N, 3): true positions (m) + isotropic Gaussian noise of ``sigma_m``."""
    sigma_m = float(sigma_m)
    if not (sigma_m >= 0.0 and math.isfinite(sigma_m)):
        raise ValueError(f"reconstruct.gnss.sigma_m must be a finite value >= 0, got {sigma_m}")
    rng = np.random.default_rng(seed)
    positions = np.asarray(positions, dtype=float)
    return positions + rng.normal(0.0, sigma_m, size=positions.shape)
