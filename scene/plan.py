"""A flight plan and its files: the contract between the planners and every stage after them.

``plan/viewpoints.csv`` (one row per viewpoint in flight order: ``index, x, y, z, yaw_deg,
pitch_deg, kind``; world frame, metres and degrees, see ``scene.camera``) and ``plan/plan.json``
(the planner's record, and ``viewpoints`` as the planner made them: the CSV's 6 decimals are
micrometres, yet a render from them differs from the cell's in a few per cent of its pixels) are
what rendering, scoring and the mission exporters read (``read_plan``).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scene.camera import VIEWPOINT_COLUMNS, validate_viewpoint_array
from scene.io import write_json_atomic, write_text_atomic


class PlanningError(RuntimeError):
    """A planner could not produce a valid plan (the message names the violated constraint)."""


@dataclass
class Plan:
    """An ordered flight.

    Attributes:
        viewpoints: (V, 5) array ``x, y, z, yaw_deg, pitch_deg`` in flight order (metres, degrees).
        kinds: V labels (``detail``, ``coverage``, ``grid``, ``oblique``, ``nadir``, ...).
        planner: planner name.
        info: parameters, per-stage timings (s), viewpoint counts, objective history, flight length.
    """

    viewpoints: np.ndarray
    kinds: list[str]
    planner: str
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.viewpoints = validate_viewpoint_array(self.viewpoints)
        if len(self.kinds) != len(self.viewpoints):
            raise ValueError(f"{len(self.kinds)} kinds for {len(self.viewpoints)} viewpoints")
        if len(self.viewpoints) == 0:
            raise PlanningError(f"planner {self.planner!r} produced no viewpoints")

    @property
    def flight_length_m(self) -> float:
        """Length in metres of the polyline through the viewpoints in flight order."""
        return polyline_length(self.viewpoints[:, :3])


def polyline_length(positions) -> float:
    """Length in metres of the polyline through ``positions`` (N, 3) in order."""
    p = np.asarray(positions, dtype=float)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def write_plan(plan: Plan, plan_dir: str | Path) -> Path:
    """Write ``viewpoints.csv`` and ``plan.json`` into ``plan_dir`` atomically; return the dir."""
    plan_dir = Path(plan_dir)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["index", *VIEWPOINT_COLUMNS, "kind"])
    for i, (row, kind) in enumerate(zip(plan.viewpoints, plan.kinds, strict=True)):
        writer.writerow([i, *(f"{v:.6f}" for v in row), kind])
    write_text_atomic(plan_dir / "viewpoints.csv", buf.getvalue())
    record = {
        "planner": plan.planner,
        "n_viewpoints": len(plan.viewpoints),
        "flight_length_m": plan.flight_length_m,
        "kinds": {k: plan.kinds.count(k) for k in sorted(set(plan.kinds))},
        **plan.info,
        "viewpoints": plan.viewpoints.tolist(),
    }
    write_json_atomic(plan_dir / "plan.json", record)
    return plan_dir


def read_plan(plan_dir: str | Path) -> tuple[np.ndarray, list[str]]:
    """A plan folder's views (V, 5) and kinds: ``viewpoints.csv``, at full precision where
    ``plan.json`` holds the same views (a CSV edited by hand wins)."""
    plan_dir = Path(plan_dir)
    viewpoints, kinds = read_viewpoints(plan_dir / "viewpoints.csv")
    record_path = plan_dir / "plan.json"
    if record_path.is_file():
        exact = json.loads(record_path.read_text()).get("viewpoints")
        if exact is not None:
            exact = np.asarray(exact, dtype=float)
            if exact.shape == viewpoints.shape and np.allclose(exact, viewpoints, rtol=0.0, atol=6e-7):
                return exact, kinds
    return viewpoints, kinds


def read_viewpoints(csv_path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Read a ``viewpoints.csv``; return the (V, 5) array in file order and the kinds."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise FileNotFoundError(f"viewpoint file not found: {csv_path}")
    with csv_path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = {"index", *VIEWPOINT_COLUMNS} - set(reader.fieldnames or [])
        if missing:
            raise ValueError(f"{csv_path}: missing columns {sorted(missing)}")
        rows = list(reader)
    try:
        arr = np.array([[float(r[c]) for c in VIEWPOINT_COLUMNS] for r in rows], dtype=float)
    except ValueError as exc:
        raise ValueError(f"{csv_path}: {exc}") from exc
    kinds = [r.get("kind") or "unknown" for r in rows]
    try:
        return validate_viewpoint_array(arr.reshape(-1, 5)), kinds
    except ValueError as exc:
        raise ValueError(f"{csv_path}: {exc}") from exc
