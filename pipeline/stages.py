"""STAGE RUN_DIR: one stage of a kept run again, on its files (render, sfm, dense, evaluate).

    uavplan stage render   RUN_DIR  # plan/ + the scene -> images/, cameras.json
    uavplan stage sfm      RUN_DIR  # images/ -> recon/sparse/, gnss.json, database.db
    uavplan stage dense    RUN_DIR  # images/ + recon/sparse/ -> recon/dense.ply, recon/dense/
    uavplan stage evaluate RUN_DIR  # recon/dense.ply + the scene -> eval/ (scores, pictures)

The settings are the run's own (``RUN_DIR/.hydra/config.yaml``), with any ``KEY=VALUE`` typed after
the run directory applied over them (``reconstruct.dense.backend=cuda``), checked once by
``pipeline.settings.cell_settings`` as a cell checks them; each stage is handed its own part. Inputs
are read from ``RUN_DIR``; outputs go where the cell writes them, under ``--out`` (default: the run
directory, replacing what the stage wrote there). The stage's record is printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from evaluate.loading import ReconstructionFileError
from evaluate.run import evaluate_reconstruction
from pipeline.settings import CellSettings, SettingsError, cell_settings
from reconstruct.errors import ReconstructionError
from reconstruct.pipeline import RECORD_FILE, SFM_RECORD_FILE, dense_flight, sfm_flight
from render import render_flight
from scene.plan import read_plan
from scene.registry import load_scene

IMAGES, RECON, EVAL = Path("images"), Path("recon"), Path("eval")


def render_stage(settings: CellSettings, plan_dir: Path, out_dir: Path) -> dict:
    """The plan's views of the scene rendered into ``out_dir`` (images and ``cameras.json``)."""
    viewpoints, kinds = read_plan(plan_dir)
    scene = load_scene(settings.scene, cache_dir=settings.cache_dir)
    rendered = render_flight(scene, viewpoints, settings.intrinsics, out_dir, settings.render, kinds=kinds)
    return {"n_images": len(viewpoints), "render_time_s": rendered.render_time_s, "image_dir": str(out_dir)}


def sfm_stage(settings: CellSettings, image_dir: Path, out_dir: Path) -> dict:
    """SfM with GNSS priors and the alignment to them (``reconstruct.pipeline.sfm_flight``)."""
    return sfm_flight(image_dir, out_dir, settings.reconstruct, settings.seed)


def dense_stage(settings: CellSettings, image_dir: Path, sparse_dir: Path, out_dir: Path) -> dict:
    """Depth maps and fusion of the aligned model (``reconstruct.pipeline.dense_flight``)."""
    oracle = settings.reconstruct.dense.backend == "oracle"
    truth = load_scene(settings.scene, cache_dir=settings.cache_dir).ground_truth_mesh if oracle else None
    return dense_flight(image_dir, sparse_dir, out_dir, settings.reconstruct, settings.seed, truth)


def evaluate_stage(settings: CellSettings, cloud: Path, out_dir: Path) -> dict:
    """The cloud scored against the scene's ground truth (``evaluate.run.evaluate_reconstruction``)."""
    scene = load_scene(settings.scene, cache_dir=settings.cache_dir)
    return evaluate_reconstruction(cloud, scene, settings.evaluation, out_dir)


# What each stage reads from the run directory and where it writes, relative to the output root.
STAGES: dict[str, tuple[tuple[Path, ...], Path, Callable]] = {
    "render": ((Path("plan"),), IMAGES, render_stage),
    "sfm": ((IMAGES,), RECON, sfm_stage),
    "dense": ((IMAGES, RECON / "sparse"), RECON, dense_stage),
    "evaluate": ((RECON / "dense.ply",), EVAL, evaluate_stage),
}
# Which stage writes each input, for the error that names it.
MAKER = {
    "plan": "uavplan run",
    "images": "render",
    "recon/sparse": "sfm",
    "recon/dense.ply": "dense",
}


def run_settings(run_dir: Path, overrides: Sequence[str]) -> CellSettings:
    """The run's settings (``RUN_DIR/.hydra/config.yaml``) with ``overrides``, checked."""
    path = run_dir / ".hydra" / "config.yaml"
    if not path.is_file():
        raise SettingsError(
            f"{run_dir} is not a run directory of `uavplan run` (no {path.relative_to(run_dir)})"
        )
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise SettingsError(f"expected KEY=VALUE after the run directory, got {bad[0]!r}")
    try:
        cfg = OmegaConf.merge(OmegaConf.load(path), OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as exc:
        raise SettingsError(f"{path}: {exc}") from exc
    return cell_settings(cfg)


def run_stage(stage: str, run_dir: Path, out_root: Path, overrides: Sequence[str] = ()) -> dict:
    """Re-run ``stage`` of ``run_dir`` into ``out_root`` (see the module docstring); its record.

    Raises:
        SettingsError: not a run directory, or a bad override.
        FileNotFoundError: an input the stage needs is missing (the message names the stage that
            writes it).
        ReconstructionError, ReconstructionFileError: the stage failed on its input.
    """
    inputs, output, function = STAGES[stage]
    settings = run_settings(run_dir, overrides)
    for relative in inputs:
        if not (run_dir / relative).exists():
            maker = MAKER[relative.as_posix()]
            fix = maker if maker.startswith("uavplan") else f"uavplan stage {maker} {run_dir}"
            raise FileNotFoundError(f"{run_dir / relative} is missing: run `{fix}` first")
    out_dir = out_root / output
    if stage in ("sfm", "dense"):
        # The cell's records vouch for the files this stage replaces: a later `uavplan run` into
        # this directory must not take them as its own.
        for record in (RECORD_FILE, SFM_RECORD_FILE) if stage == "sfm" else (RECORD_FILE,):
            (out_dir / record).unlink(missing_ok=True)
    return function(settings, *(run_dir / relative for relative in inputs), out_dir)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("stage", choices=list(STAGES))
    parser.add_argument("run_dir", type=Path, help="a run directory of `uavplan run` (outputs/...)")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="over the run's settings")
    parser.add_argument("--out", type=Path, default=None, help="output root (default: RUN_DIR itself)")
    args = parser.parse_args(argv)
    try:
        record = run_stage(args.stage, args.run_dir, args.out or args.run_dir, args.overrides)
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ReconstructionFileError, ReconstructionError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(record, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
