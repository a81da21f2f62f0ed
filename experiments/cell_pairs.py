"""The same cells recorded twice (two machines, two proxies, two revisions), figure beside figure.

    uavplan-diagnose cell-pairs results/cells/FIRST results/cells/SECOND --out DIR

A cell of the first folder is paired with the cell of the second that has its scene, planner, seed,
budget and GSD (``target_gsd_m``); a cell recorded in one folder only is left out. Per pair: the
image counts, completeness (overall and walls, real and oracle), acc90 and the plan's forecast of
well-observed walls, first folder / second, and the largest difference of each over the pairs.
Writes ``cell_pairs.md`` and ``cell_pairs.csv`` (every field, full precision) into ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from experiments.runs import RunDirectoryError, load_runs, out_is_a_file, runs_frame, write_findings

KEYS = ("scene", "planner", "seed", "budget", "target_gsd_m")
# (field, column title, scale, format): what a reader compares between the two records of a cell.
FIELDS = (
    ("n_images", "images", 1.0, "{:.0f}"),
    ("n_registered", "registered", 1.0, "{:.0f}"),
    ("comp_050", "comp. 5 cm (%)", 1.0, "{:.1f}"),
    ("comp_050_walls", "walls (%)", 1.0, "{:.1f}"),
    ("acc90_m", "acc90 (cm)", 100.0, "{:.2f}"),
    ("oracle_comp_050", "oracle comp. (%)", 1.0, "{:.1f}"),
    ("oracle_comp_050_walls", "oracle walls (%)", 1.0, "{:.1f}"),
    ("predicted_well_observed_walls_pct", "forecast walls (%)", 1.0, "{:.1f}"),
)


def paired_cells(first: pd.DataFrame, second: pd.DataFrame) -> pd.DataFrame:
    """The cells finished in both frames, one row each: ``<field>_a`` (first) and ``<field>_b``.

    Raises:
        ValueError: no cell is recorded in both.
    """
    frames = []
    for frame in (first, second):
        ok = frame[frame["status"] == "ok"].copy()
        if "target_gsd_m" not in ok.columns:
            ok["target_gsd_m"] = float("nan")
        ok["target_gsd_m"] = ok["target_gsd_m"].astype(float).round(6).fillna(-1.0)
        fields = [f for f, *_ in FIELDS if f in ok.columns] + ["method", "proxy_fingerprint"]
        frames.append(ok[[*KEYS, *[f for f in fields if f in ok.columns]]])
    pairs = frames[0].merge(frames[1], on=list(KEYS), suffixes=("_a", "_b"))
    if pairs.empty:
        raise ValueError("no cell is recorded in both folders (matched on scene, planner, seed, budget, GSD)")
    return pairs.sort_values(list(KEYS)).reset_index(drop=True)


def to_markdown(pairs: pd.DataFrame, names: tuple[str, str]) -> str:
    """The pairs as a table (each entry: first / second) and the largest difference per field."""
    fields = [f for f in FIELDS if f"{f[0]}_a" in pairs.columns and f"{f[0]}_b" in pairs.columns]
    lines = [
        f"Each entry: `{names[0]}` / `{names[1]}`.",
        "",
        "| cell | seed | " + " | ".join(title for _, title, _, _ in fields) + " |",
        "| :-- | --: | " + " | ".join("--:" for _ in fields) + " |",
    ]
    for _, row in pairs.iterrows():
        cells = [
            f"{fmt.format(scale * row[f'{field}_a'])} / {fmt.format(scale * row[f'{field}_b'])}"
            for field, _, scale, fmt in fields
        ]
        lines.append(
            f"| {row['scene']} / {row['method_a']} | {int(row['seed'])} | " + " | ".join(cells) + " |"
        )
    lines += ["", "Largest difference over the pairs (second minus first):", ""]
    for field, title, scale, fmt in fields:
        diff = scale * (pairs[f"{field}_b"] - pairs[f"{field}_a"])
        if diff.notna().any():
            worst = diff.abs().idxmax()
            where = f"{pairs.loc[worst, 'scene']} / {pairs.loc[worst, 'method_a']}"
            lines.append(f"- {title}: {fmt.format(diff[worst])} ({where})")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan-diagnose cell-pairs FIRST SECOND --out OUT``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="uavplan-diagnose cell-pairs", description=__doc__.split("\n")[0])
    parser.add_argument("first", type=Path, help="record or run directory (searched recursively)")
    parser.add_argument("second", type=Path, help="the other one")
    parser.add_argument("--out", type=Path, required=True, help="directory for cell_pairs.md and .csv")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if out_is_a_file(args.out):
        return 2
    try:
        pairs = paired_cells(runs_frame(load_runs([args.first])), runs_frame(load_runs([args.second])))
    except (RunDirectoryError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = to_markdown(pairs, (str(args.first), str(args.second)))
    write_findings(args.out, "cell_pairs", pairs, "The same cells, recorded twice", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
