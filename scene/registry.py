"""Scene registry: ``load_scene(cfg)`` turns a ``conf/scene/<name>.yaml`` mapping into a ``Scene``."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping

from scene.base import Scene
from scene.config import StageSettings, stage_node
from scene.mesh_loader import MeshSceneSpec, load_mesh_scene
from scene.procedural import build_cathedral, build_church, build_tomb

PROCEDURAL: dict[str, Callable[..., Scene]] = {
    "tomb": build_tomb,
    "church": build_church,
    "cathedral": build_cathedral,
}
KNOWN_SCENES: tuple[str, ...] = (*PROCEDURAL, "mesh")


class SceneSettings(StageSettings):
    """The ``scene`` group of a cell (``load_scene`` reads it)."""


def load_scene(cfg: Mapping | SceneSettings, cache_dir: str | os.PathLike | None = "cache") -> Scene:
    """Build or load the scene a config describes.

    Args:
        cfg: the ``scene`` config. Needs ``name`` (one of ``KNOWN_SCENES``). Procedural scenes take
            ``seed`` and their size/texture settings; ``mesh`` takes ``path`` and the keyword options
            of ``scene.mesh_loader.MeshSceneSpec`` (conf/scene/mesh.yaml lists them).
        cache_dir: stage cache folder; generated textures go to ``cache_dir/textures`` (None: no cache).

    Raises:
        ValueError: missing or unknown ``name`` (the message lists the known scenes), missing ``path``.
    """
    cfg = stage_node(cfg)
    if not isinstance(cfg, Mapping) or "name" not in cfg:
        raise ValueError(f"the scene config needs a 'name'; known scenes: {list(KNOWN_SCENES)}")
    name = str(cfg["name"])
    if name in PROCEDURAL:
        return PROCEDURAL[name](cfg, cache_dir=cache_dir)
    if name == "mesh":
        try:
            path = cfg.get("path")
        except Exception:  # OmegaConf raises on a mandatory '???' value left unset
            path = None
        if path in (None, "", "???"):
            raise ValueError("scene=mesh needs scene.path=FILE (a textured OBJ/GLB/PLY/DAE mesh)")
        options = {k: v for k, v in dict(cfg).items() if k not in ("name", "path")}
        known = MeshSceneSpec.options()
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"scene=mesh: unknown option(s) {unknown}; known: {sorted(known)}")
        return load_mesh_scene(path, MeshSceneSpec(**options), cache_dir=cache_dir)
    raise ValueError(f"unknown scene {name!r}; known scenes: {list(KNOWN_SCENES)}")
