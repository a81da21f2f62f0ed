"""``uavplan-study``: the study's own tools (records, proxies, tables, fronts, figures, the noise
floor) as one command. The diagnostics are ``uavplan-diagnose`` (``experiments.diagnose_cli``); a
plan's interactive view is ``uavplan view``."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from pipeline.cli import dispatch

COMMANDS = {
    "record": "experiments.record",
    "results": "experiments.results",
    "study-plan": "experiments.study_plan",
    "proxies": "experiments.proxies",
    "tables": "experiments.tables",
    "figures": "experiments.figures",
    "fronts": "experiments.fronts",
    "noise-floor": "experiments.noise_floor",
    "ours-plus-front": "experiments.ours_plus_front",
}


def main(argv: Sequence[str] | None = None) -> int:
    return dispatch(
        "uavplan-study", COMMANDS, argv, "The study: cell records in, tables, fronts and figures out."
    )


if __name__ == "__main__":
    sys.exit(main())
