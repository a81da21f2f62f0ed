"""Config nodes as plain data: the one conversion every stage applies to its Hydra config group."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping

from omegaconf import DictConfig, ListConfig, OmegaConf

_REQUIRED = object()


def plain(node):
    """A JSON-able copy of a config node: a Hydra ``DictConfig``/``ListConfig`` resolved and
    converted, a Mapping converted recursively (keys as strings), a list or tuple item by item, and
    anything else as it is (None stays None)."""
    if isinstance(node, DictConfig | ListConfig):
        return OmegaConf.to_container(node, resolve=True)
    if isinstance(node, Mapping):
        return {str(k): plain(v) for k, v in node.items()}
    if isinstance(node, list | tuple):
        return type(node)(plain(v) for v in node)
    return node


def detached(node) -> DictConfig:
    """A config group apart from the run config it came from: resolved (no interpolation reaches
    back into the run config), in struct mode (a key it lacks is an error, as in the run config)."""
    out = OmegaConf.create(plain(node))
    OmegaConf.set_struct(out, True)
    return out


@dataclasses.dataclass(frozen=True)
class StageSettings:
    """One stage's config group, detached from the run config (``detached``), built once at the top
    of a cell (``pipeline.settings.cell_settings``): what the stage reads, and nothing else.

    Attributes:
        node: the group, resolved.
    """

    node: DictConfig

    @classmethod
    def of(cls, node) -> StageSettings:
        return cls(detached(node))


def stage_node(cfg):
    """The config group a stage reads: a ``StageSettings``' node, or ``cfg`` itself (a mapping from
    a caller outside a cell: a benchmark, a diagnostic, a test)."""
    return cfg.node if isinstance(cfg, StageSettings) else cfg


def setting(default=_REQUIRED, *, low=None, above=None, high=None, choices=None, odd=False, multiple_of=None):
    """A settings dataclass field with its range, checked by ``typed_settings``.

    Args:
        default: the value when the config leaves the key out (none: the key is required).
        low, high: inclusive bounds; above: an exclusive lower bound.
        choices: the allowed values; odd: an odd integer; multiple_of: an integer multiple of it.
    """
    rules = {"low": low, "above": above, "high": high, "choices": choices, "multiple_of": multiple_of}
    metadata = {k: v for k, v in rules.items() if v is not None} | ({"odd": True} if odd else {})
    if default is _REQUIRED:
        return dataclasses.field(metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


_KIND_WORDS = {
    bool: "true or false",
    int: "an integer",
    float: "a finite number",
    str: "a string",
    dict: "a mapping",
    type(None): "null",
}


def _fits(value, kind) -> bool:
    """Whether a config value is of a settings field's type (an int is a float, a bool neither)."""
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if kind is dict:
        return isinstance(value, Mapping)
    return isinstance(value, kind)


def _check_range(value, rules: Mapping) -> str | None:
    """What ``value`` breaks of a field's ``setting`` rules (None: nothing, or no value). A word
    (a string) is checked against ``choices`` only."""
    if value is None:
        return None
    if "choices" in rules and value not in rules["choices"]:
        return f"must be one of {tuple(rules['choices'])}, got {value!r}"
    if isinstance(value, str):
        return None
    if "low" in rules and value < rules["low"]:
        return f"must be >= {rules['low']}, got {value}"
    if "above" in rules and not value > rules["above"]:
        return f"must be > {rules['above']}, got {value}"
    if "high" in rules and value > rules["high"]:
        return f"must be <= {rules['high']}, got {value}"
    if rules.get("odd") and value % 2 == 0:
        return f"must be an odd number, got {value}"
    if "multiple_of" in rules and value % rules["multiple_of"]:
        return f"must be a multiple of {rules['multiple_of']}, got {value}"
    return None


def typed_settings(cls, node, prefix: str):
    """Build the settings dataclass ``cls`` from a config mapping, refusing what does not fit.

    Every field of ``cls`` is a key of ``node`` (a field with a default may be left out); a key
    ``cls`` lacks is an error, and so is a value of the wrong kind. A field marked ``derived``
    (``dataclasses.field(default=None, metadata={"derived": True})``) is no key: the builder of
    ``cls`` fills it from the others. A field whose type is itself such
    a dataclass is built from its sub-mapping. Each field's range (``setting``) is checked, then
    ``cls.__post_init__`` checks what involves several fields. Every error is a ``ValueError`` that
    names the setting (``prefix.key``).
    """
    if not isinstance(node, Mapping):
        raise ValueError(f"{prefix} must be a mapping, got {node!r}")
    node = plain(node)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("derived")}
    unknown = sorted(set(node) - set(fields))
    if unknown:
        raise ValueError(f"{prefix}: unknown setting(s) {unknown}; known: {sorted(fields)}")
    values = {}
    for name, field in fields.items():
        where = f"{prefix}.{name}"
        if name not in node:
            if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
                raise ValueError(f"{where}: missing")
            continue
        value, kind = node[name], hints[name]
        if dataclasses.is_dataclass(kind):
            values[name] = typed_settings(kind, value, where)
            continue
        union = typing.get_origin(kind) in (typing.Union, type(int | None))
        options = typing.get_args(kind) if union else (kind,)
        if value is None:
            if type(None) not in options:
                raise ValueError(f"{where} must be set, got null")
            values[name] = None
            continue
        fitting = [kind for kind in options if _fits(value, kind)]
        if not fitting:
            wanted = " or ".join(_KIND_WORDS.get(k, k.__name__) for k in options)
            raise ValueError(f"{where} must be {wanted}, got {value!r}")
        if fitting == [float]:
            value = float(value)
        broken = _check_range(value, field.metadata)
        if broken:
            raise ValueError(f"{where} {broken}")
        values[name] = value
    try:
        return cls(**values)
    except ValueError as exc:
        raise ValueError(f"{prefix}.{exc}") from exc
