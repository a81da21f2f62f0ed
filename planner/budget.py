"""Image budgets: the setting of each planner that a quality-per-image sweep turns.

A planner config (``conf/planner/<name>.yaml``) names its budget knob and the knob's value at each
level, from the fewest images to the most:

    budget:
      knob: target_gsd_m             # dotted path of the setting (a list: several set together)
      levels: {low: 0.045, high: 0.02}   # ``default`` is the config's own value and needs no entry

A knob of several paths sets each to a level's value, or, where the level is a mapping from path to
value, each to its own (``{high: {front_overlap: 0.85, side_overlap: 0.85, h_target: 6.0}}``).

``python run.py planner=ours budget=high`` plans with ``target_gsd_m = 0.02``; ``budget=default``
(conf/config.yaml) leaves the config as it is. The level, knob and value go into ``metrics.json``
(``budget``, ``budget_knob``, ``budget_value``) so that fronts join a planner's cells in budget order.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

# Levels from the fewest images to the most; a front joins a planner's points in this order. `mid`
# lies between `low` and `default`, for a knob whose default is far from its low level (Yan's).
LEVELS = ("lowest", "low", "mid", "default", "high", "highest")
DEFAULT_LEVEL = "default"
# Keys of a planner config that are Hydra's or the study's, not the planner's parameters.
CONFIG_KEYS = ("name", "_target_", "budget", "version")


def level_rank(level: str) -> int:
    """Position of ``level`` in ``LEVELS`` (fewest images first).

    Raises:
        ValueError: an unknown level.
    """
    if level not in LEVELS:
        raise ValueError(f"budget must be one of {', '.join(LEVELS)}, got {level!r}")
    return LEVELS.index(level)


def _knob_paths(knob) -> list[str]:
    paths = [knob] if isinstance(knob, str) else list(knob or [])
    if not paths or not all(isinstance(p, str) and p for p in paths):
        raise ValueError(f"budget.knob must be a setting's dotted path or a list of them, got {knob!r}")
    return paths


def _get(params: Mapping, path: str, planner: str):
    node = params
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise ValueError(f"planner {planner}: budget.knob {path!r} is not one of its settings")
        node = node[part]
    return node


def _set(params: dict, path: str, value) -> None:
    *parents, leaf = path.split(".")
    node = params
    for part in parents:
        node = node[part]
    node[leaf] = value


def apply_budget(params: Mapping, level: str, planner: str) -> tuple[dict, dict]:
    """The planner's parameters at budget ``level``, without the ``budget`` block.

    Args:
        params: the planner's resolved config (plain containers), with its ``budget`` block.
        level: one of ``LEVELS``.
        planner: the planner's name (for messages).

    Returns:
        ``(params, record)``: a deep copy with the knob set and the ``budget`` block removed
        (``name`` and ``_target_`` stay: a planner may read its name), and ``{"budget",
        "budget_knob", "budget_value"}`` for metrics.json (the value of the first knob path, as
        the planner sees it).

    Raises:
        ValueError: an unknown level, a level the planner does not define, or a knob that names no
            setting.
    """
    level_rank(level)
    spec = params.get("budget")
    out = {k: copy.deepcopy(v) for k, v in params.items() if k != "budget"}
    if not spec:
        if level != DEFAULT_LEVEL:
            raise ValueError(f"planner {planner} has no budget knob (no budget block in its config)")
        return out, {"budget": level}
    paths = _knob_paths(spec.get("knob"))
    levels = dict(spec.get("levels") or {})
    for name in levels:
        level_rank(name)
    for path in paths:
        _get(out, path, planner)
    for name, value in levels.items():
        if isinstance(value, Mapping) and set(value) != set(paths):
            raise ValueError(
                f"planner {planner}: budget level {name!r} sets {sorted(value)}, its knob is {paths}"
            )
    if level != DEFAULT_LEVEL:
        if level not in levels:
            known = ", ".join(sorted({DEFAULT_LEVEL, *levels}, key=level_rank))
            raise ValueError(f"planner {planner} has no budget level {level!r} (its levels: {known})")
        value = levels[level]
        for path in paths:
            _set(out, path, copy.deepcopy(value[path] if isinstance(value, Mapping) else value))
    return out, {
        "budget": level,
        "budget_knob": ",".join(paths),
        "budget_value": _get(out, paths[0], planner),
    }
