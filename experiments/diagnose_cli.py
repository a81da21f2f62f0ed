"""``uavplan-diagnose``: the diagnostics behind the study's numbers (where the error comes from,
how stable a plan is, what a cell's pair or a replanned cell shows), apart from ``uavplan-study``."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from pipeline.cli import dispatch

COMMANDS = {
    "depth-errors": "experiments.depth_errors",
    "accuracy-sources": "experiments.accuracy_sources",
    "oracle-gap": "experiments.oracle_gap",
    "cell-pairs": "experiments.cell_pairs",
    "plan-stability": "experiments.plan_stability",
    "observations": "experiments.observations",
    "replan": "experiments.replan",
    "photo-roundtrip": "experiments.photo_roundtrip",
}


def main(argv: Sequence[str] | None = None) -> int:
    return dispatch(
        "uavplan-diagnose",
        COMMANDS,
        argv,
        "Diagnostics of the study's cells: depth errors, accuracy sources, the oracle gap, plan stability.",
    )


if __name__ == "__main__":
    sys.exit(main())
