"""Did the plan or the reconstruction lose a surface? How closely each flight observed the ground truth.

    uavplan-diagnose observations study/default --out results/observations

For every run: the ground truth of its evaluation region (``eval/gt_region.ply``) is sampled evenly
and each sample is classed like the completeness table (ground, roofs, walls, undersides). A view
*observes a sample well* when the sample lies in its image, unoccluded by the ground truth, within
``max_distance_factor`` x the survey's target distance d_t (``survey.target_gsd_m`` x focal length
in pixels) and at most ``max_incidence_deg`` off the surface normal. Only the views SfM registered
count (``recon/sparse``; all rendered views when the run has no model). Per run and class the
table gives the share of samples that ``min_views`` views observe well, and the share that as many
views see at all. Dense matching needs several close, frontal views of a point: a class with low
completeness but a high well-observed share was lost in the reconstruction, one with a low
well-observed share in the plan.

Writes ``observations.md`` (one table), ``observations.csv`` (one row per run and class).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh

from evaluate.metrics import SURFACE_CLASSES
from evaluate.settings import EvaluationSettings
from experiments.runs import (
    Run,
    RunDirectoryError,
    load_runs,
    method_name,
    read_run_config,
    run_intrinsics,
    scene_name,
    tool_parser,
)
from pipeline.forecast import ObservationCriteria, observation_shares
from scene.cameras_file import CAMERAS_FILE, read_cameras
from scene.io import write_text_atomic

log = logging.getLogger(__name__)

GT_REGION_FILE = Path("eval") / "gt_region.ply"
IMAGES_DIR = Path("images")
SPARSE_DIR = Path("recon") / "sparse"


def registered_views(run_dir: Path) -> tuple[np.ndarray, int, bool]:
    """The rendered views of a run that SfM registered.

    Returns:
        ((R, 5) viewpoints, number of rendered views, whether a sparse model said which registered;
        False: the run has no model and every rendered view is returned).

    Raises:
        RunDirectoryError: no ``images/cameras.json`` or a malformed one.
    """
    try:
        names, viewpoints, _, _ = read_cameras(run_dir / IMAGES_DIR)
    except FileNotFoundError as exc:
        path = run_dir / IMAGES_DIR / CAMERAS_FILE
        raise RunDirectoryError(f"{path}: missing (the run rendered no flight)") from exc
    except ValueError as exc:
        raise RunDirectoryError(f"not a flight record: {exc}") from exc
    registered = registered_image_names(run_dir / SPARSE_DIR)
    if registered is None:
        return viewpoints, len(names), False
    keep = np.array([name in registered for name in names], dtype=bool)
    return viewpoints[keep], len(names), True


def registered_image_names(sparse_dir: Path) -> set[str] | None:
    """Names of the images in the COLMAP model at ``sparse_dir``, or None if there is no model."""
    if not any((sparse_dir / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        return None
    # heavy (pycolmap): imported on use
    import pycolmap

    return {image.name for image in pycolmap.Reconstruction(str(sparse_dir)).images.values()}


def run_observations(run: Run, criteria: ObservationCriteria) -> pd.DataFrame:
    """``observation_shares`` of one run, with its scene, planner, seed and view counts."""
    run_dir = run.run_dir
    gt_path = run_dir / GT_REGION_FILE
    if not gt_path.is_file():
        raise RunDirectoryError(f"{gt_path}: missing (the run was not scored)")
    ground_truth = trimesh.load(gt_path, force="mesh", process=False)
    intrinsics = run_intrinsics(run_dir)
    config = read_run_config(run_dir)
    gsd = config.get("survey", {}).get("target_gsd_m") if config is not None else None
    if intrinsics is None or gsd is None:
        raise RunDirectoryError(
            f"{run_dir}: .hydra/config.yaml must give camera and survey.target_gsd_m (the target distance)"
        )
    settings = EvaluationSettings.from_config(config.get("evaluate"))
    views, n_rendered, from_model = registered_views(run_dir)
    target_distance = float(gsd) * intrinsics.focal_px
    table = observation_shares(ground_truth, views, intrinsics, target_distance, criteria, settings)
    return table.assign(
        scene=run.scene,
        planner=run.planner,
        budget=run.budget,
        seed=run.seed,
        n_views=len(views),
        n_rendered=n_rendered,
        registration_known=from_model,
        max_distance_m=criteria.max_distance_factor * target_distance,
    )


def observations_frame(paths: Sequence[str | Path], criteria: ObservationCriteria) -> pd.DataFrame:
    """``run_observations`` of every successful run under ``paths``, one row per run and class."""
    frames = []
    for run in load_runs(paths):
        if not run.ok:
            log.info("skipping failed run %s", run.run_dir)
            continue
        log.info("observations of %s/%s seed %d", run.scene, run.planner, run.seed)
        frames.append(run_observations(run, criteria))
    if not frames:
        raise RunDirectoryError(f"no successful run under {', '.join(map(str, paths))}")
    return pd.concat(frames, ignore_index=True)


def to_markdown(frame: pd.DataFrame, criteria: ObservationCriteria) -> str:
    """One row per run: views, then per class 'well observed / seen' shares in percent."""
    lines = [
        f"**Ground-truth samples observed well by >= {criteria.min_views} registered views (within "
        f"{criteria.max_distance_factor:g} d_t, <= {criteria.max_incidence_deg:g} deg off the normal) "
        f"/ seen by >= {criteria.min_views} at all (%).**",
        "",
        "| Scene | Method | Views (registered / rendered) | "
        + " | ".join(name.capitalize() for name in SURFACE_CLASSES)
        + " |",
        "| :-- | :-- | --: | " + " | ".join("--:" for _ in SURFACE_CLASSES) + " |",
    ]
    for (scene, planner, budget, seed), rows in frame.groupby(
        ["scene", "planner", "budget", "seed"], sort=False
    ):
        first = rows.iloc[0]
        registered = (
            f"{first.n_views} / {first.n_rendered}" if first.registration_known else f"all {first.n_rendered}"
        )
        cells = []
        for name in SURFACE_CLASSES:
            row = rows[rows.surface == name].iloc[0]
            cells.append(
                "n/a"
                if np.isnan(row.well_observed_pct)
                else f"{row.well_observed_pct:.0f} / {row.seen_pct:.0f}"
            )
        method = method_name(planner, budget) + (f" (seed {seed})" if frame.seed.nunique() > 1 else "")
        lines.append(f"| {scene_name(scene)} | {method} | {registered} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan-diagnose observations DIR... --out OUT``; returns the exit status."""
    defaults = ObservationCriteria()
    parser = tool_parser("uavplan-diagnose observations", __doc__, "directory for observations.md and .csv")
    parser.add_argument("--min-views", type=int, default=defaults.min_views)
    parser.add_argument("--max-distance-factor", type=float, default=defaults.max_distance_factor)
    parser.add_argument("--max-incidence-deg", type=float, default=defaults.max_incidence_deg)
    parser.add_argument("--samples", type=int, default=defaults.n_samples)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        criteria = ObservationCriteria(
            args.min_views, args.max_distance_factor, args.max_incidence_deg, args.samples
        )
        frame = observations_frame(args.dirs, criteria)
    except (ValueError, RunDirectoryError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    markdown = to_markdown(frame, criteria)
    write_text_atomic(args.out / "observations.md", markdown)
    write_text_atomic(args.out / "observations.csv", frame.to_csv(index=False, lineterminator="\n"))
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
