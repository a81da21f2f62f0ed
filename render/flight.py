"""Render a flight (a list of viewpoints) to PNGs plus ``cameras.json``, and read such a folder back.

``OUT_DIR/cameras.json`` is written last, so a folder without it is an incomplete render::

    {"scene": NAME, "intrinsics": {"width", "height", "hfov_deg", "focal_px", "cx", "cy"},
     "backend": "egl" | "osmesa", "render_time_s": S, "build_time_s": S, "images_per_s": R,
     "images": [{"name": "000000.png", "viewpoint": [x, y, z, yaw_deg, pitch_deg], "kind": K,
                 "cam_from_world": {"rotation": 3x3, "translation": 3}}, ...]}

``cam_from_world`` is COLMAP's (``x_cam = R @ x_world + t``, OpenCV camera axes), pixels follow
COLMAP's convention (the centre of the top-left pixel is (0.5, 0.5)).
"""

from __future__ import annotations

import json
import re
import time
from collections import deque
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scene.base import Scene
from scene.camera import Intrinsics, cam_from_world, validate_viewpoint_array
from scene.io import write_atomic, write_json_atomic

CAMERAS_FILE = "cameras.json"
DEFAULT_KIND = "view"
_IMAGE_NAME = re.compile(r"^\d{6}\.png$")


@dataclass(frozen=True)
class RenderResult:
    """What ``render_flight`` wrote.

    Attributes:
        image_dir: the output folder.
        names: image file names in flight order.
        backend: the OpenGL back-end used (``egl`` or ``osmesa``).
        render_time_s: seconds from the first render to the last PNG on disk.
        build_time_s: seconds to build the MuJoCo model and context.
        render_cpu_s: CPU seconds of this process (all threads) over the same span as
            ``render_time_s``; on a shared machine a steadier cost figure than wall time.
    """

    image_dir: Path
    names: tuple[str, ...]
    backend: str
    render_time_s: float
    build_time_s: float
    render_cpu_s: float = float("nan")

    @property
    def images_per_s(self) -> float:
        return len(self.names) / self.render_time_s if self.render_time_s > 0 else float("nan")


def image_name(index: int) -> str:
    """File name of the ``index``-th image of a flight (``000000.png``, ...)."""
    return f"{index:06d}.png"


def _validated_kinds(kinds: Sequence[str] | None, n: int) -> list[str]:
    if kinds is None:
        return [DEFAULT_KIND] * n
    kinds = [str(k) for k in kinds]
    if len(kinds) != n:
        raise ValueError(f"got {len(kinds)} kinds for {n} viewpoints")
    return kinds


def _write_png(path: Path, rgb: np.ndarray, compression: int) -> None:
    import cv2

    # One fixed filter (SUB) and run-length matching halve the encoding CPU of libpng's adaptive
    # filters (26 vs 55 ms for a 1024 x 768 render) for files within 2 % of the same size.
    params = [
        cv2.IMWRITE_PNG_COMPRESSION,
        compression,
        cv2.IMWRITE_PNG_FILTER,
        cv2.IMWRITE_PNG_FILTER_SUB,
        cv2.IMWRITE_PNG_STRATEGY,
        cv2.IMWRITE_PNG_STRATEGY_RLE,
    ]

    def writer(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), rgb[:, :, ::-1], params):
            raise OSError(f"could not write {path}")

    write_atomic(path, writer)


def render_flight(
    scene: Scene,
    viewpoints,
    intrinsics: Intrinsics,
    out_dir: str | Path,
    cfg: Mapping,
    kinds: Sequence[str] | None = None,
) -> RenderResult:
    """Render every viewpoint of a flight to ``out_dir/000000.png ...`` and write ``cameras.json``.

    Args:
        scene: the ground-truth scene.
        viewpoints: (V, 5) array ``x, y, z`` (m), ``yaw_deg, pitch_deg``, in flight order.
        intrinsics: the survey camera.
        out_dir: output folder (created; earlier images and ``cameras.json`` there are replaced).
        cfg: the ``render`` config.
        kinds: optional V labels (``detail``, ``coverage``, ...); ``view`` when omitted.

    Returns:
        The ``RenderResult``; timings in seconds.

    Raises:
        ValueError: a viewpoint is not 5 finite numbers (named by index, nothing written), or the
            kinds do not match the viewpoints.
        BackendError: no off-screen OpenGL back-end works.
    """
    from render.backend import select_backend
    from render.renderer import SceneRenderer

    vps = validate_viewpoint_array(viewpoints)
    kinds = _validated_kinds(kinds, len(vps))
    compression = int(cfg.get("png_compression", 1))
    if not 0 <= compression <= 9:
        raise ValueError(f"render.png_compression must lie in [0, 9], got {compression}")
    threads = max(1, int(cfg.get("writer_threads", 2)))
    # Before anything is written: a machine without a working back-end leaves the folder alone.
    select_backend(cfg.get("backend", "auto"))

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # The record goes first so that the folder reads as incomplete until the last image is written.
    (out_dir / CAMERAS_FILE).unlink(missing_ok=True)
    names = [image_name(i) for i in range(len(vps))]
    for stale in out_dir.iterdir():
        if _IMAGE_NAME.match(stale.name) and stale.name not in set(names):
            stale.unlink()

    build_start = time.perf_counter()
    with SceneRenderer(scene, intrinsics, cfg) as renderer:
        build_time_s = time.perf_counter() - build_start
        start, cpu_start = time.perf_counter(), time.process_time()
        pending: deque = deque()
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for name, row in tqdm(zip(names, vps, strict=True), total=len(vps), desc="render", unit="img"):
                rgb = renderer.render(row)
                pending.append(pool.submit(_write_png, out_dir / name, rgb, compression))
                # Bound the images held in memory while the writers catch up.
                while len(pending) > 2 * threads:
                    pending.popleft().result()
            for future in pending:
                future.result()
        render_time_s = time.perf_counter() - start
        render_cpu_s = time.process_time() - cpu_start
        backend = renderer.backend

    rotations, translations = cam_from_world(vps)
    record = {
        "scene": scene.name,
        "intrinsics": intrinsics.as_dict(),
        "backend": backend,
        "render_time_s": render_time_s,
        "build_time_s": build_time_s,
        "images_per_s": len(vps) / render_time_s if render_time_s > 0 else None,
        "images": [
            {
                "name": name,
                "viewpoint": row.tolist(),
                "kind": kind,
                "cam_from_world": {"rotation": rot.tolist(), "translation": t.tolist()},
            }
            for name, row, kind, rot, t in zip(names, vps, kinds, rotations, translations, strict=True)
        ],
    }
    write_json_atomic(out_dir / CAMERAS_FILE, record)
    return RenderResult(out_dir, tuple(names), backend, render_time_s, build_time_s, render_cpu_s)


@dataclass(frozen=True)
class CameraRecord:
    """The content of a rendered folder's ``cameras.json``."""

    names: tuple[str, ...]
    viewpoints: np.ndarray  # (V, 5)
    intrinsics: Intrinsics
    kinds: tuple[str, ...]
    backend: str

    def __iter__(self):
        # Unpacks as (names, viewpoints, intrinsics, kinds).
        return iter((self.names, self.viewpoints, self.intrinsics, self.kinds))


def read_cameras(image_dir: str | Path) -> CameraRecord:
    """Read ``image_dir/cameras.json``: names, (V, 5) viewpoints, intrinsics, kinds (and back-end).

    Raises:
        FileNotFoundError: no ``cameras.json`` (the folder is missing or its render incomplete).
        ValueError: the file is malformed (named in the message).
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
        backend = str(record.get("backend", ""))
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: malformed ({type(err).__name__}: {err})") from err
    return CameraRecord(
        names, validate_viewpoint_array(viewpoints) if len(names) else viewpoints, intrinsics, kinds, backend
    )
