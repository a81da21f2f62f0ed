"""The ``uavplan`` command, and the dispatcher behind the project's other commands.

    uavplan run scene=tomb planner=ours           # one cell (Hydra overrides, as ``python run.py``)
    uavplan run -m scene=tomb,church planner=ours  # a sweep
    uavplan view RUN_DIR --out plan.html           # a run's plan, interactive, in a browser
    uavplan stage dense RUN_DIR                    # one stage of a kept run again, on its files

``dispatch`` gives ``uavplan-study``, ``uavplan-diagnose``, ``uavplan-bench`` (and ``uavplan``) their
sub-commands: each is a module whose ``main(argv) -> int`` parses its own arguments.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from pipeline.cell import CellFailed, run_and_record, scene_label
from pipeline.photo_survey import plan_from_photos

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


@hydra.main(version_base=None, config_path=str(CONF_DIR), config_name="config")
def run_cell_main(cfg: DictConfig) -> None:
    """One cell (or, with ``-m``, each cell of a sweep) into Hydra's run directory."""
    try:
        run_and_record(cfg, Path(HydraConfig.get().runtime.output_dir))
    except CellFailed as exc:
        if HydraConfig.get().mode == RunMode.MULTIRUN or os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise  # a sweep reports the cell and goes on
        # One run: one line on stderr, the traceback on request.
        print(
            f"error: cell {scene_label(cfg)}/{cfg.planner.name} failed in stage {exc} "
            "(traceback: HYDRA_FULL_ERROR=1)",
            file=sys.stderr,
        )
        sys.exit(1)


@hydra.main(version_base=None, config_path=str(CONF_DIR), config_name="photos")
def plan_photos_main(cfg: DictConfig) -> None:
    """The second flight from a folder of photos of the first (``pipeline.photo_survey``)."""
    try:
        plan_from_photos(cfg, Path(HydraConfig.get().runtime.output_dir))
    except Exception as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"error: plan-photos {cfg.photos.dir}: {exc} (traceback: HYDRA_FULL_ERROR=1)", file=sys.stderr)
        sys.exit(1)


def photo_overrides(argv: Sequence[str]) -> list[str]:
    """``uavplan plan-photos IMAGES_DIR [overrides]`` as Hydra overrides: the folder is the first
    word without a '='; ``photos.origin=LAT,LON,HEIGHT`` and ``photos.roi=S,W,N,E`` typed with bare
    commas (as the docs once printed them, and Hydra reads as a sweep and refuses) become the lists
    they mean."""
    argv = list(argv)
    if argv and "=" not in argv[0] and not argv[0].startswith("-"):
        argv[0] = f"photos.dir={argv[0]}"
    for i, arg in enumerate(argv):
        key, sep, value = arg.partition("=")
        if sep and key.lstrip("+~") in ("photos.origin", "photos.roi") and "," in value:
            if value[:1] not in "[\"'":
                argv[i] = f"{key}=[{value}]"
    return argv


def _plan_photos(argv: Sequence[str]) -> int:
    sys.argv = ["uavplan plan-photos", *photo_overrides(argv)]
    plan_photos_main()
    return 0


def _run(argv: Sequence[str]) -> int:
    # Hydra reads sys.argv itself: hand it the overrides alone.
    sys.argv = ["uavplan run", *argv]
    run_cell_main()
    return 0


def dispatch(prog: str, commands: Mapping[str, str], argv: Sequence[str] | None, about: str) -> int:
    """Run ``prog COMMAND ARGS...``: the module ``commands[COMMAND]``'s ``main(ARGS)``.

    ``prog``, ``prog -h`` or an unknown command print the list of commands (exit 0 for help, 2 for
    a wrong call).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    width = max(len(name) for name in commands)
    listing = "\n".join(f"  {name:<{width}}  {_summary(target)}" for name, target in commands.items())
    usage = (
        f"usage: {prog} COMMAND [ARGS...]\n\n{about}\n\ncommands:\n{listing}\n\n"
        f"{prog} COMMAND --help: its own help"
    )
    if not argv or argv[0] in ("-h", "--help"):
        print(usage)
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in commands:
        print(f"{prog}: unknown command {name!r}\n\n{usage}", file=sys.stderr)
        return 2
    target = commands[name]
    if target.startswith("!"):
        return int(globals()[target[1:]](rest) or 0)
    sys.argv[0] = f"{prog} {name}"  # argparse's prog in the sub-command's help
    return int(importlib.import_module(target).main(rest) or 0)


def _summary(target: str) -> str:
    if target == "!_run":
        return "one cell or a sweep: Hydra overrides, as python run.py"
    if target == "!_plan_photos":
        return "IMAGES_DIR [overrides]: the second flight from a folder of a real first flight's photos"
    spec = importlib.util.find_spec(target)
    if spec is None or spec.origin is None:
        return ""
    text = Path(spec.origin).read_text()
    for quote in ('"""', "'''"):
        if quote in text:
            return text.split(quote, 2)[1].strip().splitlines()[0]
    return ""


COMMANDS = {
    "run": "!_run",
    "plan-photos": "!_plan_photos",
    "stage": "pipeline.stages",
    "view": "experiments.viewer",
}


def main(argv: Sequence[str] | None = None) -> int:
    return dispatch("uavplan", COMMANDS, argv, "UAV photogrammetry viewpoint planning: one cell end to end.")


if __name__ == "__main__":
    sys.exit(main())
