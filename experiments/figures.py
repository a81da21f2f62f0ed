"""The paper's figures from run directories: flight paths (Fig. 4), error views (Fig. 3), metrics vs images.

    uavplan-study figures multirun/2026-11-23_06-00-00 --out figures/

writes, each as PNG and PDF:
``flight_<scene>_<planner>``: the planned flight over the scene (3-D view and top view), viewpoints
coloured by kind, the trajectory in flight order and an arrow along each camera's viewing direction;
``flight_paths_<planner>``: that planner's flights over every scene side by side (the paper's Fig. 4);
``errors_<scene>``: the evaluation's error images (``eval/error_<view>.png``) of every method side by
side, one column per method and one row per view (Fig. 3); ``coverage_<scene>`` the same for the
ground truth coloured covered/missed (``eval/coverage_<view>.png``);
``metrics_vs_images``: accuracy and completeness against the number of images, one panel per scene.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402
from tqdm import tqdm  # noqa: E402

from evaluate.visualise import COVERED_RGB, MISSED_RGB, view_pixels  # noqa: E402
from experiments.runs import (  # noqa: E402
    Run,
    RunDirectoryError,
    load_runs,
    method_name,
    method_sort_key,
    out_is_a_file,
    read_run_config,
    read_run_viewpoints,
    run_scene_mesh,
    runs_frame,
    scene_name,
    scene_sort_key,
    tool_parser,
)
from planner.budget import DEFAULT_LEVEL, level_rank  # noqa: E402
from scene.camera import forward_vectors  # noqa: E402
from scene.io import write_atomic  # noqa: E402
from scene.plan import polyline_length  # noqa: E402

log = logging.getLogger(__name__)

# Fixed colours for the viewpoint kinds the planners emit, so a kind looks the same in every figure.
KIND_COLOURS = {
    "detail": "#d62728",
    "coverage": "#1f77b4",
    "grid": "#2ca02c",
    "oblique": "#ff7f0e",
    "nadir": "#9467bd",
    "exploration": "#8c564b",
}
_SPARE_COLOURS = ("#e377c2", "#17becf", "#bcbd22", "#7f7f7f", "#393b79", "#637939")
METHOD_MARKERS = {"ours": "o", "ours_plus": "P", "smith": "s", "yan": "^", "lawnmower": "D"}
_SPARE_MARKERS = ("v", "P", "X", "*", "<", ">")
# Longest error image shown in a panel, in inches (keeps a panel of many views printable).
PANEL_CELL_IN = 3.2
COLOUR_BAR_LABEL = "error colour bar"  # the label of an error panel's colour bar axes


def _style(name: str, fixed: dict, spare: Sequence[str], known: Sequence[str]) -> str:
    """``fixed[name]``, or for a name without one the spare styles in order of ``known``."""
    if name in fixed:
        return fixed[name]
    others = [k for k in known if k not in fixed]
    index = others.index(name) if name in others else len(others)
    return spare[index % len(spare)]


def kind_colour(kind: str, known: Sequence[str] = ()) -> str:
    """Colour of a viewpoint kind; kinds without a fixed colour take spare ones in order of ``known``."""
    return _style(kind, KIND_COLOURS, _SPARE_COLOURS, known)


def method_marker(planner: str, known: Sequence[str] = ()) -> str:
    """Scatter marker of a planner (``ours`` a circle, ``smith`` a square, ...)."""
    return _style(planner, METHOD_MARKERS, _SPARE_MARKERS, known)


def decimate_mesh(mesh, max_faces: int):
    """``mesh`` with at most ``max_faces`` triangles (quadric decimation; unchanged if already small).

    Args:
        mesh: a ``trimesh.Trimesh``.
        max_faces: the largest triangle count to keep (>= 4).
    """
    import trimesh

    if max_faces < 4:
        raise ValueError(f"max_faces must be at least 4, got {max_faces}")
    if len(mesh.faces) <= max_faces:
        return mesh
    import open3d as o3d

    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)),
    )
    simple = o3d_mesh.simplify_quadric_decimation(target_number_of_triangles=int(max_faces))
    faces = np.asarray(simple.triangles)
    if len(faces) == 0 or len(faces) > max_faces:
        # Quadric decimation can fail on degenerate input; a random subset still shows the shape.
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(len(mesh.faces), size=max_faces, replace=False))
        return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    return trimesh.Trimesh(np.asarray(simple.vertices), faces, process=False)


def _flight_extent(viewpoints: np.ndarray, mesh) -> tuple[np.ndarray, np.ndarray]:
    points = viewpoints[:, :3] if mesh is None else np.vstack([viewpoints[:, :3], np.asarray(mesh.vertices)])
    return points.min(axis=0), points.max(axis=0)


def _check_plan(viewpoints, kinds) -> tuple[np.ndarray, list[str]]:
    viewpoints = np.asarray(viewpoints, dtype=float).reshape(-1, 5)
    kinds = list(kinds)
    if len(kinds) != len(viewpoints):
        raise ValueError(f"{len(kinds)} kinds for {len(viewpoints)} viewpoints")
    return viewpoints, kinds


def _flight_geometry(viewpoints, kinds, mesh, arrow_length_m: float | None):
    """Validated plan, positions (V, 3), viewing arrows (V, 3) in metres and the (lo, hi, span) extent.

    The arrows are 4 % of the extent of flight and mesh long unless ``arrow_length_m`` is given.
    """
    viewpoints, kinds = _check_plan(viewpoints, kinds)
    lo, hi = _flight_extent(viewpoints, mesh)
    span = np.maximum(hi - lo, 1e-6)
    if arrow_length_m is None:
        arrow_length_m = 0.04 * float(np.linalg.norm(span))
    directions = forward_vectors(viewpoints[:, 3], viewpoints[:, 4]) * arrow_length_m
    return viewpoints, kinds, viewpoints[:, :3], directions, (lo, hi, span)


def draw_flight_3d(ax, viewpoints, kinds, mesh=None, arrow_length_m: float | None = None, mesh_label="scene"):
    """Draw a flight on a 3-D axes: light mesh, trajectory, one scatter and one quiver per kind.

    Args:
        ax: a matplotlib 3-D axes.
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V viewpoint kinds.
        mesh: a ``trimesh.Trimesh`` (decimated) or None.
        arrow_length_m: arrow length in metres (default: 4 % of the extent of flight and mesh).
        mesh_label: label of the mesh collection.
    """
    viewpoints, kinds, positions, directions, (lo, hi, span) = _flight_geometry(
        viewpoints, kinds, mesh, arrow_length_m
    )
    if mesh is not None and len(mesh.faces):
        triangles = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
        # Lambertian grey under a light from the upper south-west, so walls and roofs read apart.
        light = np.array([-0.4, -0.6, 1.0]) / np.linalg.norm([-0.4, -0.6, 1.0])
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        grey = 0.5 + 0.4 * np.abs(normals @ light)
        colours = np.column_stack([grey, grey, grey, np.full(len(grey), 0.45)])
        surface = Poly3DCollection(triangles, facecolors=colours, edgecolor="none", label=mesh_label)
        surface.set_rasterized(True)  # keeps the PDF small for meshes of thousands of triangles
        ax.add_collection3d(surface)
    ax.plot(*positions.T, color="0.35", linewidth=0.7, label="trajectory")
    seen = list(dict.fromkeys(kinds))
    kinds_arr = np.array(kinds)
    for kind in seen:
        mask = kinds_arr == kind
        colour = kind_colour(kind, seen)
        ax.scatter(
            *positions[mask].T, color=colour, s=14, depthshade=False, label=f"{kind} ({int(mask.sum())})"
        )
        ax.quiver(
            *positions[mask].T, *directions[mask].T, color=colour, linewidth=0.6, arrow_length_ratio=0.3
        )
    z_lo = min(lo[2], 0.0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(z_lo, hi[2])
    ax.set_box_aspect((span[0], span[1], max(hi[2] - z_lo, 1e-6)))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=30, azim=-60)


def draw_flight_top(ax, viewpoints, kinds, mesh=None, arrow_length_m: float | None = None):
    """Draw a flight seen from above (x right, y up): mesh shaded by height, trajectory, scatter and
    arrows (the horizontal part of each viewing direction) per kind. Arguments as ``draw_flight_3d``."""
    viewpoints, kinds, positions, directions, (lo, hi, span) = _flight_geometry(
        viewpoints, kinds, mesh, arrow_length_m
    )
    if mesh is not None and len(mesh.faces):
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        heights = vertices[faces, 2].mean(axis=1)
        # Draw the highest triangles last so the roof covers the walls.
        order = np.argsort(heights)
        ax.tripcolor(
            vertices[:, 0],
            vertices[:, 1],
            faces[order],
            facecolors=heights[order],
            cmap="Greys",
            alpha=0.45,
            edgecolors="none",
            linewidth=0.0,
            antialiased=False,
            rasterized=True,
            zorder=0,
        )
    ax.plot(positions[:, 0], positions[:, 1], color="0.35", linewidth=0.7, label="trajectory", zorder=1)
    seen = list(dict.fromkeys(kinds))
    kinds_arr = np.array(kinds)
    for kind in seen:
        mask = kinds_arr == kind
        colour = kind_colour(kind, seen)
        label = f"{kind} ({int(mask.sum())})"
        ax.scatter(positions[mask, 0], positions[mask, 1], color=colour, s=14, label=label, zorder=3)
        ax.quiver(
            positions[mask, 0],
            positions[mask, 1],
            directions[mask, 0],
            directions[mask, 1],
            color=colour,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.002,
            zorder=2,
        )
    ax.set_aspect("equal")
    margin = 0.05 * span[:2]
    ax.set_xlim(lo[0] - margin[0], hi[0] + margin[0])
    ax.set_ylim(lo[1] - margin[1], hi[1] + margin[1])
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_flight_path(
    viewpoints: np.ndarray,
    kinds: Sequence[str],
    mesh=None,
    title: str = "",
    arrow_length_m: float | None = None,
    mesh_label: str = "scene",
) -> Figure:
    """A flight over the scene: 3-D view (left) and top view (right).

    Args:
        viewpoints: (V, 5) ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V viewpoint kinds; each kind is one scatter (labelled with its count).
        mesh: a ``trimesh.Trimesh`` drawn light under the flight (decimate it first), or None.
        title: figure title.
        arrow_length_m: length of the viewing-direction arrows in metres (default: 4 % of the
            extent of viewpoints and mesh).
        mesh_label: legend label of the mesh.

    Returns:
        The figure: ``axes[0]`` is 3-D, ``axes[1]`` the top view (x right, y up); each holds one
        scatter per kind in order of first appearance.
    """
    fig = plt.figure(figsize=(13.0, 5.6))
    grid = fig.add_gridspec(1, 2, wspace=0.3)
    ax3d = fig.add_subplot(grid[0, 0], projection="3d")
    ax_top = fig.add_subplot(grid[0, 1])
    draw_flight_3d(ax3d, viewpoints, kinds, mesh, arrow_length_m, mesh_label)
    draw_flight_top(ax_top, viewpoints, kinds, mesh, arrow_length_m)
    ax_top.set_title("top view")
    ax_top.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    return fig


def plot_flight_paths_by_scene(flights: Sequence[tuple], title: str = "") -> Figure:
    """The paper's Figure 4: one 3-D flight per scene side by side.

    Args:
        flights: ``(subtitle, viewpoints (V, 5), kinds, mesh or None)`` per panel, in order.
        title: figure title.

    Returns:
        The figure; ``axes[i]`` is the 3-D view of ``flights[i]``.
    """
    if not flights:
        raise ValueError("no flights to draw")
    fig = plt.figure(figsize=(5.0 * len(flights), 5.0))
    for i, (subtitle, viewpoints, kinds, mesh) in enumerate(flights):
        ax = fig.add_subplot(1, len(flights), i + 1, projection="3d")
        draw_flight_3d(ax, viewpoints, kinds, mesh)
        ax.set_title(subtitle)
        ax.legend(loc="upper left", fontsize=7, frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


COST_AXES = {
    "n_images": ("number of images", 1.0),
    "flight_time_s": ("flight time (min)", 1.0 / 60.0),
}


def plot_metrics_vs_images(
    runs: pd.DataFrame, accuracy: str = "acc90_m", completeness: str = "comp_050", cost: str = "n_images"
) -> Figure:
    """Accuracy (top row) and completeness (bottom row) against a cost; one column per scene.

    Args:
        runs: one row per run (``experiments.runs.runs_frame``); failed runs and runs without a
            finite value are left out.
        accuracy: accuracy column (metres), e.g. ``acc90_m``.
        completeness: completeness column (percent), e.g. ``comp_050``.
        cost: the x axis, a key of ``COST_AXES``: ``n_images`` or ``flight_time_s`` (shown in minutes).

    Returns:
        The figure; ``axes[row][col]`` holds one scatter per planner (label = method name) whose
        offsets are (cost, value) of that planner's runs in seed order.
    """
    if cost not in COST_AXES:
        raise ValueError(f"cost must be one of {sorted(COST_AXES)}, got {cost!r}")
    cost_label, cost_scale = COST_AXES[cost]
    for column in (cost, accuracy, completeness):
        if column not in runs:
            raise ValueError(f"runs have no {column!r} column (metrics.json fields: {sorted(runs.columns)})")
    ok = runs[runs["status"] == "ok"]
    scenes = sorted(runs["scene"].unique(), key=scene_sort_key)
    planners = sorted(runs["planner"].unique(), key=method_sort_key)
    colours = plt.get_cmap("tab10")
    legend_width_in = 1.6  # beside the axes: a fraction of the width would cover a one-scene figure
    width_in = 3.6 * len(scenes) + legend_width_in
    fig, axes = plt.subplots(2, len(scenes), figsize=(width_in, 6.4), squeeze=False)
    for col, scene in enumerate(scenes):
        for row, (metric, label) in enumerate(
            [(accuracy, _metric_label(accuracy)), (completeness, _metric_label(completeness))]
        ):
            ax = axes[row][col]
            for i, planner in enumerate(planners):
                cells = ok[(ok["scene"] == scene) & (ok["planner"] == planner)].sort_values("seed")
                x = pd.to_numeric(cells[cost], errors="coerce").to_numpy(dtype=float) * cost_scale
                y = pd.to_numeric(cells[metric], errors="coerce").to_numpy(dtype=float)
                finite = np.isfinite(x) & np.isfinite(y)
                if not finite.any():
                    continue
                ax.scatter(
                    x[finite],
                    y[finite],
                    marker=method_marker(planner, planners),
                    color=colours(i % 10),
                    s=36,
                    label=method_name(planner),
                )
            ax.set_xlabel(cost_label)
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(scene_name(scene))
    handles, labels = {}, {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, handle)
            labels[label] = label
    fig.legend(list(handles.values()), list(labels), loc="center right", frameon=False)
    fig.tight_layout(rect=(0.0, 0.0, 1.0 - legend_width_in / width_in, 1.0))
    return fig


def _metric_label(column: str) -> str:
    # Keys as evaluate/settings.py names them: acc90_m, acc99p5_m, comp_050 (mm), comp_007p5.
    try:
        if column.startswith("acc") and column.endswith("_m"):
            return f"error {float(column[3:-2].replace('p', '.')):g} % (m)"
        if column.startswith("comp_"):
            t_m = float(column[5:].replace("p", ".")) / 1000.0
            return f"completeness {t_m:.3f} m (%)" if round(t_m, 3) == t_m else f"completeness {t_m:g} m (%)"
    except ValueError:
        pass
    return column


def plot_error_panel(
    images: dict[str, dict[str, Path]],
    title: str = "",
    error_scale: tuple[float, str] | None = None,
    covered_within_m: float | None = None,
) -> Figure:
    """Error images side by side: one column per method, one row per image name.

    Each picture is cut to its view (``evaluate.visualise.view_pixels``: its own title and key are
    too small to read at panel size); the panel draws one key for all of them instead.

    Args:
        images: ``{method label: {image name: PNG path}}`` in column order.
        title: figure title.
        error_scale: ``(vmax_m, colormap)`` of the error pictures: draws one distance colour bar.
        covered_within_m: the coverage pictures' threshold (m): draws one covered/missed legend.

    Returns:
        The figure; ``axes[row][col]`` shows image ``row`` (names sorted) of method ``col`` or is
        blank where that method has no such image.
    """
    if not images:
        raise ValueError("no error images to show")
    names = sorted({name for per_method in images.values() for name in per_method})
    shapes = [plt.imread(p).shape for per_method in images.values() for p in per_method.values()]
    aspect = float(np.median([s[0] / s[1] for s in shapes]))
    fig, axes = plt.subplots(
        len(names),
        len(images),
        squeeze=False,
        figsize=(PANEL_CELL_IN * len(images), PANEL_CELL_IN * aspect * len(names) + 0.6),
    )
    for col, (method, per_method) in enumerate(images.items()):
        for row, name in enumerate(names):
            ax = axes[row][col]
            ax.axis("off")
            if name in per_method:
                ax.imshow(view_pixels(plt.imread(per_method[name])))
            if row == 0:
                ax.set_title(method)
            if col == 0 and len(names) > 1:
                ax.text(
                    -0.02, 0.5, Path(name).stem, transform=ax.transAxes, rotation=90, ha="right", va="center"
                )
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    # Keys go beyond the right edge: save_figure's tight bounding box takes them in.
    if error_scale is not None:
        vmax_m, colormap = error_scale
        mappable = plt.cm.ScalarMappable(norm=plt.Normalize(0.0, float(vmax_m)), cmap=colormap)
        cax = fig.add_axes((1.01, 0.3, 0.012, 0.4), label=COLOUR_BAR_LABEL)
        fig.colorbar(mappable, cax=cax, extend="max", label="distance to ground truth (m)")
    if covered_within_m is not None:
        handles = [
            Patch(color=np.array(COVERED_RGB) / 255.0, label=f"within {1000 * covered_within_m:.0f} mm"),
            Patch(color=np.array(MISSED_RGB) / 255.0, label="missed"),
        ]
        fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    return fig


def panel_keys(run: Run) -> dict:
    """``error_scale`` and ``covered_within_m`` of a run's evaluation pictures for ``plot_error_panel``.

    From ``evaluate.visualise`` in the run's ``.hydra/config.yaml``, else the evaluation defaults.
    """
    from omegaconf import OmegaConf

    from evaluate.settings import VisualisationSettings

    known = VisualisationSettings.__dataclass_fields__
    cfg = read_run_config(run.run_dir)
    given = OmegaConf.select(cfg, "evaluate.visualise", default=None) if cfg is not None else None
    given = {k: v for k, v in OmegaConf.to_container(given).items() if k in known} if given else {}
    vis = VisualisationSettings(**given)
    return {"error_scale": (vis.vmax_m, vis.colormap), "covered_within_m": vis.coverage_threshold_m}


def save_figure(fig: Figure, stem: Path, dpi: int = 200) -> list[Path]:
    """Save ``fig`` as ``stem.png`` and ``stem.pdf`` atomically and close it; return the paths."""
    paths = []
    for suffix in (".png", ".pdf"):
        path = stem.with_suffix(suffix)
        paths.append(write_atomic(path, lambda p: fig.savefig(p, dpi=dpi, bbox_inches="tight")))
    plt.close(fig)
    return paths


def _first_run_with_plan(runs: Sequence[Run]):
    for run in sorted(runs, key=lambda r: r.seed):
        plan = read_run_viewpoints(run.run_dir)
        if plan is not None:
            return run, plan
    return None, None


def error_images(run: Run, pattern: str) -> dict[str, Path]:
    """The evaluation's images of a run matching ``pattern`` (relative to the run dir), by relative name."""
    eval_dir = run.run_dir / "eval"
    found = {}
    for path in sorted(run.run_dir.glob(pattern)):
        if path.is_file():
            found[str(path.relative_to(eval_dir)) if path.is_relative_to(eval_dir) else path.name] = path
    return found


def make_figures(
    run_paths: Sequence[str | Path],
    out_dir: str | Path,
    planners: Sequence[str] | None = None,
    mesh_source: str = "ground_truth",
    max_faces: int = 6000,
    accuracy: str = "acc90_m",
    completeness: str = "comp_050",
    error_glob: str = "eval/error_*.png",
    coverage_glob: str = "eval/coverage_*.png",
    dpi: int = 200,
) -> dict[str, list[Path]]:
    """Draw every figure for the runs under ``run_paths`` into ``out_dir``.

    Args:
        run_paths: run or multirun directories.
        out_dir: output directory.
        planners: planners whose flight paths to draw (default: all).
        mesh_source: ``ground_truth``, ``proxy`` or ``none``: the mesh under the flight paths
            (the other one is used when the preferred one is not found).
        max_faces: triangles kept of that mesh.
        accuracy, completeness: the metrics of the metrics-vs-images figure.
        error_glob: glob (relative to a run dir) of the evaluation's error images (one row per view).
        coverage_glob: glob of its ground-truth coverage images.
        dpi: PNG resolution.

    Returns:
        ``{"flight_paths": [...], "errors": [...], "coverage": [...], "metrics_vs_images": [...]}``
        files written.
    """
    if mesh_source not in ("ground_truth", "proxy", "none"):
        raise ValueError(f"mesh_source must be ground_truth, proxy or none, got {mesh_source!r}")
    runs = load_runs(run_paths)
    out_dir = Path(out_dir)
    written: dict[str, list[Path]] = {
        "flight_paths": [],
        "errors": [],
        "coverage": [],
        "metrics_vs_images": [],
        "metrics_vs_flight_time": [],
    }
    groups: dict[tuple[str, str, str], list[Run]] = {}
    for run in runs:
        groups.setdefault((run.scene, run.planner, run.budget), []).append(run)

    mesh_cache: dict[str, tuple] = {}
    by_planner: dict[tuple[str, str], list[tuple]] = {}
    for (scene, planner, budget), cell_runs in tqdm(groups.items(), desc="flight paths", unit="cell"):
        if planners is not None and planner not in planners:
            continue
        run, plan = _first_run_with_plan(cell_runs)
        if run is None:
            log.info("%s/%s: no plan/viewpoints.csv, no flight figure", scene, planner)
            continue
        mesh, label = None, ""
        if mesh_source != "none":
            if scene not in mesh_cache:
                found, label = run_scene_mesh(run, prefer=mesh_source)
                mesh_cache[scene] = (decimate_mesh(found, max_faces) if found is not None else None, label)
            mesh, label = mesh_cache[scene]
        viewpoints, kinds = plan
        length = polyline_length(viewpoints[:, :3])
        title = (
            f"{method_name(planner, budget)}: {scene_name(scene)} (seed {run.seed}), "
            f"{len(viewpoints)} viewpoints, {length:.0f} m flight"
        )
        fig = plot_flight_path(viewpoints, kinds, mesh, title=title, mesh_label=label or "scene")
        tag = planner if budget == DEFAULT_LEVEL else f"{planner}_{budget}"
        written["flight_paths"] += save_figure(fig, out_dir / f"flight_{scene}_{tag}", dpi)
        subtitle = f"{scene_name(scene)}: {len(viewpoints)} views, {length:.0f} m"
        by_planner.setdefault((planner, budget), []).append((subtitle, viewpoints, kinds, mesh))
    for (planner, budget), flights in by_planner.items():
        if len(flights) > 1:
            tag = planner if budget == DEFAULT_LEVEL else f"{planner}_{budget}"
            fig = plot_flight_paths_by_scene(flights, title=f"Flight paths: {method_name(planner, budget)}")
            written["flight_paths"] += save_figure(fig, out_dir / f"flight_paths_{tag}", dpi)

    panels = [
        ("errors", error_glob, "Reconstruction error", "error_scale"),
        ("coverage", coverage_glob, "Ground truth covered", "covered_within_m"),
    ]
    for scene in sorted({key[0] for key in groups}, key=scene_sort_key):
        for kind, pattern, heading, key in panels:
            columns: dict[str, dict[str, Path]] = {}
            keys = []
            cells = sorted(
                ((p, b) for s, p, b in groups if s == scene),
                key=lambda pb: (method_sort_key(pb[0]), level_rank(pb[1])),
            )
            for planner, budget in cells:
                for run in sorted(groups[(scene, planner, budget)], key=lambda r: r.seed):
                    found = error_images(run, pattern)
                    if found:
                        columns[f"{method_name(planner, budget)} (seed {run.seed})"] = found
                        keys.append(panel_keys(run)[key])
                        break
            if columns:
                if len(set(keys)) > 1:
                    log.warning(
                        "%s: the %s pictures use different keys %s; the panel shows the first",
                        scene,
                        kind,
                        keys,
                    )
                fig = plot_error_panel(columns, title=f"{heading}: {scene_name(scene)}", **{key: keys[0]})
                written[kind] += save_figure(fig, out_dir / f"{kind}_{scene}", dpi)
            else:
                log.info("%s: no evaluation images matching %s, no %s panel", scene, pattern, kind)

    frame = runs_frame(runs)
    for cost, stem in (("n_images", "metrics_vs_images"), ("flight_time_s", "metrics_vs_flight_time")):
        if {cost, accuracy, completeness} <= set(frame.columns):
            fig = plot_metrics_vs_images(frame, accuracy, completeness, cost=cost)
            written[stem] += save_figure(fig, out_dir / stem, dpi)
        else:
            log.warning("runs lack %s/%s/%s: no %s figure", cost, accuracy, completeness, stem)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan-study figures DIR... --out OUT``; returns the exit status."""
    parser = tool_parser("uavplan-study figures", __doc__, "directory for the figures")
    parser.add_argument("--planners", nargs="+", help="planners whose flight paths to draw (default: all)")
    parser.add_argument(
        "--mesh",
        choices=("ground_truth", "proxy", "none"),
        default="ground_truth",
        help="mesh drawn under the flight paths",
    )
    parser.add_argument("--max-faces", type=int, default=6000, help="triangles kept of that mesh")
    parser.add_argument("--accuracy", default="acc90_m", help="accuracy metric of the scatter figure")
    parser.add_argument(
        "--completeness", default="comp_050", help="completeness metric of the scatter figure"
    )
    parser.add_argument(
        "--error-glob", default="eval/error_*.png", help="error images, relative to a run dir"
    )
    parser.add_argument("--coverage-glob", default="eval/coverage_*.png", help="coverage images, ditto")
    parser.add_argument("--dpi", type=int, default=200)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if out_is_a_file(args.out):
        return 2
    try:
        written = make_figures(
            args.dirs,
            args.out,
            args.planners,
            args.mesh,
            args.max_faces,
            args.accuracy,
            args.completeness,
            args.error_glob,
            args.coverage_glob,
            args.dpi,
        )
    except (RunDirectoryError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for kind, paths in written.items():
        print(f"{kind}: {len(paths)} files" + (f" ({paths[0].parent})" if paths else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
