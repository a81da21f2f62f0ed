"""Wall and CPU time of a stage: the CPU figure (process and children, user and system) is what a
shared machine cannot blur; on N free cores a stage's CPU time lies between its wall time (one busy
thread) and N times it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass


@dataclass
class StageTime:
    """Seconds a stage took: ``wall_s`` on the clock, ``cpu_s`` of CPU in this process (every thread)
    and its child processes (user + system)."""

    wall_s: float = 0.0
    cpu_s: float = 0.0


def cpu_seconds() -> float:
    """CPU seconds so far of this process (every thread) and its waited-for children (user + system)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


@contextmanager
def stage_time() -> Iterator[StageTime]:
    """Time the block: ``with stage_time() as t: ...`` then ``t.wall_s``, ``t.cpu_s`` (filled on exit).

    Children count once they have been waited for (``os.times``), as every subprocess a stage runs is.
    """
    timing = StageTime()
    wall, cpu = time.perf_counter(), cpu_seconds()
    try:
        yield timing
    finally:
        timing.wall_s = time.perf_counter() - wall
        timing.cpu_s = cpu_seconds() - cpu
