"""Every setting of a cell, checked before any work: a bad value costs one line, not an exploration.

``cell_settings(cfg)`` builds the typed settings each stage will use from the composed run config
(the planner's parameters with its budget, the camera, the drone, SfM, dense, evaluation) and
raises ``SettingsError`` naming the first bad setting. ``pipeline.cell.run_cell`` calls it before
the scene loads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import hydra
from omegaconf import DictConfig, OmegaConf

from drone.model import DroneSettings
from evaluate.settings import EvaluationSettings
from planner.budget import DEFAULT_LEVEL, apply_budget
from reconstruct.cache_keys import flight_fusion_bytes
from reconstruct.dense_settings import DenseSettings
from reconstruct.pipeline import proxy_flight_config
from reconstruct.sfm_settings import SfmSettings
from scene.camera import Intrinsics
from scene.config import plain
from scene.plan import PlanningError

FLIGHT_ORDERS = ("flight_time", "planner")


class SettingsError(ValueError):
    """A setting of the run config is out of range or unknown (the message names it)."""


@dataclass(frozen=True)
class CellSettings:
    """What the stages of one cell run with, every block checked.

    Attributes:
        intrinsics: the survey camera (``camera``).
        drone: the drone (``drone``).
        planner_params: the planner's parameters, preset overrides and budget applied.
        budget: ``budget``, ``budget_knob``, ``budget_value`` for ``metrics.json``.
        evaluation: the evaluation settings (``evaluate``).
        target_gsd_m: the survey's target ground sampling distance (m/px).
    """

    intrinsics: Intrinsics
    drone: DroneSettings
    planner_params: DictConfig
    budget: dict
    evaluation: EvaluationSettings
    target_gsd_m: float


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


def check_fusion_memory(dense: DenseSettings, camera: dict) -> None:
    """Refuse a fusion memory budget that cannot hold two of the flight's views (fusion's least)."""
    budget = dense.fusion.max_memory_gb
    if budget is None or isinstance(budget, str):
        return
    two_views_gb = flight_fusion_bytes(2, camera, {"max_image_size": dense.max_image_size}) / 1e9
    if budget < two_views_gb:
        raise ValueError(
            f"reconstruct.dense.fusion.max_memory_gb={budget:g} holds fewer than two views of "
            f"{camera['width']}x{camera['height']} images: at least {two_views_gb:.3f} GB"
        )


def cell_settings(cfg: DictConfig) -> CellSettings:
    """Build and check every block of a cell's config (see the module docstring).

    Raises:
        SettingsError: the first bad setting, named, with the reason.
    """
    try:
        gsd = cfg.survey.target_gsd_m
        if isinstance(gsd, bool) or not isinstance(gsd, int | float) or not (math.isfinite(gsd) and gsd > 0):
            raise ValueError(f"survey.target_gsd_m must be a positive number (m/px), got {gsd!r}")
        try:
            intrinsics = Intrinsics(**plain(cfg.camera))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"camera: {exc}") from exc
        drone = DroneSettings.from_config(plain(cfg.drone))
        order = OmegaConf.select(cfg, "survey.flight_order", default="planner")
        if order not in FLIGHT_ORDERS:
            raise ValueError(f"survey.flight_order must be one of {FLIGHT_ORDERS}, got {order!r}")
        # The reconstruction before the planner: ours' budget prune reads the dense stage's partner
        # test (planner.budget_partners), so a bad value is named where the user set it.
        SfmSettings.from_config(cfg.reconstruct.sfm)
        dense = DenseSettings.from_config(cfg.reconstruct.dense)
        DenseSettings.from_config(proxy_flight_config(cfg.reconstruct)["dense"], "reconstruct.proxy.dense")
        check_fusion_memory(dense, plain(cfg.camera))
        params, budget = planner_setup(cfg)
        check_planner(str(cfg.planner._target_), params, intrinsics)
        evaluation = EvaluationSettings.from_config(cfg.evaluate)
    except SettingsError:
        raise
    except (ValueError, TypeError, KeyError, PlanningError) as exc:
        raise SettingsError(str(exc).strip("'\"")) from exc
    return CellSettings(intrinsics, drone, params, budget, evaluation, float(gsd))
