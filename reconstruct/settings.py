"""The reconstruction stage's settings (the ``reconstruct`` group of ``conf/reconstruct/default.yaml``),
typed and checked once where they are built: ``ReconstructSettings.from_config(node)`` at the top of
a cell (``pipeline.settings.cell_settings``), of a stage command or of a photo job, then handed down.
Every function of the stage reads these, never the config mapping; the mapping itself is kept only
for the stage's cache keys (``reconstruct.cache_keys``), which hash the settings as the user gave them.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from reconstruct.dense_settings import DenseSettings
from reconstruct.sfm_settings import SfmSettings
from scene.config import plain, setting, typed_settings

PROXY_SOURCES = ("reconstruction", "ground_truth_degraded")


@dataclass(frozen=True)
class AlignSettings:
    """The similarity to the GNSS priors and the merge of partial models (``reconstruct.align``)."""

    max_error_sigmas: float = setting(above=0)  # RANSAC inlier threshold, in GNSS sigmas
    min_error_m: float = setting(low=0)  # ... but never below this (m)
    min_common_images: int = setting(low=1)  # at least 3 are used whatever is set
    deregister_error_sigmas: float = setting(above=0)  # a camera this far from its fix is dropped
    merge_min_images: int = setting(low=1)  # a partial model merged only from this many images


@dataclass(frozen=True)
class DegradedSettings:
    """``proxy.source: ground_truth_degraded``: the ground truth, subdivided and noised (m)."""

    max_edge_m: float = setting(above=0)
    noise_sigma_m: float = setting(low=0)


@dataclass(frozen=True)
class ProxySettings:
    """The planners' proxy (``reconstruct.proxy``): the exploratory flight's cloud, Poisson-meshed.

    ``dense`` overrides ``reconstruct.dense`` for the exploratory flight, key by key
    (``ReconstructSettings.proxy_dense`` is the result, typed)."""

    source: str = setting(choices=PROXY_SOURCES)
    min_registered_fraction: float = setting(low=0)  # above 1: no proxy from any flight
    face_budget: int = setting(low=1)
    poisson_depth: int = setting(low=1)
    density_quantile: float = setting(low=0)  # below 1 (__post_init__)
    normal_radius_m: float = setting(above=0)
    voxel_size_m: float = setting(low=0)  # 0: no downsampling
    crop_margin_m: float = setting(low=0)
    degraded: DegradedSettings = setting()
    roi_margin_m: float | None = setting(None, low=0)  # null: the proxy is not cut to the site
    dense: dict | None = setting(None)

    def __post_init__(self) -> None:
        if not self.density_quantile < 1.0:
            raise ValueError(f"density_quantile must lie in [0, 1), got {self.density_quantile}")


@dataclass(frozen=True)
class GnssSettings:
    """The GNSS priors (``reconstruct.gnss``)."""

    sigma_m: float = setting(low=0)  # standard deviation (m); a rendered flight's noise


def _derived():
    return field(default=None, metadata={"derived": True})


@dataclass(frozen=True)
class ReconstructSettings:
    """The ``reconstruct`` group of a flight's reconstruction, typed (``from_config``).

    Attributes:
        min_images: fewest images a flight may have.
        min_registered_fraction: fewest images SfM must register, as a share of the flight.
        deterministic: single-threaded where threads change results (the study's runs).
        keep_dense_workspace: keep ``dense/`` (depth maps) after fusion.
        oracle_beside: the cell also runs the oracle beside its reconstruction.
        gnss, sfm, align, dense, proxy: the blocks, typed.
        node: the group as plain values (the stage's cache keys hash it; nothing else reads it).
        proxy_dense: the dense settings of the exploratory flight (``proxy.dense`` over ``dense``).
    """

    min_images: int = setting(low=0)
    min_registered_fraction: float = setting(low=0, high=1)
    gnss: GnssSettings = setting()
    sfm: SfmSettings = setting()
    align: AlignSettings = setting()
    dense: DenseSettings = setting()
    proxy: ProxySettings = setting()
    deterministic: bool = setting(False)
    keep_dense_workspace: bool = setting(True)
    oracle_beside: bool = setting(False)
    node: dict = _derived()
    proxy_dense: DenseSettings = _derived()

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "reconstruct") -> ReconstructSettings:
        """Check and type the ``reconstruct`` mapping (a ``ValueError`` names the bad setting)."""
        typed = typed_settings(cls, node, prefix)
        values = plain(node)
        exploration = proxy_flight_config(values)
        proxy_dense = typed_settings(DenseSettings, exploration["dense"], f"{prefix}.proxy.dense")
        return replace(typed, node=values, proxy_dense=proxy_dense)

    @property
    def gnss_sigma_m(self) -> float:
        """The priors' standard deviation (m)."""
        return self.gnss.sigma_m

    def for_exploration(self) -> ReconstructSettings:
        """These settings as the exploratory flight runs them: ``proxy.dense`` over ``dense``."""
        return replace(self, node=proxy_flight_config(self.node), dense=self.proxy_dense)


def proxy_flight_config(node: Mapping) -> dict:
    """The ``reconstruct`` mapping (plain values) of the exploratory flight: ``proxy.dense``
    overrides ``dense`` (nested sections key by key: ``proxy.dense.fusion.method`` leaves the other
    fusion settings).

    The proxy is meshed from a cloud voxelised at ``proxy.voxel_size_m``, so its depth maps need not
    be computed at the scored flights' resolution (``proxy.dense.max_image_size``).
    """
    flight = copy.deepcopy(dict(node))
    overrides = flight["proxy"].get("dense") or {}
    flight["dense"] = _overridden(flight["dense"], overrides, "reconstruct.proxy.dense")
    return flight


def _overridden(base: Mapping, overrides: Mapping, where: str) -> dict:
    unknown = sorted(set(overrides) - set(base))
    if unknown:
        raise ValueError(f"{where}: unknown dense settings {unknown}")
    out = dict(base)
    for key, value in overrides.items():
        nested = isinstance(value, Mapping) and isinstance(base[key], Mapping)
        out[key] = _overridden(base[key], value, f"{where}.{key}") if nested else value
    return out
