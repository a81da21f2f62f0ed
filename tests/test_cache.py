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

    from pipeline.proxy import ProxyInputs
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
        return key_of(scene, ProxyInputs.of(cfg))

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
    # The exploratory flight fuses with COLMAP's fusion: the ray fusion's filter is not its setting.
    assert key_with("reconstruct.dense.fusion.conditioning_ratio=3") == exploration_cache_key(cfg, same_a)
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


# Builds the tomb's exploratory flight and proxy (smoke preset: 54 images of 480 x 360, deterministic
# reconstruction) in the stage cache given as argv[1]; prints its entry, whether it was a hit and
# the proxy's SHA-256.
PROXY_CHILD = r"""
import hashlib, json, sys
from hydra import compose, initialize_config_dir
from pipeline.proxy import PROXY_FILE, ProxyInputs, build_exploration_proxy
from scene.camera import Intrinsics
from scene.registry import load_scene

cache = sys.argv[1]
with initialize_config_dir(config_dir=sys.argv[2], version_base=None):
    cfg = compose("config", overrides=["experiment=smoke", "scene=tomb"])
scene = load_scene(cfg.scene, cache_dir=cache)
inputs = ProxyInputs.of({**cfg, "cache_dir": cache})
# use_bundle=False: explore here, as for a scene without a committed proxy (the cache under test)
entry, record = build_exploration_proxy(scene, Intrinsics(**cfg.camera), inputs, use_bundle=False)
digest = hashlib.sha256((entry / PROXY_FILE).read_bytes()).hexdigest()
out = {"entry": str(entry), "hit": record["cache_hit"], "proxy": digest, "n_images": record["n_images"]}
print(json.dumps(out))
"""


def test_two_sweeps_on_one_cache_finish_with_the_results_of_one_alone(tmp_path):
    import subprocess
    import sys

    conf = str(Path(__file__).resolve().parents[1] / "conf")

    def start(cache: Path) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", PROXY_CHILD, str(cache), conf], stdout=subprocess.PIPE, text=True
        )

    def result(process: subprocess.Popen) -> dict:
        out, _ = process.communicate(timeout=900)
        assert process.returncode == 0
        return json.loads(out.strip().splitlines()[-1])

    shared = tmp_path / "shared"
    first, second = start(shared), start(shared)  # at once, on one cache directory
    together = [result(first), result(second)]
    alone = result(start(tmp_path / "alone"))
    # One of the two built the entry, the other waited for it and read it whole.
    assert sorted(r["hit"] for r in together) == [False, True]
    assert together[0]["entry"] == together[1]["entry"]
    assert len(list((shared / "exploration").glob("*/COMPLETE.json"))) == 1
    # Same key, same proxy, byte for byte, as the run with the cache to itself.
    assert Path(alone["entry"]).name == Path(together[0]["entry"]).name
    assert together[0]["proxy"] == together[1]["proxy"] == alone["proxy"]
    assert alone["n_images"] == together[0]["n_images"] > 20
    # Every texture both processes generated at once is whole: the same bytes as the lone run's.
    for texture in (tmp_path / "alone" / "textures").glob("*.png"):
        assert (shared / "textures" / texture.name).read_bytes() == texture.read_bytes(), texture.name


def test_a_proxy_fingerprint_follows_its_vertices_and_faces():
    import trimesh

    from pipeline.proxy import mesh_fingerprint

    box = trimesh.creation.box()
    same = trimesh.Trimesh(box.vertices.copy(), box.faces.copy(), process=False)
    assert mesh_fingerprint(box) == mesh_fingerprint(same) and len(mesh_fingerprint(box)) == 16
    moved = same.copy()
    moved.vertices[0, 2] += 1e-9  # one coordinate one nanometre off: another proxy
    assert mesh_fingerprint(moved) != mesh_fingerprint(box)
    flipped = trimesh.Trimesh(box.vertices.copy(), box.faces[:, ::-1].copy(), process=False)
    assert mesh_fingerprint(flipped) != mesh_fingerprint(box)
