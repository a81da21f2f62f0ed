"""Export a plan to mission files: settings from the run (or the defaults), one file per flight.

``export_mission`` is what ``uavplan-mission`` runs; the formats are ``FORMATS``' modules, each with
``render(mission) -> list[bytes]`` (one file per flight), ``SUFFIX`` and ``MAX_WAYPOINTS`` (the
app's own cap per file, or None).
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
from omegaconf import OmegaConf

from drone.model import DroneSettings
from mission import litchi, qgc, wpml
from mission.geo import MissionError, SurveyOrigin
from mission.model import Mission, build_mission
from scene.config import plain
from scene.io import write_atomic

FORMATS: dict[str, ModuleType] = {"qgc": qgc, "litchi": litchi, "wpml": wpml}
CONF_DIR = Path(__file__).resolve().parent.parent / "conf"


def default_settings() -> tuple[SurveyOrigin, DroneSettings]:
    """The survey origin and drone of ``conf/config.yaml`` and ``conf/drone/default.yaml``."""
    origin = OmegaConf.load(CONF_DIR / "config.yaml").survey.origin
    return SurveyOrigin.from_config(plain(origin)), DroneSettings.default()


def run_settings(run_dir: Path) -> tuple[SurveyOrigin, DroneSettings]:
    """The run's own ``survey.origin`` and ``drone`` (``.hydra/config.yaml``), else the defaults."""
    origin = default_settings()[0]
    config_path = run_dir / ".hydra" / "config.yaml"
    if config_path.is_file():
        node = OmegaConf.select(OmegaConf.load(config_path), "survey.origin")
        if node is not None:
            origin = SurveyOrigin.from_config(plain(node))
    return origin, DroneSettings.of_run(run_dir)


def output_paths(out: Path, n_files: int) -> list[Path]:
    """``out`` for one file; ``<stem>_<k>of<n><suffix>`` (k from 1) for several."""
    if n_files == 1:
        return [out]
    return [out.with_name(f"{out.stem}_{k}of{n_files}{out.suffix}") for k in range(1, n_files + 1)]


def export_mission(
    viewpoints: np.ndarray,
    origin: SurveyOrigin,
    drone: DroneSettings,
    fmt: str,
    out: Path,
    max_waypoints: int | None = None,
) -> tuple[Mission, list[Path]]:
    """Check, split and write ``viewpoints`` (V, 5) as ``fmt`` mission file(s) at ``out``.

    Every file is rendered before the first is written, and each is written atomically: a plan that
    cannot be flown leaves no file behind. ``max_waypoints``: the controller app's cap per file
    (``mission.controllers``), beside the drone's and the format's own.
    """
    if fmt not in FORMATS:
        raise MissionError(f"unknown mission format {fmt!r}; choose one of {sorted(FORMATS)}")
    module = FORMATS[fmt]
    cap = min(c for c in (drone.max_waypoints_per_file, module.MAX_WAYPOINTS, max_waypoints) if c is not None)
    mission = build_mission(viewpoints, origin, drone, max_waypoints=cap)
    contents = module.render(mission)
    paths = output_paths(Path(out), len(contents))
    for path, content in zip(paths, contents, strict=True):
        write_atomic(path, lambda p, c=content: p.write_bytes(c))
    return mission, paths
