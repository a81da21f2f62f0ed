"""``ours_plus``: evidence weights from the exploration's cloud, the flight-time term, and the
identity with ``ours`` when both are off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from drone.model import DroneSettings, split_flights
from planner.ours import ours, ours_plus
from planner.ours.evidence import EvidenceSettings, evidence_signals, sample_weights
from planner.ours.flight_time_term import FlightTimeTerm, greedy_order
from scene.plan import PlanningError
from scene.proxy_mesh import PROXY_CLOUD_KEY
from tests.planner_scenes import box_building
from tests.test_planner_ours import CAMERA, SMALL

ROOT = Path(__file__).resolve().parents[1]
DRONE = yaml.safe_load((ROOT / "conf" / "drone" / "default.yaml").read_text())
EVIDENCE = {
    "weight": 2.0,
    "radius_m": 0.3,
    "gap_lo_m": 0.15,
    "gap_hi_m": 0.6,
    "support_lo": 0.25,
    "support_hi": 0.75,
    "normal_lo_deg": 25.0,
    "normal_hi_deg": 60.0,
}


def _grid(a, b, step=0.1):
    return np.arange(a, b + 1e-9, step)


def recessed_wall_cloud():
    """The exploration's cloud (10 cm spacing, unit normals) of a wall x = 0 (facing +x, 10 x 6 m)
    with a 2 x 2 m recess 1 m deep at |y| < 1, 2 < z < 4: wall, recess floor and four recess sides."""
    y, z = np.meshgrid(_grid(-5, 5), _grid(0, 6), indexing="ij")
    wall = np.c_[np.zeros(y.size), y.ravel(), z.ravel()]
    mouth = (np.abs(wall[:, 1]) < 1 - 1e-9) & (wall[:, 2] > 2 + 1e-9) & (wall[:, 2] < 4 - 1e-9)
    parts = [(wall[~mouth], [1.0, 0.0, 0.0])]
    a, b = np.meshgrid(_grid(-1, 1), _grid(2, 4), indexing="ij")
    parts.append((np.c_[np.full(a.size, -1.0), a.ravel(), b.ravel()], [1.0, 0.0, 0.0]))
    for y0, n in ((-1.0, [0.0, 1.0, 0.0]), (1.0, [0.0, -1.0, 0.0])):
        d, zz = np.meshgrid(_grid(-1, 0), _grid(2, 4), indexing="ij")
        parts.append((np.c_[d.ravel(), np.full(d.size, y0), zz.ravel()], n))
    for z0, n in ((2.0, [0.0, 0.0, 1.0]), (4.0, [0.0, 0.0, -1.0])):
        d, yy = np.meshgrid(_grid(-1, 0), _grid(-1, 1), indexing="ij")
        parts.append((np.c_[d.ravel(), yy.ravel(), np.full(d.size, z0)], n))
    points = np.vstack([p for p, _ in parts])
    normals = np.vstack([np.tile(n, (len(p), 1)) for p, n in parts]).astype(float)
    return points, normals


def test_a_bridged_recess_weighs_more_at_its_rim_than_an_intact_wall():
    """The proxy bridged the recess (a flat wall): samples on the flat wall keep weight 1, samples
    5 cm inside the rim get the normal signal (the cloud turns into the recess: 49 deg, 0.69), and
    samples over the mouth get the full weight 3 (no cloud within 0.5-1 m)."""
    cloud, cloud_normals = recessed_wall_cloud()
    y, z = np.meshgrid(_grid(-5, 5, 0.25), _grid(0, 6, 0.25), indexing="ij")
    proxy = np.c_[np.zeros(y.size), y.ravel(), z.ravel()]
    probes = np.array([[0, -4, 1], [0, 3.5, 5], [0, 0.95, 3], [0, -0.95, 3], [0, 0, 2.05], [0, 0, 3]], float)
    samples = np.vstack([proxy, probes])
    settings = EvidenceSettings.from_config(EVIDENCE)
    signals = evidence_signals(
        samples, np.tile([1.0, 0.0, 0.0], (len(samples), 1)), cloud, cloud_normals, settings
    )
    weights = sample_weights(signals["uncertainty"], settings)[-len(probes) :]
    flat, rim, mouth = weights[:2], weights[2:5], weights[5]
    assert flat == pytest.approx([1.0, 1.0])
    assert signals["normal_deg"][-4:-1] == pytest.approx([49.09, 49.09, 49.09], abs=0.05)
    assert rim == pytest.approx([2.376] * 3, abs=1e-3)
    assert mouth == pytest.approx(3.0)
    assert rim.min() > flat.max()


def test_evidence_settings_are_checked():
    with pytest.raises(PlanningError, match="evidence.gap_lo_m must be below evidence.gap_hi_m"):
        EvidenceSettings.from_config({**EVIDENCE, "gap_lo_m": 1.0})
    with pytest.raises(PlanningError, match="evidence.weight must be >= 0"):
        EvidenceSettings.from_config({**EVIDENCE, "weight": -1.0})


def test_flight_time_term_is_the_missions_flight_time():
    """Legs and stops of the term equal one mission flight minus take-off and landing."""
    drone = DroneSettings.from_config(DRONE)
    vps = np.array([[10.0, 0, 8, 0, -30], [10, 12, 8, 90, -30], [-5, 12, 20, 180, -60]])
    home = np.zeros(3)
    flight = split_flights(vps, home, drone)
    term = FlightTimeTerm(drone, 6.0, home)
    seconds = float(term.seconds(vps))
    assert seconds == pytest.approx(flight[0].time_s - drone.takeoff_s - drone.landing_s)
    with pytest.raises(ValueError, match="no reference flight"):
        term.cost(vps)
    # Referenced on the first two views (greedy order from home: the same two legs out and back):
    # the full flight costs 6 units per 1 % of theirs.
    reference = float(term.seconds(vps[:2]))
    referenced = term.referenced(vps[:2])
    assert referenced.reference_s == pytest.approx(reference)
    assert float(referenced.cost(vps)) == pytest.approx(6.0 * 100.0 * seconds / reference)
    assert float(referenced.cost(vps[:2])) == pytest.approx(600.0)
    # batched over alternatives: the same per set
    both = term.seconds(np.stack([vps, vps[::-1]]))
    assert both[0] == pytest.approx(seconds) and both[1] == pytest.approx(float(term.seconds(vps[::-1])))
    assert greedy_order(vps[:, :3], home).tolist() == [0, 1, 2]


def _params(evidence_weight: float, weight_per_pct: float) -> dict:
    return {
        **SMALL,
        "evidence": {**EVIDENCE, "weight": evidence_weight},
        "flight_time": {"weight_per_pct": weight_per_pct},
        "drone": DRONE,
    }


@pytest.fixture(scope="module")
def box():
    return box_building(size=(10.0, 8.0, 6.0), ground_half=14.0)


@pytest.fixture(scope="module")
def ours_box_plan(box):
    return ours.plan(box, CAMERA, SMALL, seed=3)


def test_with_both_terms_off_ours_plus_is_ours_view_for_view(box, ours_box_plan):
    plus = ours_plus.plan(box, CAMERA, _params(0.0, 0.0), seed=3)
    assert plus.planner == "ours_plus"
    np.testing.assert_array_equal(plus.viewpoints, ours_box_plan.viewpoints)
    assert plus.kinds == ours_box_plan.kinds


def test_time_weight_zero_with_no_cloud_is_ours(box, ours_box_plan):
    """A proxy without an exploration cloud has no evidence: with time weight 0 the plan is ours'."""
    plus = ours_plus.plan(box, CAMERA, _params(2.0, 0.0), seed=3)
    assert plus.info["evidence"]["source"].startswith("none")
    np.testing.assert_array_equal(plus.viewpoints, ours_box_plan.viewpoints)


def test_a_heavy_time_weight_flies_a_shorter_plan(box, ours_box_plan):
    drone = DroneSettings.from_config(DRONE)
    home = np.asarray(ours_box_plan.info["takeoff"])
    fast = ours_plus.plan(box, CAMERA, _params(0.0, 60.0), seed=3)
    term = FlightTimeTerm(drone, 1.0, home)
    t_ours = float(term.seconds(ours_box_plan.viewpoints))
    t_fast = float(term.seconds(fast.viewpoints))
    assert fast.info["time_weight_per_pct"] == 60.0
    assert t_fast < 0.9 * t_ours, (t_fast, t_ours)


def test_evidence_from_a_cloud_changes_the_plan(box, ours_box_plan):
    """A cloud that covers only the box's +x half: the rest of the proxy is unsure (weight up to 3),
    and the plan is no longer ours'."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(box, 4000, seed=0)
    half = points[points[:, 0] > 0]
    proxy = box.copy()
    proxy.metadata[PROXY_CLOUD_KEY] = {"points": half, "normals": np.tile([0.0, 0.0, 1.0], (len(half), 1))}
    plan = ours_plus.plan(proxy, CAMERA, _params(2.0, 0.0), seed=3)
    ev = plan.info["evidence"]
    assert ev["source"] == "exploration cloud" and ev["weight_max"] == pytest.approx(3.0)
    assert ev["share_unsure"] > 0.3
    assert plan.viewpoints.shape != ours_box_plan.viewpoints.shape or not np.array_equal(
        plan.viewpoints, ours_box_plan.viewpoints
    )


def test_bad_ours_plus_settings_are_refused(box):
    with pytest.raises(PlanningError, match="flight_time.weight_per_pct must be >= 0"):
        ours_plus.plan(box, CAMERA, _params(0.0, -1.0), seed=0)
    with pytest.raises(PlanningError, match="missing setting"):
        ours_plus.plan(box, CAMERA, SMALL, seed=0)
