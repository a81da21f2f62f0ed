"""Finding and loading run directories (the run-directory contract: docs/architecture.md).

A run directory is any folder holding a ``metrics.json``; single runs (``outputs/...``) and sweeps
(``multirun/DATE/<scene>/<planner>/seed<N>/``) are found the same way, recursively.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh
from omegaconf import OmegaConf

from planner.budget import DEFAULT_LEVEL, LEVELS, level_rank
from scene.camera import Intrinsics
from scene.io import write_text_atomic
from scene.plan import read_viewpoints

log = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"
CONFIG_FILE = Path(".hydra") / "config.yaml"
VIEWPOINTS_FILE = Path("plan") / "viewpoints.csv"
PLAN_FILE = Path("plan") / "plan.json"

# Display names and order of the methods (baselines first, ours last, as in the paper's tables).
METHOD_NAMES = {
    "lawnmower": "Lawnmower",
    "smith": "Smith et al.",
    "yan": "Yan et al.",
    "ours": "Ours",
    "ours_plus": "Ours+",
}
METHOD_ORDER = ("lawnmower", "smith", "yan", "ours")
SCENE_ORDER = ("tomb", "church", "cathedral")


class RunDirectoryError(ValueError):
    """A directory given by the user holds no runs, or a run's files break the contract."""


@dataclass(frozen=True)
class Run:
    """One run directory and its ``metrics.json`` record."""

    run_dir: Path
    metrics: Mapping

    @property
    def scene(self) -> str:
        """Scene name (e.g. ``tomb``)."""
        return str(self.metrics["scene"])

    @property
    def planner(self) -> str:
        """Planner name (e.g. ``ours``)."""
        return str(self.metrics["planner"])

    @property
    def seed(self) -> int:
        """Random seed of the run."""
        return int(self.metrics["seed"])

    @property
    def budget(self) -> str:
        """Image budget level (``planner.budget``); runs that predate budgets ran at ``default``."""
        return str(self.metrics.get("budget") or DEFAULT_LEVEL)

    @property
    def gsd_m(self) -> float | None:
        """The survey's target GSD (m/px, ``survey.target_gsd_m``); None for a run from before it was
        recorded (every such study cell flew the default 3 cm, ours' former GSD budgets aside)."""
        value = self.metrics.get("target_gsd_m")
        return None if value is None else float(value)

    @property
    def ok(self) -> bool:
        """True when the run recorded ``status: ok`` (or no status); any other status counts as failed."""
        return self.metrics.get("status", "ok") == "ok"

    @property
    def error(self) -> str:
        """The recorded error message of a failed run ('' for a run that succeeded)."""
        return "" if self.ok else str(self.metrics.get("error") or "unknown error")


def method_name(planner: str, budget: str = DEFAULT_LEVEL) -> str:
    """Display name of a planner (``smith`` -> ``Smith et al.``); unknown names are title-cased; a
    budget other than the default is named after it (``Smith et al. (high budget)``)."""
    name = METHOD_NAMES.get(planner, planner.replace("_", " ").title())
    return name if budget == DEFAULT_LEVEL else f"{name} ({budget} budget)"


def scene_name(scene: str) -> str:
    """Display name of a scene (``tomb`` -> ``Tomb``)."""
    return scene.replace("_", " ").title()


def scene_sort_key(scene: str) -> tuple:
    """Sort key: the paper's scenes first (tomb, church, cathedral), then the others by name."""
    return (SCENE_ORDER.index(scene), "") if scene in SCENE_ORDER else (len(SCENE_ORDER), scene)


def method_sort_key(planner: str) -> tuple:
    """Sort key: lawnmower, smith, yan, then other planners by name, ours last."""
    if planner == "ours":
        return (3, "")
    if planner in METHOD_ORDER:
        return (0, f"{METHOD_ORDER.index(planner)}")
    return (1, planner)


def find_run_dirs(path: str | Path) -> list[Path]:
    """All run directories (folders with a ``metrics.json``) at or below ``path``, sorted.

    Raises:
        RunDirectoryError: ``path`` does not exist or holds no run.
    """
    path = Path(path)
    if not path.exists():
        raise RunDirectoryError(f"run directory not found: {path}")
    if path.is_file():
        if path.name != METRICS_FILE:
            raise RunDirectoryError(f"{path} is a file, not a run directory or a {METRICS_FILE}")
        return [path.parent]
    dirs = sorted({p.parent for p in path.rglob(METRICS_FILE) if p.is_file()})
    if not dirs:
        raise RunDirectoryError(f"no run found under {path} (no {METRICS_FILE} at or below it)")
    return dirs


def read_metrics(run_dir: str | Path) -> dict:
    """The ``metrics.json`` record of a run, checked for the keys every run must have.

    Raises:
        RunDirectoryError: the file is missing, is not JSON, or lacks scene/planner.
    """
    path = Path(run_dir) / METRICS_FILE
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise RunDirectoryError(f"{path}: not found") from exc
    except json.JSONDecodeError as exc:
        raise RunDirectoryError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(record, dict):
        raise RunDirectoryError(f"{path}: expected a JSON object, got {type(record).__name__}")
    config = None
    for key in ("scene", "planner"):
        if not record.get(key):
            # Older or crashed runs may lack the names; the composed config still has them.
            config = config if config is not None else read_run_config(run_dir)
            value = _config_name(config, key)
            if value is None:
                raise RunDirectoryError(f"{path}: missing {key!r} and no {CONFIG_FILE} names it")
            record[key] = value
    if record.get("seed") is None:
        config = config if config is not None else read_run_config(run_dir)
        record["seed"] = int(config.get("seed", 0)) if config is not None else 0
    budget = record.get("budget") or DEFAULT_LEVEL
    if budget not in LEVELS:
        raise RunDirectoryError(f"{path}: unknown budget {budget!r} (one of {', '.join(LEVELS)})")
    status = record.setdefault("status", "ok")
    if status != "ok" and not record.get("error"):
        # e.g. "running" from a run killed between writes: count it as failed, saying why.
        record["error"] = f"run ended with status {status!r}"
    return record


def _config_name(config, key: str) -> str | None:
    if config is None or key not in config:
        return None
    node = config[key]
    if isinstance(node, str):
        return node
    return str(node["name"]) if "name" in node else None


def load_runs(paths: Iterable[str | Path]) -> list[Run]:
    """Every run at or below each of ``paths``, one per (scene, planner, seed), in table order.

    When the same (scene, planner, budget, GSD, seed) occurs in several directories (a re-run), the one whose
    ``metrics.json`` is newest is kept and the others are logged: repeating a seed is not a new sample.

    Raises:
        RunDirectoryError: a path does not exist, holds no run, or a run breaks the contract.
    """
    paths = list(paths)
    if not paths:
        raise RunDirectoryError("no run directory given")
    by_key: dict[tuple, Run] = {}
    for path in paths:
        for run_dir in find_run_dirs(path):
            run = Run(run_dir.resolve(), read_metrics(run_dir))
            key = (run.scene, run.planner, run.budget, run.gsd_m, run.seed)
            if key in by_key and by_key[key].run_dir != run.run_dir:
                kept, dropped = sorted([by_key[key], run], key=_metrics_mtime, reverse=True)
                log.warning(
                    "%s/%s (%s budget, GSD %s) seed %d: using %s, ignoring older %s",
                    *key,
                    kept.run_dir,
                    dropped.run_dir,
                )
                run = kept
            by_key[key] = run
    return sorted(by_key.values(), key=run_sort_key)


def run_sort_key(run: Run) -> tuple:
    """Table order: scene, method, budget (fewest images first), GSD (coarsest first), seed."""
    gsd = -run.gsd_m if run.gsd_m is not None else 0.0
    return (scene_sort_key(run.scene), method_sort_key(run.planner), level_rank(run.budget), gsd, run.seed)


def _metrics_mtime(run: Run) -> float:
    return (run.run_dir / METRICS_FILE).stat().st_mtime


def runs_frame(runs: Iterable[Run]) -> pd.DataFrame:
    """One row per run: the scalar fields of ``metrics.json`` plus ``run_dir`` and ``method``.

    Nested fields (``versions``, ``paths``) are kept as JSON strings; ``null`` numbers become NaN.
    """
    rows = []
    for run in runs:
        row = {
            "scene": run.scene,
            "planner": run.planner,
            "method": method_name(run.planner, run.budget),
            "budget": run.budget,
            "seed": run.seed,
            "status": "ok" if run.ok else "failed",
            "error": run.error,
        }
        for key, value in run.metrics.items():
            if key in row:
                continue
            row[key] = json.dumps(value, sort_keys=True) if isinstance(value, dict | list) else value
        row["run_dir"] = str(run.run_dir)
        rows.append(row)
    return pd.DataFrame(rows)


def read_run_config(run_dir: str | Path):
    """The composed Hydra config (``.hydra/config.yaml``) of a run as a DictConfig, or None if absent."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        return None

    try:
        return OmegaConf.load(path)
    except Exception as exc:  # noqa: BLE001 - any YAML error is reported with the file name
        raise RunDirectoryError(f"{path}: cannot read the run's config ({exc})") from exc


def read_plan_record(run_dir: str | Path) -> dict:
    """The run's ``plan/plan.json`` record, or a cell record folder's ``plan.json`` ({} if neither)."""
    path = Path(run_dir) / PLAN_FILE
    if not path.is_file():
        path = Path(run_dir) / PLAN_FILE.name
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise RunDirectoryError(f"{path}: not valid JSON ({exc})") from exc


def read_run_viewpoints(run_dir: str | Path) -> tuple[np.ndarray, list[str]] | None:
    """The run's planned viewpoints ((V, 5) array in flight order, kinds), or None if it has no plan."""
    path = Path(run_dir) / VIEWPOINTS_FILE
    if not path.is_file():
        return None
    try:
        return read_viewpoints(path)
    except ValueError as exc:
        raise RunDirectoryError(str(exc)) from exc


def run_intrinsics(run_dir: str | Path) -> Intrinsics | None:
    """The survey camera of a run: ``camera`` of ``.hydra/config.yaml``, else of ``plan.json``, else None."""
    sources = []
    config = read_run_config(run_dir)
    if config is not None and "camera" in config:
        sources.append((Path(run_dir) / CONFIG_FILE, config["camera"]))
    plan = read_plan_record(run_dir)
    for key in ("camera", "intrinsics"):
        if isinstance(plan.get(key), Mapping):
            sources.append((Path(run_dir) / PLAN_FILE, plan[key]))
    for path, camera in sources:
        try:
            return Intrinsics(int(camera["width"]), int(camera["height"]), float(camera["hfov_deg"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise RunDirectoryError(f"{path}: camera needs width, height and hfov_deg ({exc})") from exc
    return None


def recorded_path(run: Run, *names: str, file_name: str | None = None) -> Path | None:
    """The first existing file recorded in the run's metrics under one of ``names``.

    A name is looked up as a flat key of ``metrics.json`` (``gt_mesh_path``: the contract) and in a
    nested ``paths`` mapping. Relative paths are taken relative to the run directory; an absolute
    path that no longer exists (a run directory copied from a cluster) is looked for by its file
    name in the run's ``eval/`` and the run directory itself. A recorded directory counts when it
    holds ``file_name``.
    """
    nested = run.metrics.get("paths")
    nested = nested if isinstance(nested, Mapping) else {}
    for name in names:
        value = run.metrics.get(name) or nested.get(name)
        if not value or not isinstance(value, str | os.PathLike):
            continue
        path = Path(value)
        candidates = [path] if path.is_absolute() else [run.run_dir / path]
        candidates += [run.run_dir / "eval" / path.name, run.run_dir / path.name]
        for candidate in candidates:
            if candidate.is_dir() and file_name is not None:
                candidate = candidate / file_name
            if candidate.is_file():
                return candidate
    return None


# Keys of ``metrics['paths']`` (or ``plan.json``) that name meshes a figure can draw under a flight.
# (evaluate.run records ``gt_mesh_path``: the ground truth cut to the evaluation region; run.py
# records the exploration cache entry holding ``proxy.ply`` as ``proxy_entry``.)
GROUND_TRUTH_PATH_KEYS = ("gt_mesh_path", "ground_truth_mesh", "gt_mesh")
PROXY_PATH_KEYS = ("proxy_path", "proxy_mesh_path", "proxy_mesh", "proxy_entry")
PROXY_FILE = "proxy.ply"
# Ground-truth faces kept for display: those within this many metres (sideways) of the evaluation region.
DISPLAY_MARGIN_M = 5.0


def run_scene_mesh(run: Run, prefer: str = "ground_truth"):
    """A mesh to draw under a run's flight: the ground truth or the proxy, whichever is found first.

    Looks, in the order ``prefer`` sets, for the ground-truth mesh (the file recorded in
    ``metrics.json``, else ``scene.registry.load_scene(cfg.scene).ground_truth_mesh`` from the
    run's ``.hydra/config.yaml``) and the proxy (a file or cache entry recorded in ``metrics.json``
    or ``plan.json``).

    Returns:
        (trimesh.Trimesh, label) with label ``"ground truth"`` or ``"proxy"``, or (None, "") if none is found.
    """
    if prefer not in ("ground_truth", "proxy"):
        raise ValueError(f"prefer must be 'ground_truth' or 'proxy', got {prefer!r}")
    loaders = [_ground_truth_mesh, _proxy_mesh]
    if prefer == "proxy":
        loaders.reverse()
    for loader in loaders:
        found = loader(run)
        if found is not None:
            return found
    return None, ""


def _load_mesh_file(path: Path):

    mesh = trimesh.load(path, force="mesh", process=False)
    return mesh if len(getattr(mesh, "faces", ())) else None


def _ground_truth_mesh(run: Run):
    path = recorded_path(run, *GROUND_TRUTH_PATH_KEYS)
    if path is not None:
        mesh = _load_mesh_file(path)
        if mesh is not None:
            return mesh, "ground truth"
    config = read_run_config(run.run_dir)
    if config is None or "scene" not in config:
        return None
    try:
        # optional dependency: imported on use
        from scene.registry import load_scene
    except ImportError:
        log.info("scene.registry is not available: no ground-truth mesh for %s", run.run_dir)
        return None
    try:
        scene = load_scene(config.scene, cache_dir=config.get("cache_dir", "cache"))
    except Exception as exc:  # noqa: BLE001 - a figure without the mesh beats no figure
        log.warning("cannot load the scene of %s (%s): drawing the flight without it", run.run_dir, exc)
        return None
    # The scene's ground reaches tens of metres past the structure: keep the part around it.
    mesh = scene.ground_truth_mesh
    region = scene.evaluation_region.expanded(DISPLAY_MARGIN_M)
    keep = np.flatnonzero(region.contains(mesh.triangles_center))
    return mesh.submesh([keep], append=True), "ground truth"


def _proxy_mesh(run: Run):
    path = recorded_path(run, *PROXY_PATH_KEYS, file_name=PROXY_FILE)
    if path is None:
        plan = read_plan_record(run.run_dir)
        path = recorded_path(Run(run.run_dir, plan), *PROXY_PATH_KEYS, file_name=PROXY_FILE)
    mesh = _load_mesh_file(path) if path is not None else None
    return (mesh, "proxy") if mesh is not None else None


def tool_parser(prog: str, doc: str, out_help: str | None = None) -> argparse.ArgumentParser:
    """The command line of a study tool: ``prog``, its module docstring's first line as the
    description and, with ``out_help``, the run directories (``DIR...``) and ``--out``."""
    parser = argparse.ArgumentParser(prog=prog, description=doc.split("\n")[0])
    if out_help is not None:
        parser.add_argument(
            "dirs", nargs="+", type=Path, help="run or multirun directories (searched recursively)"
        )
        parser.add_argument("--out", type=Path, required=True, help=out_help)
    return parser


def write_findings(out: Path, stem: str, frame: pd.DataFrame, title: str, text: str) -> None:
    """A tool's findings into ``out``, each file atomically: ``<stem>.csv`` (``frame``, full
    precision) and ``<stem>.md`` (``# title``, then ``text``); ``text`` is printed too."""
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / f"{stem}.csv", frame.to_csv(index=False))
    write_text_atomic(out / f"{stem}.md", f"# {title}\n\n{text}")
    print(text, end="")


def out_is_a_file(out: Path) -> bool:
    """True (and the error printed) when a tool's ``--out`` names something that is not a directory."""
    if out.exists() and not out.is_dir():
        print(f"error: --out {out} exists and is not a directory", file=sys.stderr)
        return True
    return False
