"""Does ``ours_plus``' evidence mean something? Its weights against the proxy's true error.

    python -m archive.evidence_check study/default_v3/tomb/ours/seed0 study/... --out results/evidence

For each run directory (any planner: only its scene and its exploration cache entry are read), the
proxy of that entry is sampled as the planner samples it (``n_points``, the run's seed), each sample
gets the evidence weight of ``conf/planner/ours_plus.yaml`` from the exploration's fused cloud and images, and
its true error is its distance to the ground-truth surface (which the planner never sees). Prints
and writes, per scene, the Spearman rank correlation between weight and true error, per signal
too, and the median true error of sure and unsure samples.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import spearmanr

from experiments.runs import RunDirectoryError, load_runs, read_run_config, scene_name
from scene.io import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]

SIGNALS = ("gap", "support", "normal", "photo")


def ours_plus_evidence_settings():
    """The ``evidence`` section of ``conf/planner/ours_plus.yaml``."""
    from omegaconf import OmegaConf

    from planner.ours.evidence import EvidenceSettings

    node = OmegaConf.load(ROOT / "conf" / "planner" / "ours_plus.yaml").evidence
    return EvidenceSettings.from_config(OmegaConf.to_container(node))


def true_error_m(mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) from each point (N, 3) to the surface of ``mesh``."""
    import open3d as o3d

    from scene.enclosure import raycasting_scene

    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return raycasting_scene(mesh).compute_distance(query).numpy().astype(float)


def check_entry(entry: Path, ground_truth, n_points: int, seed: int) -> dict:
    """Weights, signals and true errors of one exploration entry's proxy samples; the correlations."""
    from pipeline.proxy import load_proxy
    from planner.ours.evidence import proxy_evidence, sample_weights
    from planner.sampling import sample_surface

    settings = ours_plus_evidence_settings()
    proxy = load_proxy(entry)
    points, normals = sample_surface(proxy, n_points, seed)
    signals = proxy_evidence(proxy, points, normals, settings)
    if signals is None:
        raise RunDirectoryError(f"{entry}: the exploration entry holds no fused cloud (recon/dense.ply)")
    weights = sample_weights(signals["uncertainty"], settings)
    error = true_error_m(ground_truth, points)
    unsure = signals["uncertainty"] > 0.5
    row = {
        "n_samples": len(points),
        "share_unsure": float(unsure.mean()),
        "spearman_weight": float(spearmanr(weights, error).statistic),
        **{f"spearman_{s}": float(spearmanr(signals[s], error).statistic) for s in SIGNALS if s in signals},
        # The photo signal's NCC where it scored (a plain patch or a sample one view sees: no score).
        "share_photo_scored": (
            float(np.mean(np.isfinite(signals["photo_ncc"]))) if "photo_ncc" in signals else float("nan")
        ),
        "spearman_photo_ncc_scored": _scored_spearman(signals.get("photo_ncc"), error),
        "spearman_weight_cloud_only": float(
            spearmanr(np.maximum.reduce([signals[s] for s in SIGNALS[:3]]), error).statistic
        ),
        "median_error_sure_m": float(np.median(error[~unsure])) if (~unsure).any() else float("nan"),
        "median_error_unsure_m": float(np.median(error[unsure])) if unsure.any() else float("nan"),
        "share_error_over_10cm": float(np.mean(error > 0.1)),
    }
    return row


def _scored_spearman(ncc: np.ndarray | None, error: np.ndarray) -> float:
    """Spearman of -NCC against the true error over the samples the photo signal scored."""
    if ncc is None:
        return float("nan")
    scored = np.isfinite(ncc)
    return float(spearmanr(-ncc[scored], error[scored]).statistic) if scored.sum() > 2 else float("nan")


def to_markdown(frame: pd.DataFrame) -> str:
    """One row per scene: samples, unsure share, rank correlations, median true errors."""
    lines = [
        "| Scene | Samples | Unsure (u > 0.5) | Spearman weight | weight without photo | gap | support "
        "| normal | photo | photo NCC (scored share) | Median true error sure / unsure (cm) "
        "| True error > 10 cm |",
        "| :-- | --: | --: | --: | --: | --: | --: | --: | --: | --: | --: | --: |",
    ]
    for r in frame.itertuples():
        correlations = (
            r.spearman_weight,
            r.spearman_weight_cloud_only,
            r.spearman_gap,
            r.spearman_support,
            r.spearman_normal,
            getattr(r, "spearman_photo", float("nan")),
        )
        cells = [scene_name(r.scene), str(r.n_samples), f"{100 * r.share_unsure:.1f} %"]
        cells += [f"{c:.3f}" for c in correlations]
        cells.append(f"{r.spearman_photo_ncc_scored:.3f} ({100 * r.share_photo_scored:.0f} %)")
        cells.append(f"{100 * r.median_error_sure_m:.1f} / {100 * r.median_error_unsure_m:.1f}")
        cells.append(f"{100 * r.share_error_over_10cm:.1f} %")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run directories (one per scene is enough)")
    parser.add_argument("--n-points", type=int, default=2048, help="proxy samples (the planner's n_points)")
    parser.add_argument("--out", type=Path, default=None, help="write evidence_check.md / .json here")
    args = parser.parse_args(argv)
    from scene.registry import load_scene

    rows = []
    try:
        runs = load_runs(args.runs)
        for run in runs:
            entry = run.metrics.get("proxy_entry")
            config = read_run_config(run.run_dir)
            if not entry or config is None:
                raise RunDirectoryError(f"{run.run_dir}: no proxy_entry in metrics.json or no .hydra config")
            scene = load_scene(config.scene, cache_dir=config.get("cache_dir", "cache"))
            row = check_entry(
                ROOT / entry if not Path(entry).is_absolute() else Path(entry),
                scene.ground_truth_mesh,
                args.n_points,
                int(run.seed),
            )
            rows.append({"scene": run.scene, "entry": str(entry), **row})
            print(f"{run.scene}: Spearman(weight, true error) = {row['spearman_weight']:.3f}", flush=True)
    except (RunDirectoryError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = to_markdown(pd.DataFrame(rows).drop_duplicates("entry"))
    print(table)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.out / "evidence_check.md", table + "\n")
        write_text_atomic(args.out / "evidence_check.json", json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
