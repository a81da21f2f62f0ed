"""Export a plan as a mission a drone flies.

    uavplan-mission RUN_DIR --format qgc|litchi|wpml --out FILE
    uavplan-mission viewpoints.csv --origin LAT,LON[,HEIGHT[,X_AXIS_HEADING]] --format wpml --out m.kmz

A run directory brings its own ``survey.origin`` and ``drone`` settings (``.hydra/config.yaml``);
a bare ``viewpoints.csv`` needs ``--origin``. A mission longer than one battery or than a
controller accepts is written as numbered files. Errors print one line and exit 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mission.export import default_settings, export_mission, run_settings
from mission.geo import MissionError, SurveyOrigin
from scene.plan import read_viewpoints


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-mission", description=__doc__.split("\n")[0])
    parser.add_argument(
        "plan", type=Path, help="a run directory (with plan/viewpoints.csv) or a viewpoints.csv"
    )
    parser.add_argument("--format", required=True, choices=("qgc", "litchi", "wpml"))
    parser.add_argument("--out", type=Path, required=True, help="mission file (.plan, .csv or .kmz)")
    parser.add_argument("--origin", help="LAT,LON[,HEIGHT_M[,X_AXIS_HEADING_DEG]] of local (0, 0, 0)")
    parser.add_argument("--traceback", action="store_true", help="show the Python traceback on an error")
    args = parser.parse_args(argv)
    try:
        return export(args)
    except (OSError, ValueError) as exc:  # MissionError is a ValueError
        if args.traceback:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2


def export(args: argparse.Namespace) -> int:

    if args.plan.is_dir():
        csv_path = args.plan / "plan" / "viewpoints.csv"
        if not csv_path.is_file():
            raise MissionError(f"{args.plan}: no plan (plan/viewpoints.csv is missing)")
        origin, drone = run_settings(args.plan)
    elif args.plan.is_file():
        if args.origin is None:
            raise MissionError(
                f"{args.plan}: a bare viewpoint file needs --origin LAT,LON[,HEIGHT[,HEADING]]"
            )
        csv_path = args.plan
        origin, drone = default_settings()
    else:
        raise MissionError(f"{args.plan}: no such run directory or viewpoint file")
    if args.origin is not None:
        origin = SurveyOrigin.parse(args.origin)
    viewpoints, _ = read_viewpoints(csv_path)
    mission, paths = export_mission(viewpoints, origin, drone, args.format, args.out)
    minutes = mission.flight_time_s / 60.0
    print(
        f"{len(viewpoints)} waypoints, {len(mission.flights)} flight(s) / batteries, "
        f"{minutes:.1f} min flying: " + ", ".join(str(p) for p in paths)
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
