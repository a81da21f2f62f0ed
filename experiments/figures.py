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
from omegaconf import OmegaConf
from tqdm import tqdm  # noqa: E402

from evaluate.settings import VisualisationSettings
from evaluate.visualise import COVERED_RGB, MISSED_RGB, view_pixels  # noqa: E402
from experiments.flight_figures import (  # noqa: E402
    decimate_mesh,
    method_marker,
    plot_flight_path,
    plot_flight_paths_by_scene,
)
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
from scene.io import write_atomic  # noqa: E402
from scene.plan import polyline_length  # noqa: E402

log = logging.getLogger(__name__)

PANEL_CELL_IN = 3.2
COLOUR_BAR_LABEL = "error colour bar"  # the label of an error panel's colour bar axes


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
