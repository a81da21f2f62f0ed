"""Cost metrics of a run (images, flight length, stage times), read from its run directory.

What is read (every file optional; a value whose source is missing is recorded as None):

- ``plan/viewpoints.csv``: ``n_viewpoints`` and ``flight_length_m`` (the polyline through the
  viewpoints in flight order, recomputed here so it cannot disagree with the flight flown).
- ``plan/plan.json``: ``plan_time_s`` from ``plan_time_s``, else ``timings_s.total``, else ``time_s``;
  ``flight_time_s`` and ``n_batteries`` (``drone.model``), computed from the viewpoints with
  the run's drone settings for plans written before they were recorded.
- ``images/cameras.json`` (the renderer's record): ``n_images`` (its ``images`` list) and
  ``render_time_s``.
- ``recon/recon.json`` (the reconstruction's record): ``registered_fraction`` (or
  ``n_registered / n_images``), ``n_registered``, ``align_time_s`` (or the sum of
  ``extraction_time_s + matching_time_s + mapping_time_s``: the paper's alignment time) and
  ``dense_time_s``, and the CPU seconds (process + children) of both, ``align_cpu_s`` and
  ``dense_cpu_s`` (records from before they existed: None); its ``n_images`` when there is no
  render record.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path

from scene.cameras_file import CAMERAS_FILE, read_cameras
from scene.plan import polyline_length, read_viewpoints

log = logging.getLogger(__name__)

COST_KEYS = (
    "n_viewpoints",
    "n_images",
    "n_registered",
    "registered_fraction",
    "flight_length_m",
    "flight_time_s",
    "n_batteries",
    "plan_time_s",
    "render_time_s",
    "align_time_s",
    "align_cpu_s",
    "dense_time_s",
    "dense_cpu_s",
)
ALIGN_PARTS = ("extraction_time_s", "matching_time_s", "mapping_time_s")


def collect_cost_metrics(run_dir: str | Path) -> dict:
    """Cost metrics of the run in ``run_dir`` (see the module docstring for the files read).

    Returns:
        A flat dict with every key of ``COST_KEYS`` (counts, fraction 0-1, metres, seconds; None
        where the run directory does not say).

    Raises:
        ValueError: a record file exists but is not a JSON object, or a value has the wrong type
            (the message names the file and key).
    """
    run_dir = Path(run_dir)
    out: dict = dict.fromkeys(COST_KEYS)

    viewpoints_csv = run_dir / "plan" / "viewpoints.csv"
    viewpoints = None
    if viewpoints_csv.is_file():
        viewpoints, _ = read_viewpoints(viewpoints_csv)
        out["n_viewpoints"] = len(viewpoints)
        out["flight_length_m"] = polyline_length(viewpoints[:, :3])

    plan = _read_json(run_dir / "plan" / "plan.json")
    out["flight_time_s"] = _number(plan, "flight_time_s", run_dir / "plan" / "plan.json")
    out["n_batteries"] = _number(plan, "n_batteries", run_dir / "plan" / "plan.json")
    if out["flight_time_s"] is None and viewpoints is not None:
        from drone.model import DroneSettings, flight_summary

        flight = flight_summary(viewpoints, DroneSettings.of_run(run_dir))
        out["flight_time_s"], out["n_batteries"] = flight["flight_time_s"], flight["n_batteries"]
    timings = plan.get("timings_s") if isinstance(plan.get("timings_s"), Mapping) else {}
    out["plan_time_s"] = _number(plan, "plan_time_s", run_dir / "plan" / "plan.json")
    if out["plan_time_s"] is None:
        out["plan_time_s"] = _number(timings, "total", run_dir / "plan" / "plan.json")
    if out["plan_time_s"] is None:
        out["plan_time_s"] = _number(plan, "time_s", run_dir / "plan" / "plan.json")
    if out["flight_length_m"] is None:
        out["flight_length_m"] = _number(plan, "flight_length_m", run_dir / "plan" / "plan.json")

    if (run_dir / "images" / CAMERAS_FILE).is_file():
        cameras = read_cameras(run_dir / "images")
        out["n_images"] = len(cameras)
        out["render_time_s"] = _number(cameras.extra, "render_time_s", run_dir / "images" / CAMERAS_FILE)

    recon_path = run_dir / "recon" / "recon.json"
    recon = _read_json(recon_path)
    if out["n_images"] is None:
        out["n_images"] = _number(recon, "n_images", recon_path)
    out["n_registered"] = _number(recon, "n_registered", recon_path)
    out["registered_fraction"] = _number(recon, "registered_fraction", recon_path)
    if out["registered_fraction"] is None and out["n_registered"] is not None and out["n_images"]:
        out["registered_fraction"] = out["n_registered"] / out["n_images"]
    out["align_time_s"] = _number(recon, "align_time_s", recon_path)
    if out["align_time_s"] is None:
        parts = [_number(recon, key, recon_path) for key in ALIGN_PARTS]
        out["align_time_s"] = sum(parts) if all(p is not None for p in parts) else None
    for key in ("dense_time_s", "align_cpu_s", "dense_cpu_s"):
        out[key] = _number(recon, key, recon_path)

    missing = [k for k, v in out.items() if v is None]
    if missing:
        log.info("cost metrics not found in %s: %s", run_dir, ", ".join(missing))
    return out


def _read_json(path: Path) -> Mapping:
    if not path.is_file():
        return {}
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(record).__name__}")
    return record


def _number(record: Mapping, key: str, source: Path):
    value = record.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{source}: {key!r} must be a number, got {value!r}")
    return value
