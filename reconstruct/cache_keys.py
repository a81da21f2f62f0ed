"""The reconstruction stage's cache keys: which settings reach a flight's sparse model, dense cloud
and proxy (each key the settings *in effect*: a setting at its former default keys as before), the
content key of a rendered flight, and the check that a kept record still answers it.

``reconstruct.pipeline`` wraps its stages with these; nothing here runs a stage.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path

import pycolmap

from reconstruct.dense import FUSION_BYTES_PER_PX, fusion_budget_gb
from reconstruct.dense_settings import OPENCV_P1_PER_BLOCK_PIXEL, OPENCV_P2_PER_BLOCK_PIXEL
from reconstruct.flight import CAMERAS_FILE, Flight
from reconstruct.rectify import DEFAULT_MAX_AREA_RATIO
from reconstruct.sfm_settings import COLMAP_ABS_POSE, COLMAP_GLOBAL_BA_MAX_REFINEMENTS, COLMAP_LOCAL_BA
from scene.config import plain

FLIGHT_CONFIG_KEYS = (
    "min_images",
    "min_registered_fraction",
    "gnss",
    "sfm",
    "align",
    "dense",
    "deterministic",
)
# Settings that change no result (only what is kept on disk): left out of every cache key.
OUTPUT_ONLY_KEYS = ("keep_dense_workspace", "oracle_beside")
# sfm.mapping settings only the global mapper reads.
GLOBAL_ONLY_MAPPING_KEYS = ("global_prior_ba", "global_prior_ba_max_iterations")
# sfm.mapping settings that enter a flight's key only away from COLMAP's value (added after records).
COLMAP_VALUED_MAPPING_KEYS = {
    "global_ba_max_refinements": COLMAP_GLOBAL_BA_MAX_REFINEMENTS,
    **COLMAP_LOCAL_BA,
    **COLMAP_ABS_POSE,
}
# dense.fusion's memory budget changes a cloud only for a flight whose fusion would exceed it.
FUSION_BUDGET_KEY = "max_memory_gb"
# dense: depth maps for a cover of the views only; at null (every view) it leaves the keys alone.
REFERENCE_VIEWS_KEYS = ("reference_views_per_point", "reference_min_new_points")
# dense.fusion: the ray fusion's settings (with its method) and the support filter's.
RAY_FUSION_KEYS = ("method", "ray_neighbours", "ray_voxel_m", "conditioning_ratio", "conditioning_cell_m")
CONDITIONING_KEYS = ("conditioning_ratio", "conditioning_cell_m")
SUPPORT_FILTER_KEYS = ("support_share", "support_radius_m")


def _without(section: dict, keys, drop: bool) -> dict:
    return {k: v for k, v in section.items() if k not in keys} if drop else section


# The proxy's own fusion keeps COLMAP's normal tolerance: spelled out when the scored flights' moved
# to 30 deg, it fuses as every proxy did before, so it leaves their keys alone.
PROXY_FORMER_NORMAL_ERROR_DEG = 10.0


def _proxy_in_effect(proxy: dict) -> dict:
    dense = proxy.get("dense")
    if not isinstance(dense, dict):
        return proxy
    fusion = dense.get("fusion")
    if isinstance(fusion, dict):
        former = fusion.get("max_normal_error") == PROXY_FORMER_NORMAL_ERROR_DEG
        dense = {**dense, "fusion": _without(fusion, ("max_normal_error",), former)}
    sgbm = dense.get("sgbm")
    if isinstance(sgbm, dict):
        # Spelled out when the scored flights' matcher moved on: the proxy's matches as before.
        sgbm = _without(sgbm, ("crop_to_overlap",), not sgbm.get("crop_to_overlap"))
        former_p1 = sgbm.get("p1_per_block_pixel", OPENCV_P1_PER_BLOCK_PIXEL) == OPENCV_P1_PER_BLOCK_PIXEL
        dense = {**dense, "sgbm": _without(sgbm, ("p1_per_block_pixel",), former_p1)}
    return {**proxy, "dense": dense}


def _in_effect(section: str, value, fusion_bytes: float = 0.0):
    if section == "proxy" and isinstance(value, dict):
        return _proxy_in_effect(value)
    # The other mapper's settings cannot change a model: a new global-only setting must not move
    # the cache keys of incremental runs (their proxies stay valid). Nor can a fusion memory budget
    # the flight's fusion (``fusion_bytes``, bytes) stays within.
    if section == "dense" and isinstance(value, dict) and isinstance(value.get("fusion"), dict):
        fusion = value["fusion"]
        budget = fusion_budget_gb(fusion.get(FUSION_BUDGET_KEY))
        binds = budget is not None and fusion_bytes > budget * 1e9
        # Settings added after records: where they are off they act as before they existed, so
        # they leave the keys alone.
        fusion = _without(fusion, (FUSION_BUDGET_KEY,), not binds)
        fusion = _without(fusion, RAY_FUSION_KEYS, fusion.get("method", "colmap") == "colmap")
        fusion = _without(fusion, SUPPORT_FILTER_KEYS, not fusion.get("support_share"))
        fusion = _without(fusion, CONDITIONING_KEYS, not fusion.get("conditioning_ratio"))
        fusion = _without(fusion, ("slant_window_px",), not fusion.get("slant_window_px"))
        fusion = _without(fusion, ("gate_disparity_px",), not fusion.get("gate_disparity_px"))
        value = _without(value, REFERENCE_VIEWS_KEYS, value.get(REFERENCE_VIEWS_KEYS[0]) is None)
        # The oracle's noise moves no other back-end's cloud.
        value = _without(value, ("oracle",), value.get("backend") != "oracle")
        value = _without(value, ("edge_margin_px",), not value.get("edge_margin_px"))
        value = _without(value, ("partner_weights",), value.get("partner_weights", "equal") == "equal")
        rectify_keys = ("partners_must_rectify", "max_rectified_area_ratio")
        ratio = value.get("max_rectified_area_ratio", DEFAULT_MAX_AREA_RATIO)
        rectify_off = not value.get("partners_must_rectify") and ratio == DEFAULT_MAX_AREA_RATIO
        value = _without(value, rectify_keys, rectify_off)
        gc_off = not (value.get("geometric_consistency") or {}).get("min_views")
        value = _without(value, ("geometric_consistency",), gc_off)
        sgbm = value.get("sgbm")
        if isinstance(sgbm, dict):
            sgbm = _without(sgbm, ("mirror_pass",), not sgbm.get("mirror_pass"))
            sgbm = _without(sgbm, ("crop_to_overlap",), not sgbm.get("crop_to_overlap"))
            # OpenCV's own P1 and P2 (8 and 32 x block_size^2) match as before the settings existed.
            for key, opencv in (
                ("p1_per_block_pixel", OPENCV_P1_PER_BLOCK_PIXEL),
                ("p2_per_block_pixel", OPENCV_P2_PER_BLOCK_PIXEL),
            ):
                sgbm = _without(sgbm, (key,), sgbm.get(key, opencv) == opencv)
            value = {**value, "sgbm": sgbm}
        return {**value, "fusion": fusion}
    if section != "sfm" or not isinstance(value, dict) or not isinstance(value.get("mapping"), dict):
        return value
    matching = value.get("matching")
    if isinstance(matching, dict) and not (matching.get("prior_check") or {}).get("enabled", False):
        # Added after records: off, it matches as before it existed.
        value = {**value, "matching": {k: v for k, v in matching.items() if k != "prior_check"}}
    mapping = value["mapping"]
    unused = GLOBAL_ONLY_MAPPING_KEYS if mapping.get("method") != "global" else ()
    # A setting added later at COLMAP's own value maps as before it existed: keys stay.
    unused += tuple(k for k, colmap in COLMAP_VALUED_MAPPING_KEYS.items() if mapping.get(k) == colmap)
    return {**value, "mapping": {k: v for k, v in mapping.items() if k not in unused}}


def proxy_settings(node: Mapping) -> dict:
    """The ``reconstruct`` settings a proxy depends on (all but ``OUTPUT_ONLY_KEYS`` and the other
    mapper's settings), for cache keys; ``node`` as plain values (``ReconstructSettings.node``)."""
    return {key: _in_effect(key, value) for key, value in node.items() if key not in OUTPUT_ONLY_KEYS}


def flight_fusion_bytes(n_images: int, intrinsics: Mapping, dense_cfg: Mapping) -> float:
    """What fusing every image of a flight would hold in memory (bytes), at the dense image size."""
    width, height = int(intrinsics["width"]), int(intrinsics["height"])
    shrink = min(1.0, int(dense_cfg["max_image_size"]) / max(width, height))
    pixels = n_images * round(width * shrink) * round(height * shrink)
    return pixels * FUSION_BYTES_PER_PX


def flight_content_key(image_dir: Path, flight: Flight, cfg: Mapping, seed: int) -> str:
    """SHA-256 of the image bytes, the cameras, the relevant config, the seed, pycolmap's version.

    Of ``cameras.json`` only what the reconstruction reads (intrinsics and per-image poses) counts:
    the renderer's timings in it differ on every render of the same flight.
    """
    digest = hashlib.sha256()
    cameras = json.loads((Path(image_dir) / CAMERAS_FILE).read_text())
    fusion_bytes = flight_fusion_bytes(len(flight.names), cameras["intrinsics"], cfg["dense"])
    config = {key: _in_effect(key, plain(cfg[key]), fusion_bytes) for key in FLIGHT_CONFIG_KEYS}
    header = {
        "config": config,
        "seed": int(seed),
        "pycolmap": pycolmap.__version__,
        "cameras": {key: cameras.get(key) for key in ("intrinsics", "images")},
    }
    digest.update(json.dumps(header, sort_keys=True).encode())
    for name in flight.names:
        digest.update(name.encode() + b"\0")
        digest.update((Path(image_dir) / name).read_bytes())
    return digest.hexdigest()


def cached_record(out_dir: Path, key: str, record_file: str, outputs) -> dict | None:
    path = out_dir / record_file
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError:
        return None
    if record.get("content_key") != key or record.get("status") != "ok":
        return None
    if not all((out_dir / name).exists() for name in outputs):
        return None
    return record
