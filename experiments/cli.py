"""``uavplan-study``: the study's tools (records, tables, fronts, figures, checks) as one command."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from pipeline.cli import dispatch

COMMANDS = {
    "record": "experiments.record",
    "results": "experiments.results",
    "tables": "experiments.tables",
    "figures": "experiments.figures",
    "fronts": "experiments.fronts",
    "noise-floor": "experiments.noise_floor",
    "replan": "experiments.replan",
    "observations": "experiments.observations",
    "depth-errors": "experiments.depth_errors",
    "plan-stability": "experiments.plan_stability",
    "ours-plus-front": "experiments.ours_plus_front",
    "viewer": "experiments.viewer",
    "photo-roundtrip": "experiments.photo_roundtrip",
    "oracle-gap": "experiments.oracle_gap",
    "accuracy-sources": "experiments.accuracy_sources",
    "cell-pairs": "experiments.cell_pairs",
    "study-plan": "experiments.study_plan",
    "proxies": "experiments.proxies",
}


def main(argv: Sequence[str] | None = None) -> int:
    return dispatch(
        "uavplan-study", COMMANDS, argv, "The study: cell records in, tables, fronts and figures out."
    )


if __name__ == "__main__":
    sys.exit(main())
