"""The exploratory flight and the proxy built from it, cached and shared by every planner of a scene.

Flight (lawnmower aimed at the structure centre, as in the paper) -> rendered images -> pycolmap
SfM + dense -> Poisson proxy mesh. The cache key covers everything the proxy depends on (scene,
camera, exploration, render and reconstruction settings, seed), so sweep cells that differ only in
the planner share one proxy; concurrent cells wait for the first builder (experiments/cache.py).
"""

from __future__ import annotations

import logging
from pathlib import Path

import trimesh
from omegaconf import DictConfig, OmegaConf

from experiments.cache import cache_key, cached_entry
from planner.sampling import PROXY_CLOUD_KEY, PROXY_VIEWS_KEY
from reconstruct.proxy import oriented_cloud
from scene.base import Box, Scene
from scene.camera import Intrinsics
from scene.plan import write_plan

log = logging.getLogger(__name__)

PROXY_FILE = "proxy.ply"
# Voxel (m) of the exploratory cloud handed to the planners with the proxy: ~100 points per m^2.
CLOUD_VOXEL_M = 0.1
WORKDIR_REUSE_FLAGS = ("cached", "proxy_cached")


def exploration_cache_key(cfg: DictConfig, scene: Scene) -> str:
    """Content key of the exploratory flight + proxy: the scene's content and the run config."""
    from reconstruct.pipeline import proxy_settings

    def plain(node):
        return OmegaConf.to_container(node, resolve=True)

    return cache_key(
        scene.fingerprint,
        plain(cfg.scene),
        plain(cfg.camera),
        plain(cfg.exploration),
        plain(cfg.render),
        proxy_settings(cfg.reconstruct),
        int(cfg.seed),
    )


def load_proxy(entry: Path) -> trimesh.Trimesh:
    """The proxy mesh of an exploration cache entry, carrying the exploratory flight's oriented cloud
    (``proxy.metadata[PROXY_CLOUD_KEY]``, for planners that read the coarse model's points: Yan's
    confidence term) when the entry holds its ``recon/dense.ply``, and where its registered views
    and images are (``PROXY_VIEWS_KEY``, for ours_plus' photo-consistency)."""
    entry = Path(entry)
    if not (entry / PROXY_FILE).is_file():
        raise FileNotFoundError(f"{entry / PROXY_FILE}: no proxy (not an exploration cache entry)")
    proxy = trimesh.load(entry / PROXY_FILE, force="mesh", process=False)
    dense_ply = entry / "recon" / "dense.ply"
    if dense_ply.is_file():
        box = Box.from_points(proxy.vertices)
        proxy.metadata[PROXY_CLOUD_KEY] = oriented_cloud(
            dense_ply, box.expanded(1.0, 1.0, 1.0), CLOUD_VOXEL_M
        )
    if (entry / "recon" / "sparse").is_dir() and (entry / "images").is_dir():
        proxy.metadata[PROXY_VIEWS_KEY] = {"recon_dir": entry / "recon", "image_dir": entry / "images"}
    return proxy


def build_exploration_proxy(
    scene: Scene, intrinsics: Intrinsics, cfg: DictConfig
) -> tuple[trimesh.Trimesh, dict]:
    """Fly, render and reconstruct the exploratory flight once, and return its proxy mesh.

    Args:
        scene: the ground-truth scene (rendered, never shown to the planner).
        intrinsics: the survey camera.
        cfg: the composed run config (uses ``exploration``, ``render``, ``reconstruct``, ``cache_dir``,
            ``seed``).

    Returns:
        (proxy mesh in world metres, record with the exploration's image count, registered fraction,
        timings, cache entry path and whether it was a cache hit).
    """
    from planner.lawnmower import plan_exploration
    from reconstruct.pipeline import build_proxy
    from render import render_flight

    seed = int(cfg.seed)

    def build(entry: Path) -> dict:
        plan = plan_exploration(scene.structure_bounds, intrinsics, cfg.exploration, seed)
        write_plan(plan, entry / "plan")
        log.info("exploration: %d viewpoints; rendering", len(plan.viewpoints))
        rendered = render_flight(
            scene, plan.viewpoints, intrinsics, entry / "images", cfg.render, kinds=plan.kinds
        )
        proxy, record = build_proxy(
            entry / "images", entry / "recon", cfg.reconstruct, seed, roi=scene.structure_bounds
        )
        proxy.export(entry / PROXY_FILE)
        return {
            "n_images": len(plan.viewpoints),
            "render_time_s": rendered.render_time_s,
            "n_faces": len(proxy.faces),
            **{k: v for k, v in record.items() if isinstance(v, int | float | str | bool)},
        }

    entry, record = cached_entry(cfg.cache_dir, "exploration", exploration_cache_key(cfg, scene), build)
    proxy = load_proxy(entry)
    # ``cached``/``proxy_cached`` say whether build_proxy reused its own work folder; a cache entry is
    # always built fresh, so they read false even on a hit. ``cache_hit`` is the field that tells.
    record = {k: v for k, v in record.items() if k not in WORKDIR_REUSE_FLAGS}
    return proxy, {**record, "entry": str(entry)}
