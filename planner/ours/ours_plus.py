"""``ours_plus``: the paper's planner with the two extensions its conclusion proposes.

1. Evidence from the exploratory flight (``planner.ours.evidence``): each proxy sample weighs
   ``1 + evidence.weight * uncertainty`` in the objective, and the most unsure samples are served
   first when views are added and repaired. The planner still sees only the exploration's files
   (its fused cloud travels with the proxy), never the ground truth.
2. Flight time in the objective (``planner.ours.flight_time_term``): CMA-ES and culling maximise R minus
   ``flight_time.weight_per_pct`` per 1 % of the plan's first flight (its views after the first
   addition), timed by the missions' model for ``drone``.

With ``evidence.weight = 0`` and ``flight_time.weight_per_pct = 0`` the plan is ``ours``' plan, view
for view. Parameters: ``conf/planner/ours_plus.yaml`` (ours' settings plus the three sections).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import trimesh
from threadpoolctl import threadpool_limits

from drone.model import DroneSettings
from planner.base import plain_params
from planner.ours.evidence import EvidenceSettings, proxy_evidence, sample_weights
from planner.ours.flight_time_term import FlightTimeTerm
from planner.ours.ours import PlanExtensions, plan_with, resolve_params
from planner.ours.ours_settings import OursSettings
from scene.camera import Intrinsics
from scene.plan import Plan, PlanningError
from scene.proxy_mesh import PROXY_CLOUD_KEY

EXTRA_SECTIONS = ("evidence", "flight_time")


def evidence_weigher(proxy: trimesh.Trimesh, settings: EvidenceSettings):
    """(points, normals) -> (weights, record) from the cloud the proxy carries (and the
    exploration's images, with ``evidence.photo``); all ones (and a record that says so) when the
    proxy has no cloud (a degraded ground truth) or the weight is 0."""

    def weigh(points: np.ndarray, normals: np.ndarray):
        if settings.weight == 0.0:
            return None, {"source": "off"}
        signals = proxy_evidence(proxy, points, normals, settings)
        if signals is None:
            return None, {"source": "none (the proxy carries no exploration cloud)"}
        weights = sample_weights(signals["uncertainty"], settings)
        with_photo = "photo" in signals
        kinds = ("gap", "support", "normal") + (("photo",) if with_photo else ())
        record = {
            "source": "exploration cloud" + (" and images" if with_photo else ""),
            "n_cloud_points": len(proxy.metadata[PROXY_CLOUD_KEY]["points"]),
            "weight_mean": float(weights.mean()),
            "weight_max": float(weights.max()),
            "share_unsure": float(np.mean(signals["uncertainty"] > 0.5)),
            **{f"share_{k}_signal": float(np.mean(signals[k] > 0.5)) for k in kinds},
            "weights": np.round(weights, 4).tolist(),
        }
        if with_photo:
            record["share_photo_scored"] = float(np.mean(np.isfinite(signals["photo_ncc"])))
        return weights, record

    return weigh


def _parsed(params: Mapping) -> tuple[EvidenceSettings, float, DroneSettings, dict]:
    """(evidence settings, flight-time weight per percent, drone, the paper's resolved settings)."""
    raw = plain_params(params)
    missing = [k for k in EXTRA_SECTIONS if k not in raw]
    if missing:
        raise PlanningError(f"planner ours_plus: missing setting(s) {missing} (conf/planner/ours_plus.yaml)")
    evidence = EvidenceSettings.from_config(raw.pop("evidence"))
    time_cfg = raw.pop("flight_time")
    weight_per_pct = float(time_cfg["weight_per_pct"])
    if weight_per_pct < 0:
        raise PlanningError(
            f"planner ours_plus: flight_time.weight_per_pct must be >= 0, got {weight_per_pct}"
        )
    cfg = resolve_params(raw)  # the drone is ours' too (budget_limit)
    return evidence, weight_per_pct, DroneSettings.from_config(cfg["drone"]), cfg


def check_params(params: Mapping, intrinsics: Intrinsics) -> None:
    """Refuse a bad setting before any work (the planner contract, ``planner.base``)."""
    OursSettings.build(_parsed(params)[3], intrinsics)


def plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan:
    """Plan like ``planner.ours.ours.plan`` with the exploration's evidence and a flight-time term."""
    evidence, weight_per_pct, drone, cfg = _parsed(params)

    def time_term(takeoff: np.ndarray) -> FlightTimeTerm:
        return FlightTimeTerm(drone, weight_per_pct, np.asarray(takeoff, float))

    ext = PlanExtensions(
        weigh_samples=evidence_weigher(proxy, evidence),
        time_term=time_term if weight_per_pct > 0 else None,
        planner="ours_plus",
    )
    with threadpool_limits(limits=1):
        return plan_with(proxy, intrinsics, cfg, seed, ext)
