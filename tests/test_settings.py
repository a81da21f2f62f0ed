"""A bad setting in any typed block is refused before the scene loads, with the setting's name."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from pipeline import cell
from pipeline.settings import SettingsError, cell_settings
from reconstruct.dense_settings import DenseSettings
from reconstruct.sfm_settings import SfmSettings

ROOT = Path(__file__).resolve().parents[1]


def composed(*overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return compose(config_name="config", overrides=list(overrides))


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        (["survey.target_gsd_m=-1"], "survey.target_gsd_m"),
        (["camera.hfov_deg=200"], "hfov_deg"),
        (["drone.cruise_speed_m_s=0"], "drone.cruise_speed_m_s"),
        (["planner=ours", "planner.heuristics.k_count=0"], "heuristics.k_count"),
        (["planner=ours", "planner.cmaes.cluster_size=0"], "cmaes.cluster_size"),
        (["planner=ours_plus", "planner.flight_time.weight_per_pct=-1"], "flight_time.weight_per_pct"),
        (["planner=smith", "planner.front_overlap=1.5"], "front_overlap"),
        (["planner=yan", "planner.theta_t_deg=95"], "theta_t_deg"),
        (["planner=lawnmower", "planner.mode=spiral"], "mode"),
        (
            ["reconstruct.sfm.mapping.global_ba_growth_ratio=1.0"],
            "reconstruct.sfm.mapping.global_ba_growth_ratio",
        ),
        (["reconstruct.sfm.extraction.max_num_features=0"], "reconstruct.sfm.extraction.max_num_features"),
        (["reconstruct.sfm.matching.method=magic"], "reconstruct.sfm.matching.method"),
        (["reconstruct.dense.num_partners=0"], "reconstruct.dense.num_partners"),
        (["reconstruct.dense.fusion.max_memory_gb=-2"], "reconstruct.dense.fusion.max_memory_gb"),
        (["reconstruct.dense.sgbm.block_size=4"], "reconstruct.dense.sgbm.block_size"),
        (["reconstruct.dense.sgbm.p1_per_block_pixel=-1"], "reconstruct.dense.sgbm.p1_per_block_pixel"),
        (
            ["reconstruct.dense.sgbm.p2_per_block_pixel=0.5"],
            "reconstruct.dense.sgbm.p2_per_block_pixel must be at least p1_per_block_pixel",
        ),
        (["+reconstruct.dense.num_partner=3"], "num_partner"),
        (["reconstruct.proxy.dense.max_image_size=0"], "reconstruct.proxy.dense.max_image_size"),
        (["evaluate.gt_sample_density_per_m2=-5"], "gt_sample_density_per_m2"),
        (["reconstruct.dense.oracle.disparity_sigma_px=-1"], "reconstruct.dense.oracle.disparity_sigma_px"),
        (["reconstruct.dense.oracle.disparity_sigma_px=nan"], "reconstruct.dense.oracle.disparity_sigma_px"),
        (["reconstruct.dense.fusion.max_memory_gb=0.01"], "max_memory_gb=0.01 holds fewer than two views"),
        (["reconstruct.dense.fusion.max_memory_gb=lots"], "reconstruct.dense.fusion.max_memory_gb"),
        (["reconstruct.dense.fusion.method=voxels"], "reconstruct.dense.fusion.method"),
        (["reconstruct.dense.fusion.gate_disparity_px=-1"], "reconstruct.dense.fusion.gate_disparity_px"),
        (["reconstruct.dense.fusion.gate_disparity_px=nan"], "reconstruct.dense.fusion.gate_disparity_px"),
        (["survey.flight_order=alphabetical"], "survey.flight_order"),
        (["reconstruct.proxy.source=guess"], "reconstruct.proxy.source must be one of"),
        (["reconstruct.proxy.density_quantile=1.0"], "reconstruct.proxy.density_quantile must lie in [0, 1)"),
        (["reconstruct.proxy.degraded.max_edge_m=0"], "reconstruct.proxy.degraded.max_edge_m must be > 0"),
        (["reconstruct.align.merge_min_images=0"], "reconstruct.align.merge_min_images must be >= 1"),
        (
            ["+reconstruct.align.max_error_sigma=3"],
            "reconstruct.align: unknown setting(s) ['max_error_sigma']",
        ),
        (["reconstruct.gnss.sigma_m=-1"], "reconstruct.gnss.sigma_m must be >= 0"),
        (
            ["reconstruct.min_registered_fraction=1.5"],
            "reconstruct.min_registered_fraction must be <= 1",
        ),
    ],
)
def test_a_bad_setting_is_refused_by_name(overrides, named):
    with pytest.raises(SettingsError, match=re.escape(named)):
        cell_settings(composed(*overrides))


def test_every_preset_passes():
    for preset in ("default", "smoke", "paper", "budgets", "ablation", "ours_plus_front"):
        for planner in ("ours", "ours_plus", "smith", "yan", "lawnmower"):
            cell_settings(composed(f"experiment={preset}", f"planner={planner}"))


def test_the_refusal_comes_before_the_scene_loads(monkeypatch, tmp_path):
    def no_scene(*args, **kwargs):
        raise AssertionError("the scene was loaded before the settings were checked")

    monkeypatch.setattr(cell, "load_scene", no_scene)
    record = cell.cell_record(composed())
    with pytest.raises(SettingsError, match=r"reconstruct\.dense\.num_partners must be >= 1, got 0"):
        cell.run_cell(composed("reconstruct.dense.num_partners=0"), tmp_path, record)
    assert record["stage"] == "config"


def test_a_refused_cell_exits_with_one_line_and_a_failed_record(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "run.py",
            "reconstruct.sfm.mapping.local_ba_num_images=0",
            f"hydra.run.dir={tmp_path}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1
    lines = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert lines == [
        "error: cell tomb/ours failed in stage config: reconstruct.sfm.mapping.local_ba_num_images must be "
        ">= 1, got 0 (traceback: HYDRA_FULL_ERROR=1)"
    ]
    record = json.loads((tmp_path / "metrics.json").read_text())
    assert (record["status"], record["failed_stage"]) == ("failed", "config")
    assert "scene_fingerprint" not in record  # the scene never loaded


def test_typed_blocks_keep_the_yaml_values():
    cfg = composed()
    dense = DenseSettings.from_config(cfg.reconstruct.dense)
    sfm = SfmSettings.from_config(cfg.reconstruct.sfm)
    assert (dense.num_partners, dense.fusion.min_num_pixels, dense.sgbm.block_size) == (4, 3, 5)
    assert dense.fusion.max_memory_gb == "auto"
    assert (sfm.mapping.local_ba_num_images, sfm.matching.max_ratio, sfm.extraction.max_num_features) == (
        4,
        0.8,
        4096,
    )


def test_the_reconstruct_group_is_typed_once_with_the_proxy_flight_beside_it():
    from reconstruct.settings import ReconstructSettings

    settings = ReconstructSettings.from_config(composed().reconstruct)
    assert (settings.min_images, settings.gnss_sigma_m, settings.deterministic) == (3, 0.05, True)
    assert (settings.align.max_error_sigmas, settings.align.merge_min_images) == (3.0, 8)
    assert (settings.proxy.face_budget, settings.proxy.voxel_size_m, settings.proxy.roi_margin_m) == (
        50000,
        0.05,
        10.0,
    )
    # The exploratory flight: proxy.dense over dense, key by key; the rest of dense as it is.
    exploration = settings.for_exploration()
    assert (exploration.dense.max_image_size, exploration.dense.fusion.method) == (640, "colmap")
    assert (exploration.dense.fusion.max_normal_error, exploration.dense.sgbm.p1_per_block_pixel) == (
        10.0,
        8.0,
    )
    assert exploration.dense.num_partners == settings.dense.num_partners == 4
    assert (settings.dense.max_image_size, settings.dense.fusion.method) == (1024, "rays")
    assert (
        exploration.node["dense"]["max_image_size"] == 640
        and settings.node["dense"]["max_image_size"] == 1024
    )


def test_a_stage_function_refuses_a_config_mapping(tmp_path):
    """The reconstruction's functions take typed settings: a mapping is refused before any work."""
    from reconstruct.pipeline import build_proxy, oracle_flight, reconstruct_flight
    from reconstruct.sfm import sfm_options

    cfg = composed().reconstruct
    for call in (
        lambda: reconstruct_flight(tmp_path, tmp_path / "out", cfg, 0),
        lambda: build_proxy(tmp_path, tmp_path / "out", cfg, 0),
        lambda: oracle_flight(tmp_path, tmp_path, tmp_path / "out", cfg, 0, None),
        lambda: sfm_options(cfg.sfm),
    ):
        with pytest.raises(TypeError, match="Settings"):
            call()
    assert not (tmp_path / "out").exists()


def test_each_stage_is_handed_its_typed_part_not_the_run_config(monkeypatch, tmp_path):
    """The run config is read once (``cell_settings``): no stage of ``run_cell`` gets a Hydra
    mapping or a dict, each gets its own typed part of the settings."""
    from types import SimpleNamespace

    from omegaconf import DictConfig

    from pipeline.settings import CellSettings
    from reconstruct.settings import ReconstructSettings
    from render.settings import RenderSettings
    from scene.registry import SceneSettings

    calls: dict[str, tuple] = {}

    def stage(name, result):
        def spy(*args, **kwargs):
            calls[name] = (*args, *kwargs.values())
            return result

        return spy

    scene = SimpleNamespace(fingerprint="f", ground_truth_mesh=None)
    plan = SimpleNamespace(viewpoints=[], kinds=[])
    monkeypatch.setattr(cell, "load_scene", stage("scene", scene))
    monkeypatch.setattr(cell, "proxy_stage", stage("proxy", (object(), {})))
    monkeypatch.setattr(cell, "planned", stage("plan", (plan, {})))
    monkeypatch.setattr(cell, "render_flight", stage("render", SimpleNamespace(render_time_s=0.0)))
    monkeypatch.setattr(cell, "reconstruct_flight", stage("reconstruct", {"dense_ply": "d.ply"}))
    monkeypatch.setattr(cell, "evaluate_reconstruction", stage("evaluate", {}))
    monkeypatch.setattr(cell, "oracle_stage", stage("oracle", {}))
    cfg = composed("reconstruct.oracle_beside=true")
    cell.run_cell(cfg, tmp_path, cell.cell_record(cfg))
    assert set(calls) == {"scene", "proxy", "plan", "render", "reconstruct", "evaluate", "oracle"}
    for name, args in calls.items():
        assert not any(isinstance(a, DictConfig | dict) for a in args), name
    assert isinstance(calls["scene"][0], SceneSettings)
    assert isinstance(calls["plan"][1], CellSettings)
    assert isinstance(calls["render"][4], RenderSettings)
    assert isinstance(calls["reconstruct"][2], ReconstructSettings)
    assert isinstance(calls["oracle"][2], ReconstructSettings)
