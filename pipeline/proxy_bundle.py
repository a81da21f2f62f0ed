"""Committed exploration proxies: a study cell's plan does not depend on the machine that explored.

An exploration proxy (``pipeline.proxy``) is rebuilt on each machine from a rendered flight, and a
rebuild on another processor differs in a few faces (its fusion is not bit-reproducible across
machines); the plans on it differ with them. So the study's proxies are built once, exported as a
*bundle* and committed under ``proxies/<experiment>/<scene>/seed<k>/``:

    manifest.json      the exploration's cache key, the protocol, the scene's fingerprint, the
                       proxy's mesh fingerprint, each file's SHA-256 and the exploration's record
    proxy.ply          the proxy mesh (binary PLY)
    cloud.npz          the exploratory flight's oriented cloud as the planners read it
                       (``scene.proxy_mesh.PROXY_CLOUD_KEY``: 10 cm voxels inside the proxy's box)
    sparse/            the exploration's registered views (COLMAP model: cameras and poses, no
                       keypoints), for ``ours_plus``' photo-consistency evidence
    plan/              the exploratory flight (``viewpoints.csv``, ``plan.json``)

A cell whose exploration key matches a bundle installs it into the stage cache instead of exploring
(``install_bundle``): the files are checked against the manifest's SHA-256, and the exploration's
images are rendered again from ``plan/`` (the renderer is part of the protocol) for the photo
evidence. ``uavplan-study proxies`` builds, exports and lists bundles.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pycolmap
import trimesh

from pipeline.protocol import PROTOCOL
from scene.io import write_json_atomic
from scene.plan import read_viewpoints

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
# UAVPLAN_PROXIES: the study's queue runs cells from a worktree and points them at the checkout's.
BUNDLES = Path(os.environ.get("UAVPLAN_PROXIES") or ROOT / "proxies")
MANIFEST = "manifest.json"
PROXY_FILE = "proxy.ply"
CLOUD_FILE = "cloud.npz"
SPARSE_DIR = "sparse"
PLAN_DIR = "plan"


class BundleError(RuntimeError):
    """A committed proxy bundle is missing a file or does not match its manifest."""


def bundle_dir(experiment: str, scene: str, seed: int, root: Path = BUNDLES) -> Path:
    """Where the bundle of one scene and seed lives."""
    return Path(root) / experiment / scene / f"seed{int(seed)}"


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _bundle_files(bundle: Path) -> list[Path]:
    return sorted(p for p in Path(bundle).rglob("*") if p.is_file() and p.name != MANIFEST)


def write_views_model(src_sparse: Path, dest_sparse: Path) -> int:
    """Copy a COLMAP model's cameras and registered poses, without keypoints or 3-D points (a few
    kB instead of tens of MB). Returns the number of views written."""
    rec = pycolmap.Reconstruction(Path(src_sparse))
    out = pycolmap.Reconstruction()
    for camera_id in sorted(rec.cameras):
        out.add_camera_with_trivial_rig(rec.cameras[camera_id])
    image_ids = sorted(rec.reg_image_ids())
    for image_id in image_ids:
        image = rec.image(image_id)
        bare = pycolmap.Image(
            name=image.name, keypoints=np.zeros((0, 2)), camera_id=image.camera_id, image_id=image_id
        )
        out.add_image_with_trivial_frame(bare, image.cam_from_world())
    dest_sparse.mkdir(parents=True, exist_ok=True)
    out.write_binary(str(dest_sparse))
    return len(image_ids)


def export_bundle(
    entry: Path,
    dest: Path,
    key: str,
    cloud: Mapping[str, np.ndarray],
    mesh_fingerprint: str,
    scene_fingerprint: str,
    record: Mapping,
) -> dict:
    """Write the bundle of exploration cache entry ``entry`` into ``dest`` (replaced whole).

    Args:
        cloud: the oriented cloud the planners read (``pipeline.proxy.load_proxy``'s).
        record: the exploration's record (its ``COMPLETE.json``), kept in the manifest.

    Returns:
        the manifest.
    """
    dest = Path(dest)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shutil.copyfile(entry / PROXY_FILE, tmp / PROXY_FILE)
    np.savez_compressed(
        tmp / CLOUD_FILE,
        # float32: 0.01 mm at 100 m, half the bytes; every machine reads the same values back
        points=np.asarray(cloud["points"], dtype=np.float32),
        normals=np.asarray(cloud["normals"], dtype=np.float32),
    )
    n_views = write_views_model(entry / "recon" / "sparse", tmp / SPARSE_DIR)
    (tmp / PLAN_DIR).mkdir()
    for name in ("viewpoints.csv", "plan.json"):
        shutil.copyfile(entry / "plan" / name, tmp / PLAN_DIR / name)
    files = {p.relative_to(tmp).as_posix(): sha256(p) for p in _bundle_files(tmp)}
    manifest = {
        "key": key,
        "protocol": PROTOCOL,
        "scene_fingerprint": scene_fingerprint,
        "mesh_fingerprint": mesh_fingerprint,
        "n_views": n_views,
        "files": files,
        "bytes": sum((tmp / f).stat().st_size for f in files),
        "record": {k: v for k, v in record.items() if isinstance(v, int | float | str | bool) or v is None},
    }
    write_json_atomic(tmp / MANIFEST, manifest)
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return manifest


def read_manifest(bundle: Path) -> dict:
    return json.loads((Path(bundle) / MANIFEST).read_text())


def find_bundle(key: str, root: Path = BUNDLES) -> Path | None:
    """The committed bundle of exploration key ``key`` at the current protocol, or None."""
    if not Path(root).is_dir():
        return None
    for path in sorted(Path(root).rglob(MANIFEST)):
        if path.parent.name.endswith(".tmp"):  # an export that did not finish
            continue
        manifest = json.loads(path.read_text())
        if manifest.get("key") == key and manifest.get("protocol") == PROTOCOL:
            return path.parent
    return None


def check_bundle(bundle: Path) -> dict:
    """The manifest of ``bundle`` after checking every file's SHA-256 against it.

    Raises:
        BundleError: a file is missing, extra or altered."""
    manifest = read_manifest(bundle)
    found = {p.relative_to(bundle).as_posix() for p in _bundle_files(bundle)}
    expected = set(manifest["files"])
    if found != expected:
        odd = sorted(found ^ expected)
        raise BundleError(f"{bundle}: files {odd} differ from its manifest (restore it with git checkout)")
    for name, digest in manifest["files"].items():
        if sha256(bundle / name) != digest:
            raise BundleError(
                f"{bundle / name}: SHA-256 differs from its manifest (restore it with git checkout)"
            )
    return manifest


def install_bundle(bundle: Path, entry: Path, render_images) -> dict:
    """Lay ``bundle`` out as an exploration cache entry in ``entry``: ``proxy.ply``, ``cloud.npz``,
    ``recon/sparse`` and ``plan/``, then ``render_images(viewpoints, kinds, entry / "images")``
    renders the exploration's images again. Returns the exploration's record (the manifest's),
    with ``bundle`` (its path relative to the repository) and ``bundle_bytes``."""
    manifest = check_bundle(bundle)
    shutil.copyfile(bundle / PROXY_FILE, entry / PROXY_FILE)
    shutil.copyfile(bundle / CLOUD_FILE, entry / CLOUD_FILE)
    shutil.copytree(bundle / SPARSE_DIR, entry / "recon" / "sparse")
    shutil.copytree(bundle / PLAN_DIR, entry / "plan")
    viewpoints, kinds = read_viewpoints(entry / "plan" / "viewpoints.csv")
    render_images(viewpoints, kinds, entry / "images")
    try:
        where = bundle.resolve().relative_to(BUNDLES.resolve().parent).as_posix()
    except ValueError:
        where = str(bundle)
    return {**manifest["record"], "bundle": where, "bundle_bytes": manifest["bytes"]}


def load_cloud(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {"points": data["points"].astype(np.float64), "normals": data["normals"].astype(np.float64)}


def mesh_of(bundle: Path) -> trimesh.Trimesh:
    return trimesh.load(Path(bundle) / PROXY_FILE, force="mesh", process=False)
