"""The stage cache builds an entry once, even with concurrent builders, and never trusts half entries."""

import json
import multiprocessing as mp
import time
from pathlib import Path

import pytest

from pipeline.cache import MARKER, cache_key, cached_entry


def _build_slowly(cache_dir: str, counter: str) -> str:
    def build(entry: Path) -> dict:
        with open(counter, "a") as f:
            f.write("built\n")
        time.sleep(0.5)
        (entry / "out.txt").write_text("proxy")
        return {"value": 7}

    entry, record = cached_entry(cache_dir, "proxy", "k1", build)
    return json.dumps([str(entry), record["value"], record["cache_hit"]])


def test_concurrent_builders_build_once(tmp_path):
    counter = tmp_path / "count.txt"
    ctx = mp.get_context("fork")
    with ctx.Pool(3) as pool:
        results = [json.loads(r) for r in pool.starmap(_build_slowly, [(str(tmp_path), str(counter))] * 3)]
    assert counter.read_text().count("built") == 1
    assert sorted(r[2] for r in results) == [False, True, True]
    assert {r[1] for r in results} == {7}
    assert (Path(results[0][0]) / "out.txt").read_text() == "proxy"


def test_failed_build_leaves_nothing_and_incomplete_entry_is_rebuilt(tmp_path):
    def failing(entry: Path) -> dict:
        (entry / "half.txt").write_text("half")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        cached_entry(tmp_path, "proxy", "k2", failing)
    assert not (tmp_path / "proxy" / "k2").exists()

    # an entry without its marker (a killed run) is discarded, not trusted
    stale = tmp_path / "proxy" / "k2"
    stale.mkdir(parents=True)
    (stale / "half.txt").write_text("half")
    entry, record = cached_entry(tmp_path, "proxy", "k2", lambda e: {"n": 1})
    assert record == {"n": 1, "built_s": pytest.approx(record["built_s"]), "cache_hit": False}
    assert not (entry / "half.txt").exists()
    assert (entry / MARKER).is_file()


def test_cache_key_depends_on_content_only():
    assert cache_key({"a": 1, "b": [1, 2]}) == cache_key({"b": [1, 2], "a": 1})
    assert cache_key({"a": 1}) != cache_key({"a": 2})
    assert len(cache_key("x")) == 16


def test_exploration_key_follows_the_scene_content_not_only_its_config():
    import numpy as np
    from hydra import compose, initialize_config_dir

    from pipeline.proxy import exploration_cache_key as key_of
    from scene.base import Box, MeshPart, Scene

    conf_dir = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf_dir), version_base=None):
        cfg = compose(config_name="config", overrides=["scene=tomb"])

    def scene(texture_value: int) -> Scene:
        quad = MeshPart(
            "ground",
            np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float),
            np.array([[0, 1, 2], [0, 2, 3]]),
            uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float),
            texture="ground",
        )
        texture = np.full((4, 4, 3), texture_value, np.uint8)
        box = Box((0, 0, 0), (1, 1, 1))
        return Scene("tomb", [quad], {"ground": texture}, box, box)

    def exploration_cache_key(cfg, scene):
        return key_of(
            scene, cfg.scene, cfg.camera, cfg.exploration, cfg.render, cfg.reconstruct, int(cfg.seed)
        )

    same_a, same_b, other = scene(10), scene(10), scene(11)
    assert exploration_cache_key(cfg, same_a) == exploration_cache_key(cfg, same_b)
    # One texel value changed: a generator change must not be served the old scene's flight.
    assert exploration_cache_key(cfg, other) != exploration_cache_key(cfg, same_a)

    # Reconstruction settings the proxy depends on change the key; keeping the dense workspace does not.
    def key_with(override: str) -> str:
        with initialize_config_dir(config_dir=str(conf_dir), version_base=None):
            changed = compose(config_name="config", overrides=["scene=tomb", override])
        return exploration_cache_key(changed, same_a)

    assert key_with("reconstruct.keep_dense_workspace=false") == exploration_cache_key(cfg, same_a)
    assert key_with("reconstruct.dense.num_partners=7") != exploration_cache_key(cfg, same_a)
    assert key_with("reconstruct.proxy.roi_margin_m=null") != exploration_cache_key(cfg, same_a)
    # The global mapper's own settings do not move an incremental run's key; they do move a global one's.
    assert key_with("reconstruct.sfm.mapping.global_prior_ba=false") == exploration_cache_key(cfg, same_a)
    assert key_with("reconstruct.sfm.mapping.method=global") != exploration_cache_key(cfg, same_a)
    with initialize_config_dir(config_dir=str(conf_dir), version_base=None):
        glob = compose("config", overrides=["scene=tomb", "reconstruct.sfm.mapping.method=global"])
        glob_raw = compose(
            "config",
            overrides=[
                "scene=tomb",
                "reconstruct.sfm.mapping.method=global",
                "reconstruct.sfm.mapping.global_prior_ba=false",
            ],
        )
    assert exploration_cache_key(glob, same_a) != exploration_cache_key(glob_raw, same_a)
