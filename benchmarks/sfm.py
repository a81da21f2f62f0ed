"""SfM before and after: one rendered flight through variants of the SfM settings, each timed per
stage (wall and CPU: process + children) and checked against the true poses.

    uavplan-bench sfm study/default_v3/tomb/ours/seed0/images \\
        --variant spatial= --variant pose_prior=matching.method=pose_prior

A variant is ``NAME=KEY=VALUE,...`` over ``conf/reconstruct/default.yaml``'s ``sfm`` section
(``NAME=`` alone: the defaults). Each variant extracts, matches and maps the flight from scratch
into ``--out/<name>``, aligns and merges its models to the simulated GNSS fixes (seed 0) as a cell
does, and reports the registered images and camera errors. Run it on an idle machine and quote
the table it prints.

``--database RUN/recon/database.db`` maps a copy of a cell's database instead (its features,
pairs and GNSS priors as they are): only the mapping settings and the prior check of the pairs
(``matching.prior_check``, timed as matching) vary; extraction shows 0.

    uavplan-bench sfm RUN/images --database RUN/recon/database.db \\
        --variant default= --variant skip=mapping.global_ba_skip_redundant_points=true
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from omegaconf import OmegaConf

from benchmarks import write_records
from benchmarks.dense import parse_variant
from reconstruct.align import georeference_models, pose_errors
from reconstruct.flight import read_flight, simulate_gnss
from reconstruct.settings import ReconstructSettings
from reconstruct.sfm import SfmResult, check_pairs, map_reconstruction, run_sfm, sfm_options
from reconstruct.sfm_settings import SfmSettings
from reconstruct.timing import stage_time

ROOT = Path(__file__).resolve().parents[1]

STAGES = ("extraction", "matching", "mapping")


def map_database(database: Path, flight, gnss, out_dir: Path, sfm_cfg, seed: int):
    """Map a copy of ``database`` (features, pairs and priors already there) with ``sfm_cfg``, after
    its prior check of the pairs (``matching.prior_check``) when that is on."""
    # heavy (pycolmap): imported on use
    import pycolmap

    out_dir.mkdir(parents=True, exist_ok=True)
    copy = out_dir / "database.db"
    shutil.copyfile(database, copy)
    options = sfm_options(SfmSettings.from_config(sfm_cfg), seed)
    pycolmap.set_random_seed(int(seed))
    with stage_time() as check:
        n_rejected = check_pairs(copy, flight, gnss, options, seed)
    with stage_time() as clock:
        models = map_reconstruction(copy, flight.image_dir, options)
    n_pairs = pycolmap.Database.open(copy).num_matched_image_pairs()
    times = {"extraction": 0.0, "matching": check.wall_s, "mapping": clock.wall_s}
    cpu = {"extraction": 0.0, "matching": check.cpu_s, "mapping": clock.cpu_s}
    return SfmResult(models, "database", times, cpu, n_pairs, n_rejected)


def run_variant(
    image_dir: Path, out_dir: Path, overrides: list[str], seed: int = 0, database: Path | None = None
) -> dict:
    """SfM, GNSS alignment and merging of the flight in ``image_dir`` with ``overrides``
    (only mapping, from a copy of ``database``, when given)."""
    cfg = OmegaConf.load(ROOT / "conf" / "reconstruct" / "default.yaml")
    unknown = [o.split("=")[0] for o in overrides if OmegaConf.select(cfg.sfm, o.split("=")[0]) is None]
    if unknown:
        raise ValueError(f"unknown sfm settings {unknown}")
    sfm_cfg = OmegaConf.merge(cfg.sfm, OmegaConf.from_dotlist(overrides))
    align = ReconstructSettings.from_config(cfg).align
    flight = read_flight(image_dir)
    sigma = float(cfg.gnss.sigma_m)
    gnss = simulate_gnss(flight.positions, sigma, seed)
    if database is None:
        sfm = run_sfm(flight, out_dir, gnss, sigma, SfmSettings.from_config(sfm_cfg), seed)
    else:
        sfm = map_database(database, flight, gnss, out_dir, sfm_cfg, seed)
    model, merged = georeference_models(sfm.models, flight.names, gnss, sigma, align, seed)
    record = {f"{s}_time_s": sfm.times_s[s] for s in STAGES} | {f"{s}_cpu_s": sfm.cpu_s[s] for s in STAGES}
    record |= {
        "n_image_pairs": sfm.n_image_pairs,
        "n_pairs_rejected": sfm.n_pairs_rejected,
        "model_sizes": merged["model_sizes"],
    }
    return record | pose_errors(model, flight)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("image_dir", type=Path, help="a rendered flight (images + cameras.json)")
    parser.add_argument("--variant", action="append", required=True, help="NAME=KEY=VALUE,... (repeatable)")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "bench_sfm")
    parser.add_argument(
        "--database", type=Path, help="map a copy of this database (mapping and prior-check variants only)"
    )
    args = parser.parse_args(argv)
    try:
        variants = [parse_variant(v) for v in args.variant]
        if not (args.image_dir / "cameras.json").is_file():
            raise ValueError(f"{args.image_dir}: no cameras.json (not a rendered flight)")
        if args.database is not None and not args.database.is_file():
            raise ValueError(f"{args.database}: no such database")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    header = (
        f"{'variant':>12} "
        + " ".join(f"{s[:7] + ' s':>10} {'cpu':>6}" for s in STAGES)
        + f" {'total s':>8} {'cpu':>7} {'pairs':>6} {'dropped':>7} {'models':>9}"
        + f" {'reg':>5} {'pos med m':>9} {'p90 m':>6} {'rot max':>7}"
    )
    print(f"{args.image_dir}, {os.cpu_count()} cores\n{header}", flush=True)
    rows = {}
    for name, overrides in variants:
        try:
            r = run_variant(args.image_dir, args.out / name, overrides, database=args.database)
        except ValueError as exc:
            print(f"error: variant {name}: {exc}", file=sys.stderr)
            return 2
        rows[name] = r | {"overrides": overrides}
        wall = sum(r[f"{s}_time_s"] for s in STAGES)
        cpu = sum(r[f"{s}_cpu_s"] for s in STAGES)
        print(
            f"{name:>12} "
            + " ".join(f"{r[f'{s}_time_s']:>10.1f} {r[f'{s}_cpu_s']:>6.0f}" for s in STAGES)
            + f" {wall:>8.1f} {cpu:>7.0f} {r['n_image_pairs']:>6d} {r['n_pairs_rejected']:>7d}"
            + f" {r['model_sizes']:>9} {r['n_registered']:>5d}"
            + f" {r['position_error_median_m']:>9.3f} {r['position_error_p90_m']:>6.3f}"
            + f" {r['rotation_error_max_deg']:>7.1f}",
            flush=True,
        )
    write_records(args.out, "bench_sfm", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
