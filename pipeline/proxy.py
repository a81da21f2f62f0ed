"""The proxy stage: the exploratory flight and the proxy mesh built from it, cached per scene.

Flight (lawnmower aimed at the structure centre, as in the paper) -> rendered images -> pycolmap
SfM + dense -> Poisson proxy mesh. The cache key covers everything the proxy depends on (scene,
camera, exploration, render and reconstruction settings, seed), so sweep cells that differ only in
the planner share one proxy; concurrent cells wait for the first builder (``pipeline.cache``).
``reconstruct.proxy.source=ground_truth_degraded`` (NOT the paper's setting) plans on the cropped,
decimated and noised ground truth instead, for planner work without a reconstruction.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from pipeline.cache import cache_key, cached_entry
from pipeline.proxy_bundle import CLOUD_FILE, MANIFEST, find_bundle, install_bundle, load_cloud, sha256
from planner.lawnmower.lawnmower import plan_exploration
from reconstruct.cache_keys import proxy_settings
from reconstruct.pipeline import build_proxy
from reconstruct.proxy import degraded_ground_truth, oriented_cloud
from reconstruct.settings import ReconstructSettings
from render import RenderSettings, render_flight
from scene.base import Box, Scene
from scene.camera import Intrinsics
from scene.config import plain
from scene.plan import write_plan
from scene.proxy_mesh import PROXY_CLOUD_KEY, PROXY_VIEWS_KEY

log = logging.getLogger(__name__)

PROXY_FILE = "proxy.ply"
# Voxel (m) of the exploratory cloud handed to the planners with the proxy: ~100 points per m^2.
CLOUD_VOXEL_M = 0.1
WORKDIR_REUSE_FLAGS = ("cached", "proxy_cached")


@dataclass(frozen=True)
class ProxyInputs:
    """The config groups the proxy stage reads, as plain values (all but ``cache_dir`` key its cache
    entry).

    Attributes:
        scene, camera, exploration: the ``scene``, ``camera`` and ``exploration`` (the
            exploratory flight) groups.
        render, reconstruct: the ``render`` and ``reconstruct`` settings, typed (the latter's
            ``proxy`` block meshes the proxy).
        cache_dir: the stage cache root.
        seed: seed of the reconstruction (GNSS noise, RANSAC, mapper).
    """

    scene: Mapping
    camera: Mapping
    exploration: Mapping
    render: RenderSettings
    reconstruct: ReconstructSettings
    cache_dir: str
    seed: int

    @classmethod
    def of(cls, cfg: Mapping) -> ProxyInputs:
        """The proxy stage's groups of a composed run config, as plain values."""
        return cls(
            plain(cfg["scene"]),
            plain(cfg["camera"]),
            plain(cfg["exploration"]),
            RenderSettings.from_config(cfg["render"]),
            ReconstructSettings.from_config(cfg["reconstruct"]),
            str(cfg["cache_dir"]),
            int(cfg["seed"]),
        )


def exploration_cache_key(scene: Scene, inputs: ProxyInputs, for_bundle: bool = False) -> str:
    """Content key of the exploratory flight + proxy: the scene's content and the stage's settings
    (the ``reconstruct`` settings as the exploratory flight runs them: ``proxy.dense`` in effect, so
    a change to the scored flights' dense settings leaves proxies valid).

    ``for_bundle``: the key of a committed proxy (``pipeline.proxy_bundle``), without the
    deterministic mode (a committed proxy is one fixed mesh, whichever mode the cell then
    reconstructs its own flight in: the noise floor's cells plan on the study's proxy) and without
    a mesh scene's path (another checkout's is another path to the same mesh)."""
    settings = proxy_settings(inputs.reconstruct.for_exploration().node)
    scene_settings = dict(inputs.scene)
    if for_bundle:
        settings.pop("deterministic", None)
        # a mesh scene's path differs per checkout; its content is in scene.fingerprint
        scene_settings = {k: v for k, v in scene_settings.items() if k != "path"}
    return cache_key(
        scene.fingerprint,
        scene_settings,
        inputs.camera,
        inputs.exploration,
        inputs.render.node,
        settings,
        int(inputs.seed),
    )


def load_proxy(entry: Path) -> trimesh.Trimesh:
    """The proxy mesh of an exploration cache entry, carrying the exploratory flight's oriented cloud
    (``proxy.metadata[PROXY_CLOUD_KEY]``) when the entry holds its ``recon/dense.ply``, and where its
    registered views and images are (``PROXY_VIEWS_KEY``); see ``scene.proxy_mesh``."""
    entry = Path(entry)
    if not (entry / PROXY_FILE).is_file():
        raise FileNotFoundError(f"{entry / PROXY_FILE}: no proxy (not an exploration cache entry)")
    proxy = trimesh.load(entry / PROXY_FILE, force="mesh", process=False)
    dense_ply = entry / "recon" / "dense.ply"
    if (entry / CLOUD_FILE).is_file():  # a committed bundle's (pipeline.proxy_bundle)
        proxy.metadata[PROXY_CLOUD_KEY] = load_cloud(entry / CLOUD_FILE)
    elif dense_ply.is_file():
        box = Box.from_points(proxy.vertices)
        proxy.metadata[PROXY_CLOUD_KEY] = oriented_cloud(
            dense_ply, box.expanded(1.0, 1.0, 1.0), CLOUD_VOXEL_M
        )
    if (entry / "recon" / "sparse").is_dir() and (entry / "images").is_dir():
        proxy.metadata[PROXY_VIEWS_KEY] = {"recon_dir": entry / "recon", "image_dir": entry / "images"}
    return proxy


def build_exploration_proxy(
    scene: Scene, intrinsics: Intrinsics, inputs: ProxyInputs, use_bundle: bool = True
) -> tuple[Path, dict]:
    """Fly, render and reconstruct the exploratory flight once; return its cache entry.

    Args:
        scene: the ground-truth scene (rendered, never shown to the planner).
        intrinsics: the survey camera (``inputs.camera`` as an ``Intrinsics``).
        inputs: the stage's config groups.
        use_bundle: install the committed proxy of this exploration where there is one
            (``pipeline.proxy_bundle``); false builds it here (``uavplan-study proxies build``).

    Returns:
        (the entry folder holding ``proxy.ply``, ``plan/``, ``images/``, ``recon/``; record with the
        exploration's image count, registered fraction, timings, ``entry`` and ``cache_hit``).
    """
    seed = int(inputs.seed)

    def build(entry: Path) -> dict:
        plan = plan_exploration(scene.structure_bounds, intrinsics, inputs.exploration, seed)
        write_plan(plan, entry / "plan")
        log.info("exploration: %d viewpoints; rendering", len(plan.viewpoints))
        rendered = render_flight(
            scene, plan.viewpoints, intrinsics, entry / "images", inputs.render, kinds=plan.kinds
        )
        proxy, record = build_proxy(
            entry / "images", entry / "recon", inputs.reconstruct, seed, roi=scene.structure_bounds
        )
        proxy.export(entry / PROXY_FILE)
        return {
            "n_images": len(plan.viewpoints),
            "render_time_s": rendered.render_time_s,
            "n_faces": len(proxy.faces),
            **{k: v for k, v in record.items() if isinstance(v, int | float | str | bool)},
        }

    key = exploration_cache_key(scene, inputs)
    bundle_key = exploration_cache_key(scene, inputs, for_bundle=True)
    bundle = find_bundle(bundle_key) if use_bundle else None
    if bundle is None:
        entry, record = cached_entry(inputs.cache_dir, "exploration", key, build)
    else:
        # The committed proxy of this exploration (the study's): installed, not rebuilt, so every
        # machine plans on the same one. Keyed by its manifest too: a re-exported bundle reinstalls.
        def install(entry: Path) -> dict:
            log.info("exploration: the committed proxy %s", bundle)
            return install_bundle(bundle, entry, render_images)

        def render_images(viewpoints, kinds, out: Path) -> None:
            render_flight(scene, viewpoints, intrinsics, out, inputs.render, kinds=kinds)

        installed = f"{bundle_key}-{sha256(bundle / MANIFEST)[:8]}"
        entry, record = cached_entry(inputs.cache_dir, "exploration_bundle", installed, install)
    # ``cached``/``proxy_cached`` say whether build_proxy reused its own work folder; a cache entry is
    # always built fresh, so they read false even on a hit. ``cache_hit`` is the field that tells.
    record = {k: v for k, v in record.items() if k not in WORKDIR_REUSE_FLAGS}
    return entry, {**record, "entry": str(entry)}


def proxy_stage(scene: Scene, intrinsics: Intrinsics, inputs: ProxyInputs) -> tuple[trimesh.Trimesh, dict]:
    """The proxy the planners plan on, from ``reconstruct.proxy.source`` (arguments as
    ``build_exploration_proxy``).

    Returns:
        (proxy mesh in world metres, the ``proxy_*`` fields of ``metrics.json``: ``proxy_source``,
        and for a reconstruction the exploration's record, ``proxy_entry`` among them).
    """
    if inputs.reconstruct.proxy.source == "ground_truth_degraded":
        proxy = degraded_ground_truth(scene, inputs.reconstruct.proxy, int(inputs.seed))
        return proxy, {"proxy_source": "ground_truth_degraded (NOT the paper's setting)"}
    entry, record = build_exploration_proxy(scene, intrinsics, inputs)
    fields = {f"proxy_{k}": v for k, v in record.items() if isinstance(v, int | float | str | bool)}
    proxy = load_proxy(entry)
    # Cells that share this digest planned on the same proxy: a proxy rebuilt on another machine can
    # differ in a few faces (its fusion is not bit-reproducible across machines), and so can a plan.
    fields["proxy_fingerprint"] = mesh_fingerprint(proxy)
    return proxy, {**fields, "proxy_source": "reconstruction"}


def mesh_fingerprint(mesh: trimesh.Trimesh) -> str:
    """Hex digest of a mesh's vertices and faces (what a planner plans on)."""
    digest = hashlib.blake2b(digest_size=8)
    for array in (mesh.vertices, mesh.faces):
        digest.update(repr(array.shape).encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()
