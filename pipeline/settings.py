"""Every setting of a cell, checked before any work: a bad value costs one line, not an exploration.

``cell_settings(cfg)`` resolves the stages' groups of the composed run config once, as plain
values, and builds from them the typed settings each stage will use (the planner's parameters with
its budget, the camera, the drone, the whole reconstruction, evaluation; the scene, exploration and
render groups as plain values) and raises ``SettingsError`` naming the first bad setting.
``pipeline.cell.run_cell`` calls it before the scene loads and hands each stage its own part; no
stage reads the run config.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from drone.model import DroneSettings
from evaluate.settings import EvaluationSettings
from pipeline.protocol import protocol_fields
from pipeline.proxy import ProxyInputs
from planner.budget import DEFAULT_LEVEL, apply_budget
from reconstruct.cache_keys import flight_fusion_bytes
from reconstruct.dense_settings import DenseSettings
from reconstruct.settings import ReconstructSettings
from render.settings import RenderSettings
from scene.camera import Intrinsics
from scene.config import plain
from scene.plan import PlanningError
from scene.registry import SceneSettings

FLIGHT_ORDERS = ("flight_time", "planner")
# The run config's groups the stages read (the planner's is ``planner_setup``'s).
STAGE_GROUPS = ("survey", "camera", "drone", "reconstruct", "evaluate", "scene", "exploration", "render")


class SettingsError(ValueError):
    """A setting of the run config is out of range or unknown (the message names it)."""


@dataclass(frozen=True)
class PlannerSettings:
    """What the plan stage runs: the planner and its parameters.

    Attributes:
        target: the planner's ``plan`` function (``planner._target_``).
        params: its parameters, preset overrides and budget applied (``planner_setup``).
        flight_order: ``planner`` (its own order) or ``flight_time`` (``survey.flight_order``).
    """

    target: str
    params: DictConfig
    flight_order: str


@dataclass(frozen=True)
class CellSettings:
    """What the stages of one cell run with, every block checked, built once (``cell_settings``).

    Attributes:
        intrinsics: the survey camera (``camera``).
        drone: the drone (``drone``).
        planner_params: the planner's parameters, preset overrides and budget applied.
        budget: ``budget``, ``budget_knob``, ``budget_value`` for ``metrics.json``.
        evaluation: the evaluation settings (``evaluate``).
        target_gsd_m: the survey's target ground sampling distance (m/px).
        planner: the plan stage's part (``PlannerSettings``).
        scene: the ``scene`` group (``scene.registry.load_scene``).
        proxy: the proxy stage's groups (``pipeline.proxy.ProxyInputs``).
        render: the ``render`` group (``render.render_flight``).
        reconstruct: the ``reconstruct`` group, typed (``reconstruct.pipeline.reconstruct_flight``).
        seed: the cell's seed.
        cache_dir: the stage cache root.
        protocol: ``protocol`` and ``protocol_digest`` for ``metrics.json`` (``pipeline.protocol``).
    """

    intrinsics: Intrinsics
    drone: DroneSettings
    planner_params: DictConfig
    budget: dict
    evaluation: EvaluationSettings
    target_gsd_m: float
    planner: PlannerSettings
    scene: SceneSettings
    proxy: ProxyInputs
    render: RenderSettings
    reconstruct: ReconstructSettings
    seed: int
    cache_dir: str | None
    protocol: dict


def scene_label(cfg: DictConfig) -> str:
    """The scene's name in records: its config's name, or for ``scene=mesh`` the mesh file's stem
    (``scene.path=cache/meshes/hall.glb`` -> ``hall``), so two users' meshes are two scenes."""
    path = OmegaConf.select(cfg, "scene.path", default=None) if cfg.scene.name == "mesh" else None
    return Path(str(path)).stem if path else str(cfg.scene.name)


def planner_setup(cfg: DictConfig) -> tuple[DictConfig, dict]:
    """The planner's parameters, and the budget record (``budget``, ``budget_knob``, ``budget_value``).

    The experiment preset's overrides for this planner are merged in first: presets
    (conf/experiment/*.yaml) carry ``experiment.planner_overrides.<planner name>``, because each
    planner has parameters of its own. Then ``budget=<level>`` sets the planner's budget knob
    (``planner.budget``) and the ``budget`` block is dropped (``name`` and ``_target_`` stay).

    Raises:
        ValueError: a budget level the planner does not define.
    """
    overrides = OmegaConf.select(cfg, f"experiment.planner_overrides.{cfg.planner.name}")
    # Resolved first: planner settings interpolate run-level values (``${survey.target_gsd_m}``).
    params = OmegaConf.create(OmegaConf.to_container(cfg.planner, resolve=True))
    if overrides:
        params = OmegaConf.merge(params, overrides)
    params, budget = apply_budget(
        OmegaConf.to_container(params, resolve=True), str(cfg.get("budget", DEFAULT_LEVEL)), cfg.planner.name
    )
    # The planner's version (bumped by hand when its plans change) goes into the record, not the plan.
    version = params.pop("version", None)
    budget["planner_version"] = None if version is None else int(version)
    return OmegaConf.create(params), budget


def planner_params(cfg: DictConfig) -> DictConfig:
    """The parameters ``plan`` receives (``planner_setup`` without the budget record)."""
    return planner_setup(cfg)[0]


def check_planner(target: str, params, intrinsics: Intrinsics) -> None:
    """Call the planner module's ``check_params`` (the planner contract, ``planner.base``), if any."""
    module_name = target.rsplit(".", 1)[0]
    module = hydra.utils.get_object(module_name) if "." in target else None
    check = getattr(module, "check_params", None)
    if check is not None:
        check(params, intrinsics)


def check_fusion_memory(dense: DenseSettings, camera: Intrinsics) -> None:
    """Refuse a fusion memory budget that cannot hold two of the flight's views (fusion's least)."""
    budget = dense.fusion.max_memory_gb
    if budget is None or isinstance(budget, str):
        return
    size = {"width": camera.width, "height": camera.height}
    two_views_gb = flight_fusion_bytes(2, size, {"max_image_size": dense.max_image_size}) / 1e9
    if budget < two_views_gb:
        raise ValueError(
            f"reconstruct.dense.fusion.max_memory_gb={budget:g} holds fewer than two views of "
            f"{camera.width}x{camera.height} images: at least {two_views_gb:.3f} GB"
        )


def cell_settings(cfg: DictConfig) -> CellSettings:
    """Build and check every block of a cell's config (see the module docstring).

    Raises:
        SettingsError: the first bad setting, named, with the reason.
    """
    try:
        # Each stage's group as plain values, resolved once: every block below is typed from these.
        group = {name: plain(cfg[name]) for name in STAGE_GROUPS}
        gsd = group["survey"]["target_gsd_m"]
        if isinstance(gsd, bool) or not isinstance(gsd, int | float) or not (math.isfinite(gsd) and gsd > 0):
            raise ValueError(f"survey.target_gsd_m must be a positive number (m/px), got {gsd!r}")
        try:
            intrinsics = Intrinsics(**group["camera"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"camera: {exc}") from exc
        drone = DroneSettings.from_config(group["drone"])
        order = group["survey"].get("flight_order", "planner")
        if order not in FLIGHT_ORDERS:
            raise ValueError(f"survey.flight_order must be one of {FLIGHT_ORDERS}, got {order!r}")
        # The reconstruction before the planner: ours' budget prune reads the dense stage's partner
        # test (planner.budget_partners), so a bad value is named where the user set it.
        reconstruct = ReconstructSettings.from_config(group["reconstruct"])
        check_fusion_memory(reconstruct.dense, intrinsics)
        params, budget = planner_setup(cfg)
        target = str(cfg.planner._target_)
        check_planner(target, params, intrinsics)
        evaluation = EvaluationSettings.from_config(group["evaluate"])
        render = RenderSettings.from_config(group["render"])
    except SettingsError:
        raise
    except (ValueError, TypeError, KeyError, PlanningError) as exc:
        raise SettingsError(str(exc).strip("'\"")) from exc
    seed = int(cfg.seed)
    proxy = ProxyInputs(
        group["scene"],
        group["camera"],
        group["exploration"],
        render,
        reconstruct,
        str(cfg.cache_dir),
        seed,
    )
    return CellSettings(
        intrinsics,
        drone,
        params,
        budget,
        evaluation,
        float(gsd),
        planner=PlannerSettings(target, params, str(order)),
        scene=SceneSettings(proxy.scene),
        proxy=proxy,
        render=render,
        reconstruct=reconstruct,
        seed=seed,
        cache_dir=None if cfg.cache_dir is None else str(cfg.cache_dir),
        protocol=protocol_fields(cfg, scene_label(cfg)),
    )
