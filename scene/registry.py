"""Scene registry: ``load_scene(cfg)`` turns a ``conf/scene/<name>.yaml`` mapping into a ``Scene``."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping

from scene.base import Scene
from scene.procedural import build_cathedral, build_church, build_tomb

PROCEDURAL: dict[str, Callable[..., Scene]] = {
    "tomb": build_tomb,
    "church": build_church,
    "cathedral": build_cathedral,
}
KNOWN_SCENES: tuple[str, ...] = (*PROCEDURAL, "mesh")


def load_scene(cfg: Mapping, cache_dir: str | os.PathLike | None = "cache") -> Scene:
    """Build or load the scene a config describes.

    Args:
        cfg: the ``scene`` config. Needs ``name`` (one of ``KNOWN_SCENES``). Procedural scenes take
            ``seed`` and their size/texture settings; ``mesh`` takes ``path``, ``up_axis`` (z|y),
            ``scale``, ``add_detail`` and optionally ``apron_m``, ``ground``, ``ground_margin_m``,
            ``detail_strength``, ``seed``.
        cache_dir: stage cache folder; generated textures go to ``cache_dir/textures`` (None: no cache).

    Raises:
        ValueError: missing or unknown ``name`` (the message lists the known scenes), missing ``path``.
    """
    if not isinstance(cfg, Mapping) or "name" not in cfg:
        raise ValueError(f"the scene config needs a 'name'; known scenes: {list(KNOWN_SCENES)}")
    name = str(cfg["name"])
    if name in PROCEDURAL:
        return PROCEDURAL[name](cfg, cache_dir=cache_dir)
    if name == "mesh":
        from scene.mesh_loader import load_mesh_scene

        try:
            path = cfg.get("path")
        except Exception:  # OmegaConf raises on a mandatory '???' value left unset
            path = None
        if path in (None, "", "???"):
            raise ValueError("scene=mesh needs scene.path=FILE (a textured OBJ/GLB/PLY/DAE mesh)")
        return load_mesh_scene(
            path,
            up_axis=str(cfg.get("up_axis", "z")),
            scale=float(cfg.get("scale", 1.0)),
            add_detail=bool(cfg.get("add_detail", False)),
            apron_m=float(cfg.get("apron_m", 3.0)),
            ground=bool(cfg.get("ground", True)),
            ground_margin_m=float(cfg.get("ground_margin_m", 30.0)),
            detail_strength=float(cfg.get("detail_strength", 0.3)),
            seed=int(cfg.get("seed", 0)),
            cache_dir=cache_dir,
        )
    raise ValueError(f"unknown scene {name!r}; known scenes: {list(KNOWN_SCENES)}")
