"""``uavplan-bench``: the benchmarks, one sub-command each."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from pipeline.cli import dispatch

COMMANDS = {
    name.replace("_", "-"): f"benchmarks.{name}"
    for name in (
        "baselines",
        "dense",
        "dense_cuda",
        "evaluate",
        "fusion",
        "large_mesh",
        "planner",
        "reconstruct",
        "render",
        "sfm",
    )
}


def main(argv: Sequence[str] | None = None) -> int:
    return dispatch("uavplan-bench", COMMANDS, argv, "Benchmarks: time a stage, compare two settings.")


if __name__ == "__main__":
    sys.exit(main())
