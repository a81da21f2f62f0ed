"""Photo-consistency evidence (planner/ours/photo_evidence.py) on a textured ground seen by six cameras."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.ndimage import map_coordinates

from planner.ours.evidence import EvidenceSettings, evidence_signals
from planner.ours.photo_evidence import PhotoSettings, PhotoViews, photo_consistency
from scene.camera import Intrinsics, cam_from_world, look_at
from scene.plan import PlanningError

INTR = Intrinsics(320, 240, 60.0)
TEXEL_M = 0.08  # texture cells, 2-3 pixels at 8 m (finer noise would alias: no pixel integration here)
SETTINGS = PhotoSettings(n_views=6, patch_size=5, max_incidence_deg=70.0, min_std=3.0, ncc_lo=0.3, ncc_hi=0.9)


def _texture(rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(20.0, 235.0, size=(300, 300))  # 24 x 24 m of 8 cm cells around the origin


def _ground_views(texture: np.ndarray) -> PhotoViews:
    """Six cameras 8 m above a textured ground (z = 0), rendered by ray casting it."""
    positions = [(-3, -2, 8), (3, -2, 8), (0, 3, 8), (-2, 1, 9), (2, 2, 7.5), (0, -3.5, 8.5)]
    f = INTR.focal_px
    K = np.array([[f, 0.0, INTR.width / 2 - 0.5], [0.0, f, INTR.height / 2 - 0.5], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.arange(INTR.width, dtype=float), np.arange(INTR.height, dtype=float))
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    rotations, translations, images = [], [], []
    for position in positions:
        rot, t = cam_from_world(look_at(position, (0.0, 0.0, 0.0)))
        centre = -rot.T @ t
        rays = pixels @ rot  # camera rays in the world frame
        depth = -centre[2] / rays[..., 2]
        ground = centre + rays * depth[..., None]
        cells = ground[..., :2] / TEXEL_M + 150.0 - 0.5
        image = map_coordinates(texture, [cells[..., 0], cells[..., 1]], order=1, mode="nearest")
        rotations.append(rot)
        translations.append(t)
        images.append(np.clip(np.round(image), 0, 255).astype(np.uint8))
    return PhotoViews(
        np.stack([K] * len(positions)), np.stack(rotations), np.stack(translations), np.stack(images)
    )


def _plane(z: float) -> trimesh.Trimesh:
    return trimesh.Trimesh(
        [[-6, -6, z], [6, -6, z], [6, 6, z], [-6, 6, z]], [[0, 1, 2], [0, 2, 3]], process=False
    )


def test_a_proxy_on_the_surface_is_photo_consistent_one_off_it_is_not():
    views = _ground_views(_texture(np.random.default_rng(0)))
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.5, 1.5, size=(40, 2))
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    results = {}
    for z in (0.0, 0.05, 0.15):
        points = np.column_stack([xy, np.full(40, z)])
        results[z] = photo_consistency(points, normals, _plane(z), views, SETTINGS)
    on, near, off = results[0.0], results[0.05], results[0.15]
    # Every sample is seen by all six views and scored.
    assert (on["n_views"] == 6).all() and all(np.isfinite(r["ncc"]).all() for r in results.values())
    # On the true surface the patches agree up to resampling (median 0.996 here); 15 cm off (3-4 px
    # of parallax between these views) they do not (median 0.10); 5 cm off lies between (0.81).
    assert np.median(on["ncc"]) > 0.98 and on["ncc"].min() > 0.95
    assert 0.6 < np.median(near["ncc"]) < 0.9
    assert np.median(off["ncc"]) < 0.2
    assert (on["signal"] == 0.0).all() and (off["signal"] > 0.95).mean() > 0.85


def test_plain_and_hidden_samples_get_no_score():
    views = _ground_views(np.full((300, 300), 128.0))  # no texture: nothing to correlate
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    plain = photo_consistency(points, normals, _plane(0.0), views, SETTINGS)
    assert np.isnan(plain["ncc"]).all() and (plain["signal"] == 0.0).all()
    # A roof 1 m above hides the ground from every camera.
    roof = trimesh.util.concatenate([_plane(0.0), _plane(1.0)])
    textured = _ground_views(_texture(np.random.default_rng(0)))
    hidden = photo_consistency(points, normals, roof, textured, SETTINGS)
    assert (hidden["n_views"] == 0).all() and np.isnan(hidden["ncc"]).all()


def test_the_photo_signal_joins_the_cloud_signals_as_their_maximum():
    settings = EvidenceSettings(1.0, 0.3, 0.15, 0.6, 0.25, 0.75, 25.0, 60.0, SETTINGS)
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    cloud = np.array([[x, y, 0.0] for x in np.linspace(-1, 2, 31) for y in np.linspace(-1, 1, 21)])
    photo = {"signal": np.array([0.0, 0.8]), "ncc": np.array([0.95, 0.42])}
    with_photo = evidence_signals(
        points, normals, cloud, np.tile([0, 0, 1.0], (len(cloud), 1)), settings, photo
    )
    assert with_photo["uncertainty"] == pytest.approx([0.0, 0.8])
    assert with_photo["photo_ncc"] == pytest.approx([0.95, 0.42])


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("n_views", 1, "n_views must be >= 2"),
        ("patch_size", 4, "patch_size must be odd"),
        ("max_incidence_deg", 90.0, r"max_incidence_deg must be in \(0, 90\)"),
        ("ncc_lo", 0.95, "ncc_lo < ncc_hi"),
    ],
)
def test_bad_photo_settings_are_refused(key, value, message):
    node = {**SETTINGS.__dict__, key: value}
    with pytest.raises(PlanningError, match=message):
        PhotoSettings.from_config(node)


def test_an_exploration_entry_hands_its_views_to_the_planner(tmp_path):
    from pipeline.proxy import load_proxy
    from scene.proxy_mesh import PROXY_VIEWS_KEY

    _plane(0.0).export(tmp_path / "proxy.ply")
    assert PROXY_VIEWS_KEY not in load_proxy(tmp_path).metadata  # no registered views yet
    (tmp_path / "recon" / "sparse").mkdir(parents=True)
    (tmp_path / "images").mkdir()
    views = load_proxy(tmp_path).metadata[PROXY_VIEWS_KEY]
    assert views == {"recon_dir": tmp_path / "recon", "image_dir": tmp_path / "images"}


def test_a_proxy_carries_its_own_evidence():
    """``proxy_evidence`` reads the cloud the proxy carries: a sample 1 m from the cloud's edge is a
    gap (signal 1), one inside it is sure (0); no views with it, no photo signal; no cloud, None."""
    from planner.ours.evidence import proxy_evidence
    from scene.proxy_mesh import PROXY_CLOUD_KEY

    settings = EvidenceSettings(1.0, 0.3, 0.15, 0.6, 0.25, 0.75, 25.0, 60.0, SETTINGS)
    proxy = _plane(0.0)
    points = np.array([[-1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    assert proxy_evidence(proxy, points, normals, settings) is None
    cloud = np.array([[x, y, 0.0] for x in np.linspace(-3, 2, 51) for y in np.linspace(-2, 2, 41)])
    proxy.metadata[PROXY_CLOUD_KEY] = {"points": cloud, "normals": np.tile([0, 0, 1.0], (len(cloud), 1))}
    signals = proxy_evidence(proxy, points, normals, settings)
    assert "photo" not in signals
    assert signals["gap_m"] == pytest.approx([0.0, 1.0], abs=1e-9)
    assert signals["gap"] == pytest.approx([0.0, 1.0])
    assert signals["uncertainty"] == pytest.approx([0.0, 1.0])
