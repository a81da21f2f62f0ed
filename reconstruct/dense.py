"""Dense reconstruction: depth + normal maps in a standard COLMAP workspace, fused by pycolmap.

Two back-ends write the same workspace (``images/``, ``sparse/``, ``stereo/depth_maps``,
``stereo/normal_maps``), then ``pycolmap.stereo_fusion`` fuses the geometric maps into a point cloud
in the frame of the sparse model (the world frame once it is aligned):

- ``cpu``: OpenCV semi-global matching on rectified pairs of each reference view with its best
  partner views (shared sparse points, triangulation angle, sideways baseline), disparities turned
  into depth along the reference rays, a multi-partner consistency filter, normals from the depth
  gradients;
- ``cuda``: ``pycolmap.patch_match_stereo`` (needs a CUDA build of pycolmap).

The matching itself lives in ``reconstruct.stereo``; this module picks the back-end, runs it on a
workspace and fuses its maps.

Pixel coordinates here are OpenCV's (pixel centres at integers); COLMAP's pinhole parameters are
shifted by half a pixel when the intrinsic matrices are built.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil
import pycolmap
from tqdm import tqdm

from reconstruct import fusion_chunks as fc
from reconstruct.dense_settings import BACKENDS, DenseSettings, FusionSettings
from reconstruct.fusion_chunks import read_visibility
from reconstruct.fusion_rays import best_conditioned_per_voxel, fuse_along_rays, well_conditioned
from reconstruct.fusion_support import supported_points
from reconstruct.oracle import compute_depth_maps_oracle
from reconstruct.stereo.depth_maps import compute_depth_maps_cpu, compute_depth_maps_cuda
from reconstruct.workspace import (
    overlapping_views,
    prepare_workspace,
    read_views,
    select_partners,
    stereo_baselines,
)
from scene.io import write_atomic, write_text_atomic

log = logging.getLogger(__name__)


def select_backend(requested: str) -> str:
    """The depth back-end to run: ``auto`` is the CPU back-end (SGBM), measured the better one here.

    The one CUDA measurement (PatchMatch on a 40-view 640 px tomb workspace, archive/pre_p1/limitations.md)
    was both slower end to end and less accurate than SGBM on 2 CPU cores, so ``auto`` does not pick
    CUDA merely because pycolmap has it; ``cuda`` asks for it. ``oracle`` ray-casts the ground truth
    (``reconstruct.oracle``): the matcher's ceiling, for simulated runs only.
    """
    if requested not in BACKENDS:
        raise ValueError(f"reconstruct.dense.backend must be one of {BACKENDS}, got {requested!r}")
    if requested == "auto":
        return "cpu"
    if requested == "cuda" and not pycolmap.has_cuda:
        raise ValueError(
            "reconstruct.dense.backend=cuda but this pycolmap has no CUDA (install pycolmap-cuda12)"
        )
    return requested


def fusion_options(settings: DenseSettings, deterministic: bool = False) -> pycolmap.StereoFusionOptions:
    """COLMAP's fusion options from the dense settings (``fusion`` and ``max_image_size``, px)."""
    fusion = settings.fusion
    options = pycolmap.StereoFusionOptions()
    options.min_num_pixels = fusion.min_num_pixels
    options.max_reproj_error = fusion.max_reproj_error
    options.max_depth_error = fusion.max_depth_error
    options.max_normal_error = fusion.max_normal_error
    options.max_image_size = settings.max_image_size
    if fusion.check_num_images is not None:  # COLMAP's default (50) unless set
        options.check_num_images = fusion.check_num_images
    if deterministic:
        options.num_threads = 1
    return options


# What COLMAP's fusion holds per view, in bytes per pixel: the RGB image (3), the depth (4), the
# normal (12) and the "already fused" mask (1).
FUSION_BYTES_PER_PX = 20


# ``fusion.max_memory_gb: auto``: fusion's views may hold this share of the memory the machine has
# free when fusion starts. Chunked fusion peaks at about 1.6x its budget (archive/pre_p1/throughput.md),
# so 0.5 keeps the peak near 0.8 of what is free.
AUTO_MEMORY_SHARE = 0.5


def fusion_budget_gb(setting) -> float | None:
    """The fusion memory budget (GB) of ``fusion.max_memory_gb``: a number as given, ``auto`` a share
    of the memory free now (``AUTO_MEMORY_SHARE``), None no budget."""
    if setting is None:
        return None
    if setting == "auto":
        return AUTO_MEMORY_SHARE * psutil.virtual_memory().available / 1e9
    return float(setting)


def fusion_chunk_size(workspace: Path, names, max_memory_gb: float | None) -> int | None:
    """How many views a fusion chunk may hold within ``max_memory_gb`` (GB); None when every view
    of ``names`` fits at once (or there is no budget)."""
    if max_memory_gb is None:
        return None
    views = read_views(workspace)
    view_bytes = [FUSION_BYTES_PER_PX * views[n].width * views[n].height for n in names]
    budget = float(max_memory_gb) * 1e9
    if sum(view_bytes) <= budget:
        return None
    max_views = int(budget // max(view_bytes))
    if max_views < 2:
        raise ValueError(
            f"reconstruct.dense.fusion.max_memory_gb={max_memory_gb:.3g} holds fewer than two views "
            f"({max(view_bytes) / 1e9:.3f} GB each)"
        )
    return max_views


@dataclass(frozen=True)
class FusionReport:
    """How a fusion ran: fused points, chunks (1: every view at once) and the budget (GB, or None)."""

    n_points: int
    n_chunks: int
    max_memory_gb: float | None


def fuse(
    workspace: Path, output_ply: Path, settings: DenseSettings, names, deterministic: bool = False
) -> int:
    """Fuse the workspace's geometric depth/normal maps of ``names`` into ``output_ply``; return the
    number of fused points (``fuse_report`` says how it ran)."""
    return fuse_report(workspace, output_ply, settings, names, deterministic).n_points


def fuse_report(
    workspace: Path, output_ply: Path, settings: DenseSettings, names, deterministic: bool = False
) -> FusionReport:
    """Fuse the workspace's geometric depth/normal maps of ``names`` into ``output_ply``. The PLY
    carries positions, normals and colours (model frame, metres).

    Above the ``fusion.max_memory_gb`` budget (``fusion_budget_gb``) the views are fused in chunks
    (``reconstruct.fusion_chunks``). ``deterministic`` fuses on one thread: COLMAP's fusion threads
    share the "pixel already fused" masks, so which thread claims a pixel first (and so the cloud)
    changed from run to run.
    """
    workspace = Path(workspace)
    names = sorted(names)
    if settings.fusion.method == "rays":
        return FusionReport(_fuse_rays(workspace, output_ply, settings, names), 1, None)
    budget = fusion_budget_gb(settings.fusion.max_memory_gb)
    max_views = fusion_chunk_size(workspace, names, budget)
    if max_views is None:
        n_points = _fuse_views(workspace, output_ply, settings, names, deterministic)
        return FusionReport(_support_filtered(output_ply, settings.fusion, n_points), 1, budget)
    n_points, n_chunks = _fuse_in_chunks(workspace, output_ply, settings, names, max_views, deterministic)
    return FusionReport(n_points, n_chunks, budget)


def _fuse_views(
    workspace: Path, output_ply: Path, settings: DenseSettings, names, deterministic: bool
) -> int:
    """One COLMAP fusion of ``names`` (all held in memory at once) into ``output_ply``."""
    write_text_atomic(workspace / "stereo" / "fusion.cfg", "".join(f"{n}\n" for n in sorted(names)))
    fused = pycolmap.stereo_fusion(
        output_ply,
        workspace,
        workspace_format="COLMAP",
        input_type="geometric",
        options=fusion_options(settings, deterministic),
        output_type="PLY",
    )
    return int(fused.num_points3D()) if hasattr(fused, "num_points3D") else -1


def _fuse_in_chunks(
    workspace: Path,
    output_ply: Path,
    settings: DenseSettings,
    names: list[str],
    max_views: int,
    deterministic: bool,
) -> tuple[int, int]:
    # heavy (open3d): imported on use
    import open3d as o3d

    sparse_dir = workspace / "sparse"
    # COLMAP's fusion walks from a view to its check_num_images most overlapping ones: a chunk
    # holds them for each of its own views.
    per_view = fusion_options(settings, deterministic).check_num_images
    neighbours = fc.top_neighbours(fc.shared_points(sparse_dir, names), per_view)
    chunks = fc.plan_chunks(neighbours, max_views)
    log.info(
        "fusion: %d views in %d chunks of at most %d (own + neighbour views: %s)",
        len(names),
        len(chunks),
        max_views,
        ", ".join(f"{len(c.own)}+{len(c.neighbours)}" for c in chunks),
    )
    workspace_index = {name: i for i, name in enumerate(fc.model_image_names(sparse_dir))}
    chunk_of = np.full(len(workspace_index), -1)
    for c, chunk in enumerate(chunks):
        chunk_of[[workspace_index[names[v]] for v in chunk.own]] = c
    parts: dict[str, list[np.ndarray]] = {"points": [], "normals": [], "colors": [], "support": []}
    chunk_ply = Path(output_ply).with_name(Path(output_ply).name + ".chunk.ply")
    chunk_vis = chunk_ply.with_name(chunk_ply.name + ".vis")
    try:
        for c, chunk in enumerate(tqdm(chunks, desc="fusion", unit="chunk")):
            _fuse_views(workspace, chunk_ply, settings, [names[v] for v in chunk.views], deterministic)
            counts, indices = fc.read_visibility(chunk_vis)
            cloud = o3d.io.read_point_cloud(str(chunk_ply))
            if len(cloud.points) != len(counts) or (chunk_of[indices] < 0).any():
                raise RuntimeError(f"{chunk_vis}: does not match {chunk_ply} and the chunk's views")
            keep = fc.owning_chunk(counts, indices, chunk_of, len(chunks)) == c
            parts["points"].append(np.asarray(cloud.points)[keep])
            parts["normals"].append(np.asarray(cloud.normals)[keep])
            parts["colors"].append(np.asarray(cloud.colors)[keep])
            parts["support"].append(counts[keep])
    finally:
        chunk_ply.unlink(missing_ok=True)
        chunk_vis.unlink(missing_ok=True)
    arrays = {key: np.concatenate(value) for key, value in parts.items()}
    n_points = _write_cloud(output_ply, arrays, _support_kept(arrays, settings.fusion))
    return n_points, len(chunks)


def _fuse_rays(workspace: Path, output_ply: Path, settings: DenseSettings, names: list[str]) -> int:
    """``fusion.method: rays`` (``reconstruct.fusion_rays``): points on the depth maps' rays."""
    fusion = settings.fusion
    views = read_views(workspace)
    partners = select_partners(workspace, views, settings)
    baselines = stereo_baselines(views, partners, settings.partner_weights)
    cloud = fuse_along_rays(workspace, names, views, overlapping_views(workspace), baselines, fusion)
    n_fused = len(cloud["points"])
    cloud = well_conditioned(cloud, fusion.conditioning_cell_m, fusion.conditioning_ratio)
    n_conditioned = len(cloud["points"])
    cloud = best_conditioned_per_voxel(cloud, fusion.ray_voxel_m)
    log.info(
        "fusion along rays: %d points from %d views (%d after the conditioning filter, %d one per voxel)",
        n_fused,
        len(names),
        n_conditioned,
        len(cloud["points"]),
    )
    return _write_cloud(output_ply, cloud, _support_kept(cloud, fusion))


def _support_kept(cloud: Mapping, fusion: FusionSettings) -> np.ndarray | None:
    """The fused points the support filter keeps (``reconstruct.fusion_support``: ``support_share``
    of the best support within ``support_radius_m``, m); None when it is off."""
    share = fusion.support_share
    if share <= 0:
        return None

    keep = supported_points(cloud["points"], cloud["support"], fusion.support_radius_m, share)
    log.info("fusion: the support filter keeps %d of %d points", int(keep.sum()), len(keep))
    return keep


# Open3D's binary PLY row of a fused point: position and normal as doubles, colour as bytes.
PLY_ROW_BYTES = 3 * 8 + 3 * 8 + 3
PLY_HEADER_MAX_BYTES = 4096


def _write_cloud(path: Path, cloud: Mapping, keep: np.ndarray | None) -> int:
    """Write points, normals and colours (``keep`` of them, or all) as a PLY; return the count.

    Raises OSError, leaving no file, when the disk has not the room or the file came out short:
    Open3D reports success on a PLY the full disk cut off, and evaluation then fails on it later.
    """
    # heavy (open3d): imported on use
    import open3d as o3d

    keep = slice(None) if keep is None else keep
    out = o3d.geometry.PointCloud()
    out.points = o3d.utility.Vector3dVector(cloud["points"][keep])
    out.normals = o3d.utility.Vector3dVector(cloud["normals"][keep])
    out.colors = o3d.utility.Vector3dVector(cloud["colors"][keep])
    need = len(out.points) * PLY_ROW_BYTES
    free = shutil.disk_usage(Path(path).parent).free
    if free < need + PLY_HEADER_MAX_BYTES:
        raise OSError(f"{path}: the fused cloud needs {need / 1e9:.2f} GB, the disk has {free / 1e9:.2f} GB")
    written = o3d.io.write_point_cloud(str(path), out)
    size = Path(path).stat().st_size if Path(path).exists() else 0
    if not written or not need <= size <= need + PLY_HEADER_MAX_BYTES:
        Path(path).unlink(missing_ok=True)
        raise OSError(f"{path}: wrote {size} bytes of the fused cloud's {need} and a header (disk full?)")
    return len(out.points)


def _support_filtered(output_ply: Path, fusion: FusionSettings, n_points: int) -> int:
    """Apply the support filter to a one-pass fusion's PLY (and its ``.vis``) in place."""
    if fusion.support_share <= 0 or n_points <= 0:
        return n_points
    # Imported here: the CUDA back-end's machine needs only numpy, OpenCV and pycolmap.
    import open3d as o3d

    counts, _ = read_visibility(Path(str(output_ply) + ".vis"))
    cloud = o3d.io.read_point_cloud(str(output_ply))
    arrays = {
        "points": np.asarray(cloud.points),
        "normals": np.asarray(cloud.normals),
        "colors": np.asarray(cloud.colors),
        "support": counts,
    }
    return _write_cloud(output_ply, arrays, _support_kept(arrays, fusion))


def dense_reconstruct(
    sparse_dir: Path,
    image_dir: Path,
    out_dir: Path,
    settings: DenseSettings,
    deterministic: bool = False,
    ground_truth=None,
    seed: int = 0,
) -> dict:
    """Workspace, depth maps (CPU, CUDA or oracle back-end) and fusion into ``out_dir/dense.ply``.

    Args:
        sparse_dir: the (aligned) sparse model.
        image_dir: the flight's images.
        out_dir: where ``dense/`` (the workspace) and ``dense.ply`` go.
        settings: the ``reconstruct.dense`` settings (``DenseSettings.from_config``).
        deterministic: the same cloud, bit for bit, from the same model and images (see ``fuse``).
        ground_truth: the ground-truth mesh (world metres), for the ``oracle`` back-end only.
        seed: seeds the oracle's noise.

    Returns:
        ``backend``, ``dense_time_s`` (s), ``n_depth_maps``, ``n_dense_points``, ``dense_path``,
        ``fusion_n_chunks``, ``fusion_max_memory_gb`` (the budget fusion ran under, or None).

    Raises:
        TypeError: ``settings`` is not a ``DenseSettings`` (a raw config mapping, say).
        ValueError: the oracle asked for without a ground truth, or CUDA without a CUDA pycolmap.
    """
    if not isinstance(settings, DenseSettings):
        raise TypeError(
            "dense_reconstruct takes a DenseSettings (DenseSettings.from_config(mapping) builds one "
            f"from the reconstruct.dense config), got {type(settings).__name__}"
        )
    backend = select_backend(settings.backend)
    if backend == "oracle" and ground_truth is None:
        raise ValueError(
            "reconstruct.dense.backend=oracle needs the ground truth: only a simulated run has one"
        )
    start = time.perf_counter()
    workspace = prepare_workspace(
        Path(sparse_dir),
        Path(image_dir),
        Path(out_dir) / "dense",
        settings,
        downscale_first=settings.downscale_before_undistorting,
    )
    log.info("dense: %s back-end", backend)
    if backend == "cuda":
        valid = compute_depth_maps_cuda(workspace, settings)
    elif backend == "oracle":
        valid = compute_depth_maps_oracle(workspace, settings, ground_truth, seed)
    else:
        valid = compute_depth_maps_cpu(workspace, settings)
    names = [n for n, count in valid.items() if count > 0]
    output_ply = Path(out_dir) / "dense.ply"
    report = FusionReport(0, 0, None)
    if names:
        report = _fuse_atomic(workspace, output_ply, fusion_config(backend, settings), names, deterministic)
    return {
        "backend": backend,
        "dense_time_s": time.perf_counter() - start,
        "n_depth_maps": len(names),
        "n_dense_points": report.n_points,
        "dense_path": str(output_ply) if names else None,
        "fusion_n_chunks": report.n_chunks,
        "fusion_max_memory_gb": report.max_memory_gb,
    }


def fusion_config(backend: str, settings: DenseSettings) -> DenseSettings:
    """The dense settings ``backend``'s maps are fused with. The oracle's depth comes from no
    matching window, and its noise is the stereo model's alone (``reconstruct.oracle``), so fusion
    weighs it by that model: ``fusion.slant_window_px`` 0."""
    fusion = settings.fusion
    if backend != "oracle" or not fusion.slant_window_px:
        return settings
    return dataclasses.replace(settings, fusion=dataclasses.replace(fusion, slant_window_px=0.0))


def _fuse_atomic(
    workspace: Path, output_ply: Path, settings: DenseSettings, names, deterministic: bool
) -> FusionReport:
    holder = {}

    def writer(tmp: Path) -> None:
        holder["report"] = fuse_report(workspace, tmp, settings, names, deterministic)
        # pycolmap also writes which images saw each point (<ply>.vis, ~70 MB a cell); nothing
        # here reads it, and under the temporary name it would be left behind.
        tmp.with_name(tmp.name + ".vis").unlink(missing_ok=True)

    write_atomic(output_ply, writer)
    return holder["report"]
