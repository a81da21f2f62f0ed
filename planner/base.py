"""The planner contract and the parameter merge every planner uses.

Planner contract: a module ``planner/<name>.py`` exposes
``plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan``;
``conf/planner/<name>.yaml`` names it with ``_target_`` and carries its parameters. ``Plan`` and its
files live in ``scene.plan`` (shared by every stage). A module may also expose
``check_params(params: Mapping, intrinsics: Intrinsics) -> None``, which raises (``ValueError`` or
``PlanningError``, naming the setting) on a bad parameter; the pipeline calls it before the scene
loads (``pipeline.settings``), so a bad setting costs no exploration.
"""

from __future__ import annotations

from collections.abc import Mapping

from planner.budget import CONFIG_KEYS
from scene.config import plain
from scene.plan import Plan, PlanningError

__all__ = ["Plan", "PlanningError", "merge_params", "plain_params"]


def plain_params(params: Mapping | None) -> dict:
    """A planner's parameters as plain containers (``scene.config.plain``), None as {}."""
    return plain(params) if params is not None else {}


def merge_params(planner: str, defaults: Mapping, params: Mapping | None) -> dict:
    """``defaults`` overridden by a planner config's flat ``params``; an unknown key is an error.

    ``name``, ``_target_`` (the Hydra registry keys) and ``budget`` (``planner.budget``) are ignored.
    """
    merged = dict(defaults)
    if params:
        unknown = sorted(set(params) - set(defaults) - set(CONFIG_KEYS))
        if unknown:
            raise ValueError(f"{planner}: unknown parameter(s) {unknown}; known: {sorted(defaults)}")
        merged.update({k: v for k, v in params.items() if k in defaults})
    return merged
