"""The render stage's settings (``conf/render/default.yaml``), typed and checked once where they are
built: ``RenderSettings.from_config(node)`` at the top of a cell (``pipeline.settings.cell_settings``)
or of a tool, then handed to ``render.render_flight``. What each value does is said beside it in
the YAML; ranges that need a sentence are checked where they are used (``render.model``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from scene.config import plain, setting, typed_settings


@dataclass(frozen=True)
class SunSettings:
    """The sun: a directional light (degrees; diffuse intensity)."""

    azimuth_deg: float = setting()
    elevation_deg: float = setting()  # (0, 90]: render.model.LightingConfig
    diffuse: float = setting(low=0)


@dataclass(frozen=True)
class SkySettings:
    """The sky: ambient and overhead light, and the background's colours (RGB in [0, 1])."""

    ambient: float = setting(low=0)
    diffuse: float = setting(low=0)
    color: list = setting()
    horizon_color: list = setting()


@dataclass(frozen=True)
class ShadowSettings:
    """The sun's shadow map (texels; metres)."""

    enabled: bool = setting()
    coverage: str = setting()  # scene or structure: render.model.build_model
    map_size: int = setting()  # [256, 16384]: render.model.LightingConfig
    margin_m: float = setting(low=0)


@dataclass(frozen=True)
class RenderSettings:
    """The ``render`` group, typed (``from_config``).

    Attributes:
        node: the group as plain values (the exploration's cache key hashes it; nothing else reads it).
    """

    sun: SunSettings = setting()
    sky: SkySettings = setting()
    shadows: ShadowSettings = setting()
    znear_m: float = setting(above=0)
    zfar_m: float = setting(above=0)
    crease_angle_deg: float = setting(low=0, high=180)
    backend: str = setting("auto")  # auto, egl or osmesa: render.backend.select_backend
    antialias_samples: int = setting(0, low=0)
    cull_backfaces: bool = setting(False)
    png_compression: int = setting(1)  # [0, 9]: render.flight.render_flight
    writer_threads: int = setting(2)  # below 1: one
    node: dict = field(default=None, metadata={"derived": True})

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "render") -> RenderSettings:
        """Check and type the ``render`` mapping (a ``ValueError`` names the bad setting)."""
        return replace(typed_settings(cls, node, prefix), node=plain(node))
