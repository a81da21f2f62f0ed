"""The study's protocol: everything in a cell that is not the planner, frozen and versioned.

A study cell's numbers depend on two things: the planner (its own ``version`` in
``conf/planner/<name>.yaml``, bumped by hand when its plans change) and everything else, which is
the protocol: rendering, SfM, alignment, dense matching, fusion, the oracle, evaluation (metrics,
ground-truth sampling, the enclosed-surface test), the scenes and the default preset (image size,
survey GSD, drone). ``results/protocol.md`` says what each version is and why it changed.

Two guards keep a version honest:

- the protocol's *settings*: the config groups below, resolved, hashed per scene
  (``protocol_digest``), must equal ``PROTOCOL_DIGESTS`` for a cell to carry ``protocol: PROTOCOL``
  in its ``metrics.json``; a cell run with another setting (a ``--set``, an edited YAML) records
  ``protocol: null`` and the study does not read it;
- the protocol's *code*: the golden records of the default test run (``tests/test_golden.py``), a
  smoke cell end to end and every planner's smoke plan on the committed smoke proxy.

A change that moves either is a bug to fix or a protocol bump: ``PROTOCOL`` + 1, the new digests
and golden values committed beside a line in ``results/protocol.md``, and the study re-run.
The forecast (``pipeline.forecast``) is not in the protocol: it is the planners' business.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from pipeline.cache import cache_key

PROTOCOL = 1

# The config groups the protocol covers (the planner, the budget level and the seed are the cell).
COVERED_GROUPS = ("camera", "scene", "exploration", "render", "reconstruct", "evaluate", "drone", "survey")
# Settings inside those groups that move no protocol number, or that are the study's own axes:
# the scene's seed is the cell's seed; a mesh scene's path differs per machine (its content is
# ``scene_fingerprint``); the GSD is the study's second axis (``target_gsd_m`` in every record);
# the deterministic mode, the dense workspace and the oracle beside change no scored number
# (archive/pre_p1/reproducibility.md; conf/reconstruct/default.yaml).
NEUTRAL_KEYS = (
    "scene.seed",
    "scene.path",
    "survey.target_gsd_m",
    "reconstruct.deterministic",
    "reconstruct.keep_dense_workspace",
    "reconstruct.oracle_beside",
)

# The study's scenes, each with the overrides it needs in every cell (conf/scene/powerplant.yaml
# says why the power plant's exploration circles it).
STUDY_SCENES: dict[str, tuple[str, ...]] = {
    "tomb": (),
    "church": (),
    "cathedral": (),
    "school": (),
    "powerplant": ("exploration=lawnmower_orbit",),
}
# protocol_digest of the default preset per study scene (``uavplan-study protocol`` prints them).
PROTOCOL_DIGESTS: dict[str, str] = {
    "tomb": "6aefeba628db1467",
    "church": "6d5591c0acc323c6",
    "cathedral": "c3f5fadb0a5151f1",
    "school": "c5e8b455ca510219",
    "powerplant": "3142caeeea9a54d5",
}


def protocol_settings(cfg: DictConfig | Mapping) -> dict:
    """The covered groups of a composed run config, resolved, without ``NEUTRAL_KEYS``."""
    container = (
        OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else copy.deepcopy(dict(cfg))
    )
    settings = {group: container.get(group) for group in COVERED_GROUPS}
    for dotted in NEUTRAL_KEYS:
        group, *path = dotted.split(".")
        node = settings.get(group)
        for key in path[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(path[-1], None)
    return settings


def protocol_digest(cfg: DictConfig | Mapping) -> str:
    """A 16-hex digest of ``protocol_settings``: equal digests, equal protocol settings."""
    return cache_key(protocol_settings(cfg))


def preset_digest(scene: str, overrides: tuple[str, ...] = ()) -> str:
    """``protocol_digest`` of ``run.py scene=<scene>`` with ``overrides`` (the default preset)."""
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base=None):
        return protocol_digest(compose("config", overrides=[f"scene={scene}", *overrides]))


def study_digests() -> dict[str, str]:
    """``preset_digest`` of every study scene: what ``PROTOCOL_DIGESTS`` must hold."""
    return {scene: preset_digest(scene, overrides) for scene, overrides in STUDY_SCENES.items()}


def planner_version(planner: str, conf_dir=None) -> int | None:
    """The ``version`` of ``conf/planner/<planner>.yaml`` (of ``conf_dir``, default this checkout's
    ``conf/``; None where it has none).

    Raises:
        hydra.errors.MissingConfigException: no such planner config."""
    conf = Path(conf_dir) if conf_dir is not None else Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base=None):
        version = compose("config", overrides=[f"planner={planner}"]).planner.get("version")
    return None if version is None else int(version)


def protocol_fields(cfg: DictConfig | Mapping, scene: str) -> dict:
    """The ``metrics.json`` fields: ``protocol`` (``PROTOCOL`` where the cell's settings are the
    protocol's for ``scene``, else None) and ``protocol_digest``."""
    digest = protocol_digest(cfg)
    return {
        "protocol": PROTOCOL if PROTOCOL_DIGESTS.get(scene) == digest else None,
        "protocol_digest": digest,
    }
