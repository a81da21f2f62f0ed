"""The real reconstruction against its oracle ceiling, cell by cell: does the matcher rank the plans
as a perfect one would?

    uavplan-diagnose oracle-gap multirun/<date> results/... --out archive/pre_p1/oracle_gap

Every cell scored with ``reconstruct.oracle_beside`` carries ``oracle_*`` fields in its
``metrics.json``: the ground truth ray-cast at the registered SfM cameras with the stereo noise
model, fused like the real depth maps. Per metric (completeness at 5 cm, acc90), this prints and
writes (``oracle_gap.md``, ``oracle_gap.csv``) each cell's real and oracle values, their Spearman
rank correlation over the cells and the cell with the largest gap (oracle minus real completeness;
real minus oracle acc90).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence

import pandas as pd

from experiments.runs import (
    RunDirectoryError,
    load_runs,
    out_is_a_file,
    runs_frame,
    tool_parser,
    write_findings,
)

# (metric, its oracle field, the sign that makes "gap" the real reconstruction's shortfall)
METRICS = (("comp_050", "oracle_comp_050", 1.0), ("acc90_m", "oracle_acc90_m", -1.0))
MIN_CELLS = 3  # a rank correlation over fewer says nothing


def gap_frame(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per finished cell with oracle fields: its name, real and oracle values, gaps."""
    ok = runs[runs["status"] == "ok"]
    missing = [field for _, field, _ in METRICS if field not in ok.columns]
    if missing:
        raise ValueError(f"no cell has {missing} (run the cells with reconstruct.oracle_beside=true)")
    ok = ok.dropna(subset=[m for m, _, _ in METRICS] + [f for _, f, _ in METRICS])
    if len(ok) < MIN_CELLS:
        raise ValueError(f"{len(ok)} cells with real and oracle values; a rank correlation needs {MIN_CELLS}")
    out = pd.DataFrame(
        {
            "scene": ok["scene"],
            "method": ok["method"],
            "seed": ok["seed"],
            "n_images": ok.get("n_images"),
        }
    )
    for metric, field, sign in METRICS:
        out[metric] = ok[metric]
        out[field] = ok[field]
        out[f"{metric}_gap"] = sign * (ok[field] - ok[metric])
    return out.reset_index(drop=True)


def rank_agreement(cells: pd.DataFrame) -> dict[str, dict]:
    """Per metric: Spearman's rho of real against oracle over the cells, and the largest gap's cell."""
    summary = {}
    for metric, field, _ in METRICS:
        rho = cells[metric].corr(cells[field], method="spearman")
        worst = cells.loc[cells[f"{metric}_gap"].idxmax()]
        summary[metric] = {
            "spearman": float(rho),
            "largest_gap": float(worst[f"{metric}_gap"]),
            "largest_gap_cell": f"{worst['scene']} / {worst['method']} / seed {int(worst['seed'])}",
        }
    return summary


def to_markdown(cells: pd.DataFrame, summary: dict[str, dict]) -> str:
    lines = [
        "| scene | method | seed | images | comp. 5 cm real / oracle (%) | acc90 real / oracle (cm) |",
        "| :-- | :-- | --: | --: | --: | --: |",
    ]
    for row in cells.itertuples():
        lines.append(
            f"| {row.scene} | {row.method} | {row.seed} | {int(row.n_images)} | "
            f"{row.comp_050:.1f} / {row.oracle_comp_050:.1f} | "
            f"{100 * row.acc90_m:.2f} / {100 * row.oracle_acc90_m:.2f} |"
        )
    comp, acc = summary["comp_050"], summary["acc90_m"]
    lines += [
        "",
        f"{len(cells)} cells. Completeness at 5 cm: Spearman rho {comp['spearman']:.2f} between real and "
        f"oracle; largest shortfall {comp['largest_gap']:.1f} points ({comp['largest_gap_cell']}). "
        f"acc90: rho {acc['spearman']:.2f}; largest excess {100 * acc['largest_gap']:.2f} cm "
        f"({acc['largest_gap_cell']}).",
    ]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: ``uavplan-diagnose oracle-gap DIR... --out OUT``; returns the exit status."""
    parser = tool_parser("uavplan-diagnose oracle-gap", __doc__, "directory for oracle_gap.md and .csv")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if out_is_a_file(args.out):
        return 2
    try:
        cells = gap_frame(runs_frame(load_runs(args.dirs)))
    except (RunDirectoryError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = rank_agreement(cells)
    text = to_markdown(cells, summary)
    write_findings(args.out, "oracle_gap", cells, "Real reconstruction against its oracle", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
