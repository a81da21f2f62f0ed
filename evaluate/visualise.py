"""Error pictures like the paper's Figure 3: the reconstruction coloured by its distance to the
ground truth, and the ground-truth samples coloured covered / missed, as coloured PLYs and as PNG
views from five fixed viewpoints (four obliques and a nadir around the evaluation region).

The views are drawn by a NumPy z-buffer splatting of the points through ``scene.camera``'s
pinhole model, so no display or GPU is needed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from evaluate.settings import VisualisationSettings
from scene.base import Box
from scene.camera import Intrinsics, look_at, project_points
from scene.io import write_atomic

VIEW_NAMES = ("oblique_ne", "oblique_nw", "oblique_sw", "oblique_se", "nadir")
COVERED_RGB = (44, 160, 44)
MISSED_RGB = (214, 39, 40)
BACKGROUND_RGB = (255, 255, 255)
# Where save_view_png draws the view (left, bottom, width, height as figure fractions). The colour bar
# or legend sits right of this box; view_pixels cuts them and the title off.
VIEW_AXES_BOX = (0.01, 0.02, 0.80, 0.90)


def error_colors(distances_m: np.ndarray, vmax_m: float, colormap: str = "turbo") -> np.ndarray:
    """RGB colours (N, 3) uint8 of distances (N,) in metres on a fixed scale [0, vmax_m] (clipped)."""
    # heavy (matplotlib): imported on use
    import matplotlib

    cmap = matplotlib.colormaps[colormap]
    scaled = np.clip(np.asarray(distances_m, dtype=float) / float(vmax_m), 0.0, 1.0)
    return (255.0 * cmap(scaled)[:, :3] + 0.5).astype(np.uint8)


def coverage_colors(covered: np.ndarray) -> np.ndarray:
    """RGB colours (N, 3) uint8: green where ``covered`` (N,) bool, red where missed."""
    return np.where(np.asarray(covered, bool)[:, None], COVERED_RGB, MISSED_RGB).astype(np.uint8)


def write_colored_ply(path: str | Path, points: np.ndarray, colors: np.ndarray) -> Path:
    """Write points (N, 3) in metres with RGB colours (N, 3) uint8 as a binary PLY, atomically."""
    # heavy (open3d): imported on use
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64) / 255.0)

    def writer(tmp: Path) -> None:
        if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
            raise OSError(f"Open3D could not write {tmp}")

    return write_atomic(path, writer)


def overview_viewpoints(region: Box, intrinsics: Intrinsics, oblique_pitch_deg: float = -35.0) -> np.ndarray:
    """Five viewpoints (5, 5) framing the whole region: obliques from NE, NW, SW, SE, then nadir.

    Each camera looks at the region's centre from the distance at which the region's bounding
    sphere fills the narrower field of view.
    """
    center = region.center
    radius = 0.5 * float(np.linalg.norm(region.extent))
    half_fov = math.radians(min(intrinsics.hfov_deg, intrinsics.vfov_deg)) / 2.0
    distance = max(radius, 1e-3) / math.sin(half_fov)
    rows = []
    pitch = math.radians(oblique_pitch_deg)
    for azimuth in (45.0, 135.0, 225.0, 315.0):
        a = math.radians(azimuth)
        offset = distance * np.array(
            [math.cos(pitch) * math.cos(a), math.cos(pitch) * math.sin(a), -math.sin(pitch)]
        )
        rows.append(look_at(center + offset, center).as_array())
    # Nadir with yaw 90: image right is +x and image up is +y, like a map.
    rows.append(np.array([*center[:2], center[2] + distance, 90.0, -90.0]))
    return np.array(rows)


def splat(
    points: np.ndarray, colors: np.ndarray, viewpoint: np.ndarray, intrinsics: Intrinsics, radius_px: int = 1
) -> np.ndarray:
    """Image (H, W, 3) uint8 of coloured points seen from one viewpoint (5,), nearest point wins.

    Each point covers a (2r+1) x (2r+1) pixel square at its depth; pixels no point covers are white.
    """
    width, height = intrinsics.width, intrinsics.height
    pixels, depth = project_points(points, np.asarray(viewpoint, float)[None], intrinsics)
    pixels, depth = pixels[0], depth[0]
    with np.errstate(invalid="ignore"):
        col = np.floor(pixels[:, 0])
        row = np.floor(pixels[:, 1])
        visible = (depth > 1e-6) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    index = np.flatnonzero(visible)
    flat = row[index].astype(np.int64) * width + col[index].astype(np.int64)
    # One z-buffer pass at one pixel per point: per pixel, the nearest point.
    order = np.lexsort((depth[index], flat))
    flat_sorted = flat[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = flat_sorted[1:] != flat_sorted[:-1]
    zbuffer = np.full(height * width, np.inf)
    owner = np.full(height * width, -1, dtype=np.int64)
    zbuffer[flat_sorted[first]] = depth[index[order[first]]]
    owner[flat_sorted[first]] = index[order[first]]
    zbuffer, owner = zbuffer.reshape(height, width), owner.reshape(height, width)
    # Grow every point to its square: a pixel takes the nearest point among its neighbours.
    best_depth, best_owner = zbuffer.copy(), owner.copy()
    for dy in range(-radius_px, radius_px + 1):
        for dx in range(-radius_px, radius_px + 1):
            if dx == 0 and dy == 0:
                continue
            shifted_depth = np.full_like(zbuffer, np.inf)
            shifted_owner = np.full_like(owner, -1)
            target = (slice(max(dy, 0), height + min(dy, 0)), slice(max(dx, 0), width + min(dx, 0)))
            source = (slice(max(-dy, 0), height + min(-dy, 0)), slice(max(-dx, 0), width + min(-dx, 0)))
            shifted_depth[target] = zbuffer[source]
            shifted_owner[target] = owner[source]
            nearer = shifted_depth < best_depth
            best_depth[nearer] = shifted_depth[nearer]
            best_owner[nearer] = shifted_owner[nearer]
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[:] = BACKGROUND_RGB
    drawn = best_owner >= 0
    image[drawn] = np.asarray(colors)[best_owner[drawn]]
    return image


def save_view_png(path: str | Path, image: np.ndarray, title: str, colorbar: dict | None = None) -> Path:
    """Save a rendered view with a title and either a distance colour bar or a covered/missed legend.

    Args:
        colorbar: ``{"vmax_m": V, "colormap": NAME}`` for a distance scale; None draws the
            covered/missed legend.
    """
    # heavy (matplotlib): imported on use
    import matplotlib

    # heavy (matplotlib): imported on use
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    # heavy (matplotlib): imported on use
    from matplotlib.figure import Figure

    # heavy (matplotlib): imported on use
    from matplotlib.patches import Patch

    height, width = image.shape[:2]
    fig = Figure(figsize=(width / 100.0 + 1.6, height / 100.0 + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes(VIEW_AXES_BOX)
    ax.imshow(image, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    if colorbar is not None:
        norm = matplotlib.colors.Normalize(vmin=0.0, vmax=float(colorbar["vmax_m"]))
        mappable = matplotlib.cm.ScalarMappable(norm=norm, cmap=colorbar["colormap"])
        cax = fig.add_axes((0.84, 0.1, 0.025, 0.75))
        fig.colorbar(mappable, cax=cax, extend="max", label="distance to ground truth (m)")
    else:
        handles = [
            Patch(color=np.array(COVERED_RGB) / 255.0, label="covered"),
            Patch(color=np.array(MISSED_RGB) / 255.0, label="missed"),
        ]
        right_of_view = VIEW_AXES_BOX[0] + VIEW_AXES_BOX[2] + 0.01
        fig.legend(
            handles=handles, loc="center left", bbox_to_anchor=(right_of_view, 0.5), fontsize=9, frameon=False
        )
    return write_atomic(path, lambda tmp: fig.savefig(tmp, format="png"))


def view_pixels(picture: np.ndarray) -> np.ndarray:
    """The view inside a picture written by ``save_view_png``, without title, legend or blank margins.

    Args:
        picture: the PNG's pixels (H, W, C), as ``matplotlib.pyplot.imread`` returns them (floats in
            [0, 1]) or as uint8.

    Returns:
        The longest band of rows of ``VIEW_AXES_BOX`` with drawn (non-background) pixels, cut to its
        drawn columns; the whole box when nothing is drawn. (The axes shrink to the view's aspect, so
        the title can fall inside the box; blank rows separate it from the view.)
    """
    picture = np.asarray(picture)
    height, width = picture.shape[:2]
    left, bottom, box_w, box_h = VIEW_AXES_BOX
    rows = slice(int(round(height * (1.0 - bottom - box_h))), int(round(height * (1.0 - bottom))))
    cols = slice(int(round(width * left)), int(round(width * (left + box_w))))
    box = picture[rows, cols]
    scale = 1.0 if np.issubdtype(box.dtype, np.floating) else 255.0
    background = np.asarray(BACKGROUND_RGB, dtype=float) / 255.0
    drawn = np.any(np.abs(box[..., :3] / scale - background) > 0.02, axis=-1)
    rows_drawn = drawn.any(axis=1)
    if not rows_drawn.any():
        return box
    # Runs of drawn rows: a run starts where a drawn row follows a blank one.
    edges = np.diff(np.concatenate(([0], rows_drawn.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    longest = int(np.argmax(ends - starts))
    top, bottom = starts[longest], ends[longest]
    c = np.flatnonzero(drawn[top:bottom].any(axis=0))
    return box[top:bottom, c[0] : c[-1] + 1]


def write_error_visualisation(
    out_dir: str | Path,
    points: np.ndarray,
    distances_m: np.ndarray,
    gt_samples: np.ndarray,
    gt_distances_m: np.ndarray,
    region: Box,
    settings: VisualisationSettings | None = None,
    label: str = "",
) -> dict:
    """Coloured PLYs and PNG views of a scored reconstruction.

    Args:
        out_dir: folder for ``error_points.ply``, ``gt_coverage.ply``, ``error_<view>.png`` and
            ``coverage_<view>.png``.
        points, distances_m: scored reconstruction points (N, 3) and their distances (N,) to the
            ground truth, metres.
        gt_samples, gt_distances_m: ground-truth samples (S, 3) and their distances (S,) to the
            reconstruction (inf where none is near), metres.
        region: the box the views frame (the in-region ground truth's bounds: the same for every
            method of a scene).
        settings: colour scale, camera, splatting (defaults when None).
        label: prefix of the pictures' titles (e.g. ``tomb / ours``).

    Returns:
        Flat ``{"error_ply": path, "coverage_ply": path, "error_png_<view>": path, ...}`` (strings).
    """
    settings = settings or VisualisationSettings()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    error_rgb = error_colors(distances_m, settings.vmax_m, settings.colormap)
    covered = np.asarray(gt_distances_m) <= settings.coverage_threshold_m
    coverage_rgb = coverage_colors(covered)
    paths = {
        "error_ply": write_colored_ply(out_dir / "error_points.ply", points, error_rgb),
        "coverage_ply": write_colored_ply(out_dir / "gt_coverage.ply", gt_samples, coverage_rgb),
    }
    intrinsics = Intrinsics(settings.width, settings.height, settings.hfov_deg)
    viewpoints = overview_viewpoints(region, intrinsics, settings.oblique_pitch_deg)
    rng = np.random.default_rng(settings.seed)
    shown_points, shown_error = _subsample(rng, settings.max_render_points, points, error_rgb)
    shown_samples, shown_coverage = _subsample(rng, settings.max_render_points, gt_samples, coverage_rgb)
    prefix = f"{label}: " if label else ""
    t_mm = 1000.0 * settings.coverage_threshold_m
    share = 100.0 * covered.mean() if len(covered) else 0.0
    for name, viewpoint in zip(VIEW_NAMES, viewpoints, strict=True):
        image = splat(shown_points, shown_error, viewpoint, intrinsics, settings.point_radius_px)
        paths[f"error_png_{name}"] = save_view_png(
            out_dir / f"error_{name}.png",
            image,
            f"{prefix}reconstruction error ({name})",
            {"vmax_m": settings.vmax_m, "colormap": settings.colormap},
        )
        image = splat(shown_samples, shown_coverage, viewpoint, intrinsics, settings.point_radius_px)
        paths[f"coverage_png_{name}"] = save_view_png(
            out_dir / f"coverage_{name}.png",
            image,
            f"{prefix}ground truth within {t_mm:g} mm ({share:.1f} %) ({name})",
        )
    return {key: str(path) for key, path in paths.items()}


def _subsample(rng: np.random.Generator, limit: int, points: np.ndarray, colors: np.ndarray):
    if len(points) <= limit:
        return points, colors
    keep = np.sort(rng.choice(len(points), size=limit, replace=False))
    return points[keep], colors[keep]
