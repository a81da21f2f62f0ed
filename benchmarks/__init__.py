"""Benchmarks: each module times one stage (or two variants of it, one after the other) and prints a
table to quote; ``uavplan-bench NAME --help`` says what each measures."""

from __future__ import annotations

import json
from pathlib import Path


def write_records(out_dir: Path, name: str, rows: list[dict]) -> Path:
    """Write a benchmark's rows to ``out_dir/<name>.json`` and say where."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.json"
    path.write_text(json.dumps(rows, indent=1))
    print(f"records: {path}")
    return path
