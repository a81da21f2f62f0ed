"""Planner stability: how much a plan changes when its proxy moves by the run-to-run amount.

    uavplan-diagnose plan-stability --proxy PROXY.ply --out OUT -- experiment=smoke scene=tomb

Two default-mode reconstructions of the same exploratory flight give proxies a few millimetres apart
(the smoke tomb: median 3.1 mm, 90th percentile 11 mm between the two surfaces; see
``archive/pre_p1/reproducibility.md``). Each planner plans once on the proxy as it is and
``--repeats`` times on copies whose vertices moved along their normals by Gaussian noise of
``--sigma-mm`` (5 mm: median offset 3.4 mm, 90th percentile 8 mm), with the same planner seed. Per
plan it reports the image count, the flight length, how far the views moved (each view to the
nearest view of the unperturbed plan) and the predicted coverage per surface class: the share of the
unperturbed proxy's samples that ``min_views`` planned views observe within ``max_distance_factor``
d_t and ``max_incidence_deg`` of the normal (``experiments.observations``' criteria, measured on the
same unperturbed proxy for every plan, so only the plan changes). A planner whose plan swings by
more than the reconstruction's own noise makes its table cells noisier than the reconstruction alone
would.

Writes ``plan_stability.md`` (per planner: the unperturbed plan, the spread over the perturbed ones)
and ``plan_stability.csv`` (one row per plan) into ``--out``.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
import trimesh
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree

from evaluate.metrics import SURFACE_CLASSES
from evaluate.settings import EvaluationSettings
from experiments.runs import method_name, tool_parser
from pipeline.forecast import ObservationCriteria, observation_shares
from pipeline.settings import planner_params
from scene.camera import Intrinsics
from scene.io import write_text_atomic

log = logging.getLogger(__name__)

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
PLANNERS = ("ours", "smith", "yan", "lawnmower")


def perturb_proxy(proxy: trimesh.Trimesh, sigma_m: float, seed: int) -> trimesh.Trimesh:
    """A copy of ``proxy`` whose vertices moved along their normals by N(0, ``sigma_m``) metres."""
    if not sigma_m >= 0:
        raise ValueError(f"--sigma-mm must be >= 0, got {sigma_m * 1000:g}")
    rng = np.random.default_rng(seed)
    offsets = rng.normal(0.0, sigma_m, size=len(proxy.vertices))
    vertices = np.asarray(proxy.vertices) + offsets[:, None] * np.asarray(proxy.vertex_normals)
    return trimesh.Trimesh(vertices=vertices, faces=np.asarray(proxy.faces), process=False)


def view_shift_m(views: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance (m) from each view's position to the nearest position of ``reference``."""
    return cKDTree(np.asarray(reference)[:, :3]).query(np.asarray(views)[:, :3])[0]


def compose_config(overrides: Sequence[str]):
    """The composed run config for ``overrides`` (as ``python run.py OVERRIDES`` would see it)."""
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        return compose("config", overrides=list(overrides))


def plan_rows(
    proxy: trimesh.Trimesh,
    planner: str,
    overrides: Sequence[str],
    repeats: int,
    sigma_m: float,
    criteria: ObservationCriteria,
) -> list[dict]:
    """One row per plan of ``planner``: the unperturbed proxy (``perturbation`` -1), then ``repeats``
    perturbed copies (``perturbation`` 0..repeats-1)."""
    cfg = compose_config([*overrides, f"planner={planner}"])
    intrinsics = Intrinsics(**cfg.camera)
    params = planner_params(cfg)
    plan_fn = hydra.utils.get_method(cfg.planner._target_)
    settings = EvaluationSettings.from_config(cfg.evaluate)
    target_distance = float(cfg.survey.target_gsd_m) * intrinsics.focal_px
    rows, reference = [], None
    for perturbation in range(-1, repeats):
        mesh = proxy if perturbation < 0 else perturb_proxy(proxy, sigma_m, seed=perturbation)
        start = time.perf_counter()
        plan = plan_fn(mesh, intrinsics, params, int(cfg.seed))
        seconds = time.perf_counter() - start
        views = np.asarray(plan.viewpoints, dtype=float)
        if reference is None:
            reference = views
        shift = view_shift_m(views, reference)
        shares = observation_shares(proxy, views, intrinsics, target_distance, criteria, settings)
        row = {
            "planner": planner,
            "perturbation": perturbation,
            "sigma_mm": 0.0 if perturbation < 0 else sigma_m * 1000.0,
            "n_images": len(views),
            "flight_length_m": float(plan.flight_length_m),
            "view_shift_median_m": float(np.median(shift)),
            "view_shift_p90_m": float(np.percentile(shift, 90)),
            "plan_time_s": seconds,
        }
        for share in shares.itertuples():
            row[f"well_observed_{share.surface}_pct"] = float(share.well_observed_pct)
        log.info(
            "%s perturbation %d: %d images, views moved %.2f m (median)",
            planner,
            perturbation,
            len(views),
            row["view_shift_median_m"],
        )
        rows.append(row)
    return rows


def to_markdown(frame: pd.DataFrame, proxy_path: str, sigma_mm: float, criteria: ObservationCriteria) -> str:
    """Per planner: the unperturbed plan's numbers, then mean and range over the perturbed plans."""
    columns = ["n_images", "flight_length_m", "view_shift_median_m"] + [
        f"well_observed_{name}_pct" for name in SURFACE_CLASSES
    ]
    labels = ["Images", "Flight (m)", "Views moved, median (m)"] + [
        f"{name.capitalize()} (%)" for name in SURFACE_CLASSES
    ]
    lines = [
        "# Planner stability",
        "",
        f"Proxy `{proxy_path}`, perturbed along its vertex normals by N(0, {sigma_mm:g} mm). Predicted "
        f"coverage: share of the unperturbed proxy's samples with >= {criteria.min_views} planned views "
        f"within {criteria.max_distance_factor:g} d_t and {criteria.max_incidence_deg:g} deg of the normal.",
        "Each cell: unperturbed plan; perturbed plans as mean [min, max].",
        "",
        "| Method | " + " | ".join(labels) + " |",
        "| :-- | " + " | ".join("--:" for _ in labels) + " |",
    ]
    for planner, group in frame.groupby("planner", sort=False):
        base = group[group["perturbation"] < 0].iloc[0]
        moved = group[group["perturbation"] >= 0]
        cells = []
        for column in columns:
            values = moved[column].to_numpy(dtype=float)
            spread = f" ({values.mean():.4g} [{values.min():.4g}, {values.max():.4g}])" if len(values) else ""
            cells.append(f"{base[column]:.4g}{spread}")
        lines.append(f"| {method_name(planner)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command line; returns the exit status."""
    defaults = ObservationCriteria()
    parser = tool_parser("uavplan-diagnose plan-stability", __doc__)
    parser.add_argument(
        "--proxy", type=Path, required=True, help="proxy mesh (e.g. cache/exploration/<key>/proxy.ply)"
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for plan_stability.md and .csv")
    parser.add_argument("--planners", default=",".join(PLANNERS), help="comma-separated planner names")
    parser.add_argument("--repeats", type=int, default=3, help="perturbed proxies per planner (default 3)")
    parser.add_argument("--sigma-mm", type=float, default=5.0, help="vertex offset sigma in mm (default 5)")
    parser.add_argument("--samples", type=int, default=defaults.n_samples, help="proxy samples for coverage")
    parser.add_argument("overrides", nargs="*", help="run.py overrides after --: experiment=smoke scene=tomb")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if not args.proxy.is_file():
        print(f"error: proxy mesh not found: {args.proxy}", file=sys.stderr)
        return 2
    if args.repeats < 1:
        print(f"error: --repeats must be at least 1, got {args.repeats}", file=sys.stderr)
        return 2
    proxy = trimesh.load(args.proxy, force="mesh", process=False)
    if len(proxy.faces) == 0:
        print(f"error: {args.proxy} holds no triangles", file=sys.stderr)
        return 2
    criteria = ObservationCriteria(n_samples=args.samples)
    rows = []
    try:
        for planner in [p.strip() for p in args.planners.split(",") if p.strip()]:
            rows += plan_rows(proxy, planner, args.overrides, args.repeats, args.sigma_mm / 1000.0, criteria)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    frame = pd.DataFrame(rows)
    markdown = to_markdown(frame, str(args.proxy), args.sigma_mm, criteria)
    write_text_atomic(args.out / "plan_stability.csv", frame.to_csv(index=False, lineterminator="\n"))
    write_text_atomic(args.out / "plan_stability.md", markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
