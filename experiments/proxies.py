"""The study's committed exploration proxies (``pipeline.proxy_bundle``): build, export, list, check.

    uavplan-study proxies build tomb/0 church/0 [--experiment default] [--commit] [--force]
    uavplan-study proxies list                  # every bundle: scene, seed, key, size, files intact

``build`` explores a scene at a seed here (the exploratory flight rendered, SfM, dense, Poisson:
about 6 minutes at the default preset on 2 cores), exports the proxy the planners plan on into
``proxies/<experiment>/<scene>/seed<k>/`` and, with ``--commit``, commits that folder alone. A
scene and seed that has its bundle already is left alone unless ``--force``. The study's queue
(``uavplan-study study-plan --run``) builds the bundles its cells need first.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir

from experiments.record import commit_record
from pipeline.protocol import STUDY_SCENES
from pipeline.proxy import (
    ProxyInputs,
    build_exploration_proxy,
    exploration_cache_key,
    load_proxy,
    mesh_fingerprint,
)
from pipeline.proxy_bundle import BUNDLES, MANIFEST, BundleError, bundle_dir, check_bundle, export_bundle
from pipeline.settings import cell_settings
from scene.proxy_mesh import PROXY_CLOUD_KEY
from scene.registry import load_scene

ROOT = Path(__file__).resolve().parents[1]


def compose_cell(scene: str, seed: int, experiment: str = "default", overrides: Sequence[str] = ()):
    """The composed run config of ``scene`` at ``seed`` with the study's scene overrides."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        return compose(
            "config",
            overrides=[
                f"scene={scene}",
                f"seed={int(seed)}",
                f"experiment={experiment}",
                *STUDY_SCENES.get(scene, ()),
                *overrides,
            ],
        )


def build_bundle(
    scene: str, seed: int, experiment: str = "default", overrides: Sequence[str] = (), root: Path = BUNDLES
) -> tuple[Path, dict]:
    """Explore ``scene`` at ``seed`` here (or reuse this machine's cache entry) and export its bundle.

    Returns:
        (the bundle folder, its manifest)."""
    cfg = compose_cell(scene, seed, experiment, overrides)
    settings = cell_settings(cfg)
    loaded = load_scene(cfg.scene, cache_dir=cfg.cache_dir)
    inputs = ProxyInputs.of(cfg)
    entry, record = build_exploration_proxy(loaded, settings.intrinsics, inputs, use_bundle=False)
    proxy = load_proxy(entry)
    dest = bundle_dir(experiment, scene, seed, root)
    manifest = export_bundle(
        entry,
        dest,
        exploration_cache_key(loaded, inputs, for_bundle=True),
        proxy.metadata[PROXY_CLOUD_KEY],
        mesh_fingerprint(proxy),
        loaded.fingerprint,
        {k: v for k, v in record.items() if k not in ("entry",)},
    )
    return dest, manifest


def bundles(root: Path = BUNDLES) -> list[Path]:
    return sorted(p.parent for p in Path(root).rglob(MANIFEST)) if Path(root).is_dir() else []


def list_lines(root: Path = BUNDLES) -> list[str]:
    """One line per bundle: where, key, protocol, views, size, and whether its files are intact."""
    lines = []
    for bundle in bundles(root):
        try:
            manifest = check_bundle(bundle)
            state = "intact"
        except BundleError as exc:
            manifest, state = json.loads((bundle / MANIFEST).read_text()), f"DAMAGED: {exc}"
        lines.append(
            f"{bundle.relative_to(root).as_posix()}: key {manifest['key']}, protocol {manifest['protocol']}, "
            f"{manifest['n_views']} views, {manifest['bytes'] / 1e6:.2f} MB, proxy "
            f"{manifest['mesh_fingerprint']}, {state}"
        )
    return lines


def parse_scene_seed(text: str) -> tuple[str, int]:
    scene, _, seed = text.partition("/")
    if not scene or not seed.isdigit():
        raise ValueError(f"a proxy is scene/seed (e.g. tomb/0), got {text!r}")
    return scene, int(seed)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="uavplan-study proxies", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True)
    build = sub.add_parser("build", help="explore here and export (and commit) bundles")
    build.add_argument("proxies", nargs="+", metavar="SCENE/SEED")
    build.add_argument("--experiment", default="default", help="the preset (conf/experiment/)")
    build.add_argument("--set", action="append", default=[], help="a run.py override")
    build.add_argument("--commit", action="store_true", help="commit each bundle as it is exported")
    build.add_argument("--force", action="store_true", help="export again where a bundle exists")
    sub.add_parser("list", help="the committed bundles, each checked against its manifest")
    args = parser.parse_args(argv)
    if args.action == "list":
        lines = list_lines()
        print("\n".join(lines) if lines else f"no bundle under {BUNDLES}")
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    try:
        wanted = [parse_scene_seed(t) for t in args.proxies]
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for scene, seed in wanted:
        dest = bundle_dir(args.experiment, scene, seed)
        if (dest / MANIFEST).is_file() and not args.force:
            print(f"{scene}/{seed}: bundle {os.path.relpath(dest, ROOT)} exists (--force exports it again)")
            continue
        dest, manifest = build_bundle(scene, seed, args.experiment, args.set)
        line = (
            f"Proxy bundle: {args.experiment} {scene} seed {seed} (protocol {manifest['protocol']}): "
            f"{manifest['record'].get('n_faces')} faces, {manifest['n_views']} views, "
            f"{manifest['bytes'] / 1e6:.2f} MB, proxy {manifest['mesh_fingerprint']}"
        )
        print(line, flush=True)
        if args.commit:
            commit_record(dest, line)  # the folder alone, as a cell's record
    return 0


if __name__ == "__main__":
    sys.exit(main())
