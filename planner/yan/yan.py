"""Yan et al. 2021 ("Sampling-based path planning for high-quality aerial 3D reconstruction of urban
scenes", Remote Sensing 13(5):989) baseline. No public code: built from the paper's description and
``reference/baselines.md``; every value the paper leaves open is a documented parameter.

1. Surface samples of the proxy (4000, as the seed paper gave it) and a per-sample quality: a
   Poisson-gradient confidence (``poisson_gradient``: how strongly the exploratory flight's oriented
   points support the surface there, read from ``proxy.metadata["exploration_cloud"]``; 1 for a
   proxy without a cloud) times the smoothness of the normals around it, sum_j exp(-|s_i - s_j| / R)
   exp(-(1 - n_i.n_j)^2 / (1 - cos theta_t)^2) / sum_j exp(-|s_i - s_j| / R), min-max normalised.
2. No-fly space: closer than d_min to the proxy (or under it: the sky straight above is blocked).
   View-sampling space: voxels whose distance to the proxy lies in [d_min, d_max]. The paper gives no
   numbers; reimplementations used 25 / 35 m around d_opt = 30 m, scaled here to the target GSD
   distance (d_min = 25/30 d_opt, d_max = 35/30 d_opt).
3. Candidates: uniform samples in the view-sampling space, each aimed at its closest proxy point
   (pitch clipped to the gimbal range).
4. Score of a candidate for a sample: c = visible * c_d * c_o, c_d = 1 - (d - d_opt)^2 / (d_opt -
   d_min)^2 (expected accuracy: distance), c_o = exp(-(1 - n.v)^2 / (1 - cos theta_t)^2) (expected
   completeness: obliqueness); a sample above the camera is invisible (the camera does not look up).
5. Selection, greedy in two stages: local, every low-quality sample (quality < threshold, lowest
   first) gets its best not-yet-chosen candidate, re-aimed at it; global, candidates are added by
   the largest score over the samples still observed fewer than ``min_observations`` times, skipping
   candidates adjacent to chosen ones, until no candidate adds anything.
6. Key-image selection on the flight order: a view whose observed samples overlap the previous key
   view's by more than ``key_max_overlap``, or that observes fewer than ``key_min_samples``
   samples, is dropped -- unless a sample it observes would fall below min(min_observations, its
   count before the step). The paper selects key images of the exploratory flight; a planner
   gets no images, so the rule runs on the planned views' observed samples.
7. Flight order: travelling-salesman path (``planner.trajectory``; the paper used ant-colony
   optimisation on a distance/direction cost, we use the shared LKH path on distance).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numpy as np
import scipy.sparse as sparse
import trimesh
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree
from tqdm import tqdm

from planner.base import merge_params
from planner.sampling import sample_surface, validate_proxy
from planner.trajectory import order_viewpoints
from planner.visibility import VisibilityLimits, VisibilityModel
from scene.camera import Intrinsics, aim_at
from scene.plan import Plan, PlanningError
from scene.proxy_mesh import PROXY_CLOUD_KEY

DEFAULTS = {
    "n_samples": 4000,
    "target_gsd_m": 0.03,
    "target_distance_m": None,
    "d_min_ratio": 25.0 / 30.0,
    "d_max_ratio": 35.0 / 30.0,
    "theta_t_deg": 60.0,
    "max_incidence_deg": 85.0,
    "voxel_size_m": 1.0,
    "n_candidates": 20000,
    "min_altitude_m": 2.0,
    "pitch_min_deg": -90.0,
    "pitch_max_deg": 30.0,
    "quality_radius_m": 2.0,
    "quality_threshold": 0.5,
    "confidence": "poisson_gradient",
    "confidence_radius_m": 0.5,
    "confidence_percentile": 50.0,
    "min_score": 0.1,
    "min_observations": 2,
    "adjacency_m": 1.0,
    "key_max_overlap": 0.95,
    "key_min_samples": 5,
    "min_coverage": 0.95,
    "takeoff_xyz": None,
    "tsp_runs": 1,
    "tsp_cluster_size": 300,
    "batch_size": 2000,
    "progress": True,
}


CONFIDENCES = ("poisson_gradient", "none")


def _merged(params: Mapping | None) -> dict:
    merged = merge_params("yan", DEFAULTS, params)
    if not 0.0 < float(merged["d_min_ratio"]) < 1.0 < float(merged["d_max_ratio"]):
        raise ValueError(
            "yan: need 0 < d_min_ratio < 1 < d_max_ratio, got "
            f"{merged['d_min_ratio']}, {merged['d_max_ratio']}"
        )
    if merged["target_distance_m"] is None:
        if not float(merged["target_gsd_m"]) > 0.0:
            raise ValueError(f"yan: target_gsd_m must be > 0, got {merged['target_gsd_m']}")
    elif not float(merged["target_distance_m"]) > 0.0:
        raise ValueError(f"yan: target_distance_m must be > 0, got {merged['target_distance_m']}")
    if not 0.0 < float(merged["theta_t_deg"]) < 90.0:
        raise ValueError(f"yan: theta_t_deg must lie in (0, 90), got {merged['theta_t_deg']}")
    for key in ("n_samples", "n_candidates", "min_observations"):
        if int(merged[key]) < 1:
            raise ValueError(f"yan: {key} must be >= 1, got {merged[key]}")
    if not float(merged["voxel_size_m"]) > 0.0:
        raise ValueError(f"yan: voxel_size_m must be > 0, got {merged['voxel_size_m']}")
    if merged["confidence"] not in CONFIDENCES:
        raise ValueError(f"yan: confidence must be one of {CONFIDENCES}, got {merged['confidence']!r}")
    if not float(merged["confidence_radius_m"]) > 0.0:
        raise ValueError(f"yan: confidence_radius_m must be > 0, got {merged['confidence_radius_m']}")
    if not 0.0 < float(merged["confidence_percentile"]) <= 100.0:
        raise ValueError(
            f"yan: confidence_percentile must lie in (0, 100], got {merged['confidence_percentile']}"
        )
    return merged


def check_params(params: Mapping | None, intrinsics: Intrinsics) -> None:
    """Refuse a bad setting before any work (the planner contract, ``planner.base``)."""
    distance_limits(_merged(params), intrinsics)


def distance_limits(params: Mapping, intrinsics: Intrinsics) -> tuple[float, float, float]:
    """(d_min, d_opt, d_max) in metres: the view-sampling band around the target distance.

    d_opt is ``target_distance_m`` when given, else the distance at which the camera images at
    ``target_gsd_m`` (m/px), the GSD every planner of a study shares.
    """
    d_opt = params["target_distance_m"]
    d_opt = intrinsics.distance_for_gsd(float(params["target_gsd_m"])) if d_opt is None else float(d_opt)
    return float(params["d_min_ratio"]) * d_opt, d_opt, float(params["d_max_ratio"]) * d_opt


def sample_quality(
    points: np.ndarray,
    normals: np.ndarray,
    radius_m: float,
    theta_t_deg: float,
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """Quality (P,) in [0, 1] of surface samples (low: edges, corners, noise, poor support).

    The confidence (P,) in [0, 1] (None: ones) times the weighted mean over neighbours within
    ``2 * radius_m`` of exp(-(1 - n_i.n_j)^2 / (1 - cos theta_t)^2), weights exp(-|s_i - s_j| /
    radius_m); min-max normalised over the samples.
    """
    n = len(points)
    confidence = np.ones(n) if confidence is None else np.asarray(confidence, dtype=float)
    tree = cKDTree(points)
    pairs = tree.query_pairs(2.0 * float(radius_m), output_type="ndarray")
    if len(pairs) == 0:
        return _min_max(confidence)
    i, j = pairs[:, 0], pairs[:, 1]
    dist = np.linalg.norm(points[i] - points[j], axis=1)
    weight = np.exp(-dist / float(radius_m))
    denom = (1.0 - math.cos(math.radians(theta_t_deg))) ** 2
    smooth = np.exp(-((1.0 - np.sum(normals[i] * normals[j], axis=1)) ** 2) / denom)
    num = np.bincount(i, weight * smooth, n) + np.bincount(j, weight * smooth, n)
    den = np.bincount(i, weight, n) + np.bincount(j, weight, n)
    smoothness = np.where(den > 0, num / np.maximum(den, 1e-12), 1.0)
    return _min_max(confidence * smoothness)


def _min_max(values: np.ndarray) -> np.ndarray:
    """``values`` scaled to [0, 1]; ones when they are all equal."""
    span = values.max() - values.min()
    return (values - values.min()) / span if span > 1e-12 else np.ones(len(values))


def poisson_gradient(
    points: np.ndarray, cloud_points: np.ndarray, cloud_normals: np.ndarray, radius_m: float
) -> np.ndarray:
    """Magnitude (P,) of the oriented cloud's normal field at ``points``: |sum_j w_j n_j|.

    Poisson surface reconstruction (Kazhdan et al. 2006) solves grad(chi) = V for the field V of
    the cloud's normals splatted with a smoothing kernel, so |V| at a surface point is the gradient
    of the indicator function there: large where many consistently oriented points support the
    surface, small where the cloud was sparse or its normals disagree. This is the confidence of
    Wu et al. 2014 ("Quality-driven Poisson-guided autoscanning"), which Yan et al. 2021 reuse.
    Kernel: Gaussian weights w_j = exp(-|p - c_j|^2 / (2 (radius_m / 2)^2)) over cloud points
    within ``radius_m`` (m). Unit: weighted points; 0 where no cloud point lies within the radius.
    """
    points = np.asarray(points, dtype=float)
    cloud_points = np.asarray(cloud_points, dtype=float)
    if len(cloud_points) == 0:
        return np.zeros(len(points))
    pairs = cKDTree(points).sparse_distance_matrix(
        cKDTree(cloud_points), float(radius_m), output_type="ndarray"
    )
    sigma = 0.5 * float(radius_m)
    weight = np.exp(-(pairs["v"] ** 2) / (2.0 * sigma * sigma))
    normals = np.asarray(cloud_normals, dtype=float)[pairs["j"]]
    field = np.stack(
        [np.bincount(pairs["i"], weight * normals[:, k], minlength=len(points)) for k in range(3)], axis=1
    )
    return np.linalg.norm(field, axis=1)


def sample_confidence(proxy: trimesh.Trimesh, points: np.ndarray, params: Mapping) -> tuple[np.ndarray, str]:
    """Confidence (P,) in [0, 1] of the samples and where it came from.

    ``poisson_gradient`` on the exploratory flight's cloud (``proxy.metadata[PROXY_CLOUD_KEY]``), divided by
    its ``confidence_percentile`` over the samples and clipped at 1 (the median by default: a sample
    supported as well as the scene's typical one is confident); ones when the setting is
    ``none`` or the proxy carries no cloud (a degraded ground truth).
    """
    cloud = proxy.metadata.get(PROXY_CLOUD_KEY) if params["confidence"] == "poisson_gradient" else None
    if cloud is None:
        source = "none" if params["confidence"] == "none" else "none (the proxy carries no cloud)"
        return np.ones(len(points)), source
    gradient = poisson_gradient(
        points, cloud["points"], cloud["normals"], float(params["confidence_radius_m"])
    )
    scale = float(np.percentile(gradient, float(params["confidence_percentile"])))
    if scale <= 0.0:
        return np.ones(len(points)), "none (no cloud point near the samples)"
    return np.clip(gradient / scale, 0.0, 1.0), "poisson_gradient"


def view_sampling_space(model: VisibilityModel, proxy: trimesh.Trimesh, params: Mapping) -> np.ndarray:
    """Centres (N, 3) of the voxels whose distance to the proxy lies in [d_min, d_max] (metres).

    Voxels below ``min_altitude_m`` and voxels whose sky is blocked by the proxy (inside or under
    the structure) belong to the no-fly space.
    """
    d_min, _, d_max = distance_limits(params, model.intrinsics)
    step = float(params["voxel_size_m"])
    lo = proxy.bounds[0] - d_max
    hi = proxy.bounds[1] + d_max
    lo[2] = max(lo[2], float(params["min_altitude_m"]))
    axes = [np.arange(lo[k] + 0.5 * step, hi[k], step) for k in range(3)]
    n_voxels = int(np.prod([len(a) for a in axes]))
    if n_voxels > 30_000_000:
        raise PlanningError(
            f"yan: voxel_size_m = {step} gives {n_voxels} voxels; choose a larger voxel_size_m"
        )
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    keep = []
    for start in range(0, len(grid), 500_000):
        chunk = grid[start : start + 500_000]
        clearance = model.clearance(chunk)
        band = (clearance >= d_min) & (clearance <= d_max)
        keep.append(chunk[band])
    inside = np.concatenate(keep) if keep else np.zeros((0, 3))
    if len(inside):
        sky = inside.copy()
        sky[:, 2] = proxy.bounds[1][2] + d_max + 1.0
        inside = inside[~model.occluded(inside, sky)]
    if len(inside) == 0:
        raise PlanningError(
            f"yan: no valid viewpoint position: the view-sampling space [d_min, d_max] = [{d_min:.2f}, "
            f"{d_max:.2f}] m above min_altitude_m = {params['min_altitude_m']} m is empty"
        )
    return inside


def view_scores(
    model: VisibilityModel, viewpoints: np.ndarray, d_min: float, d_opt: float, theta_t_deg: float, batch: int
) -> sparse.csr_matrix:
    """Sparse (V, P) scores c = visible * c_d * c_o of every viewpoint for every sample.

    ``visible`` is the shared visibility model's test (frustum, distance, incidence, occlusion) and
    additionally the sample must not lie above the camera.
    """
    denom_o = (1.0 - math.cos(math.radians(theta_t_deg))) ** 2
    rows = []
    for start in range(0, len(viewpoints), batch):
        vps = viewpoints[start : start + batch]
        obs = model.observe(vps)
        visible = obs.visible & (model.points[None, :, 2] <= vps[:, None, 2])
        c_d = 1.0 - (obs.distance - d_opt) ** 2 / (d_opt - d_min) ** 2
        c_o = np.exp(-((1.0 - obs.cos_incidence) ** 2) / denom_o)
        rows.append(
            sparse.csr_matrix(np.where(visible, np.clip(c_d, 0.0, 1.0) * c_o, 0.0).astype(np.float32))
        )
    return sparse.vstack(rows, format="csr")


def position_scores(
    model: VisibilityModel,
    positions: np.ndarray,
    samples: np.ndarray,
    d_min: float,
    d_opt: float,
    d_max: float,
    theta_t_deg: float,
    max_incidence_deg: float,
) -> sparse.csr_matrix:
    """Sparse (N, S) scores of positions for samples when the camera is aimed at the sample.

    Aimed at the sample, the frustum test always passes; distance band, incidence, the
    no-looking-up rule and occlusion remain.
    """
    pts = model.points[samples]
    nrm = model.normals[samples]
    to_cam = positions[:, None, :] - pts[None]
    dist = np.linalg.norm(to_cam, axis=-1)
    cos = np.einsum("npk,pk->np", to_cam, nrm) / np.maximum(dist, 1e-9)
    ok = (dist >= d_min) & (dist <= d_max) & (cos >= math.cos(math.radians(max_incidence_deg)))
    ok &= pts[None, :, 2] <= positions[:, None, 2]
    ni, si = np.nonzero(ok)
    if len(ni):
        origins = pts[si] + model.ray_offset_m * nrm[si]
        free = ~model.occluded(origins, positions[ni])
        ni, si = ni[free], si[free]
    denom_o = (1.0 - math.cos(math.radians(theta_t_deg))) ** 2
    c_d = np.clip(1.0 - (dist[ni, si] - d_opt) ** 2 / (d_opt - d_min) ** 2, 0.0, 1.0)
    c_o = np.exp(-((1.0 - cos[ni, si]) ** 2) / denom_o)
    return sparse.csr_matrix((c_d * c_o, (ni, si)), shape=(len(positions), len(samples)))


def select_global(
    scores: sparse.csr_matrix,
    counts: np.ndarray,
    candidate_positions: np.ndarray,
    taken: np.ndarray,
    params: Mapping,
) -> list[int]:
    """Greedy global selection: add the candidate with the largest score over under-observed samples.

    Args:
        scores: (C, P) candidate scores.
        counts: (P,) observations so far (updated in place).
        candidate_positions: (C, 3) for the adjacency rule.
        taken: (C,) bool, candidates already chosen or blocked (updated in place).
        params: ``min_score``, ``min_observations``, ``adjacency_m``.

    Returns:
        indices of the chosen candidates, in order.
    """
    need = int(params["min_observations"])
    observes = scores >= float(params["min_score"])
    observed = scores.multiply(observes).tocsr()
    observed_t = observed.T.tocsr()
    observes_t = observes.T.tocsr().astype(np.int64)
    tree = cKDTree(candidate_positions)
    short = counts < need
    gains = observed @ short.astype(np.float32)
    # How many under-observed samples each candidate observes, counted exactly: the float gains
    # keep rounding residues after their samples are done, and a candidate whose only gain is such a
    # residue observes nothing the plan still needs (the stage once added hundreds of those).
    useful = observes.astype(np.int64) @ short.astype(np.int64)
    chosen: list[int] = []
    while True:
        eligible = (useful > 0) & ~taken
        if not eligible.any():
            break
        best = int(np.argmax(np.where(eligible, gains, -np.inf)))
        chosen.append(best)
        taken[best] = True
        row = observed.getrow(best)
        counts[row.indices] += 1
        newly_done = row.indices[counts[row.indices] == need]
        if len(newly_done):
            # Those samples no longer count: remove their scores from every candidate's gain.
            gains -= np.asarray(observed_t[newly_done].sum(axis=0)).ravel()
            useful -= np.asarray(observes_t[newly_done].sum(axis=0)).ravel()
        blocked = tree.query_ball_point(candidate_positions[best], float(params["adjacency_m"]))
        taken[blocked] = True
    return chosen


def key_images(order_vis: sparse.csr_matrix, max_overlap: float, min_samples: int, need: int) -> np.ndarray:
    """Mask (V,) of the key views along a flight order.

    A view is dropped when it observes fewer than ``min_samples`` samples or when the share of its
    samples also observed by the previous key view exceeds ``max_overlap`` -- but only if every
    sample it observes stays observed min(need, its initial count) times (coverage is kept).
    """
    vis = order_vis.tocsr()
    counts = np.asarray(vis.sum(axis=0)).ravel()
    floor = np.minimum(counts, need)
    keep = np.ones(vis.shape[0], bool)
    last = None
    for v in range(vis.shape[0]):
        cols = vis.indices[vis.indptr[v] : vis.indptr[v + 1]]
        redundant = len(cols) < min_samples
        if not redundant and last is not None:
            redundant = np.isin(cols, last, assume_unique=True).mean() > max_overlap
        if redundant and np.all(counts[cols] - 1 >= floor[cols]):
            keep[v] = False
            counts[cols] -= 1
            continue
        last = cols
    return keep


def order_in_clusters(
    positions: np.ndarray, start, runs: int, cluster_size: int, rng: np.random.Generator
) -> np.ndarray:
    """Flight order (V,) of many viewpoints: a TSP path over spatial clusters, then within each.

    LKH on thousands of nodes takes many minutes on two cores; like the reimplementations of
    Yan et al. (TSP over subspaces, then inside each), the positions are split by k-means into
    clusters of about ``cluster_size``, the cluster centres ordered by the shared TSP path and
    each cluster's views ordered by it from the end of the previous cluster.
    """
    n = len(positions)
    if n <= cluster_size:
        return order_viewpoints(positions, start=start, runs=runs)
    k = int(math.ceil(n / cluster_size))
    centres, labels = kmeans2(positions, k, seed=rng, minit="++")
    used = np.unique(labels)
    cluster_order = used[order_viewpoints(centres[used], start=start, runs=runs)]
    order: list[np.ndarray] = []
    here = start
    for c in cluster_order:
        members = np.flatnonzero(labels == c)
        local = members[order_viewpoints(positions[members], start=here, runs=runs)]
        order.append(local)
        here = positions[local[-1]]
    return np.concatenate(order)


def _local_views(model, positions, points, quality, p: Mapping, distances, pitch_lim):
    """Yan's local views: for each low-quality sample (worst first) the best free candidate position
    aimed at it. Returns the views (n, 5), which candidates they took, the samples' observation
    counts so far and the local views' own counts (both (P,)), and the low-quality samples."""
    d_min, d_opt, d_max = distances
    n_cand = len(positions)
    taken = np.zeros(n_cand, bool)
    counts = np.zeros(len(points), np.int64)
    local_vps: list[np.ndarray] = []
    low = np.flatnonzero(quality < float(p["quality_threshold"]))
    low = low[np.argsort(quality[low], kind="stable")]
    if len(low):
        aimed = position_scores(
            model, positions, low, d_min, d_opt, d_max, float(p["theta_t_deg"]), float(p["max_incidence_deg"])
        ).tocsc()
        for k in tqdm(range(len(low)), desc="yan local", disable=not p["progress"]):
            col = aimed.getcol(k)
            cand, val = col.indices, col.data
            free = ~taken[cand]
            if not free.any():
                continue
            best = cand[free][np.argmax(val[free])]
            taken[best] = True
            local_vps.append(aim_at(positions[best][None], points[low[k]][None], *pitch_lim)[0])
    local_vps = np.array(local_vps).reshape(-1, 5)
    counts_local = np.zeros(len(points), np.int64)
    if len(local_vps):
        local_scores = view_scores(
            model, local_vps, d_min, d_opt, float(p["theta_t_deg"]), int(p["batch_size"])
        )
        counts_local = (
            np.asarray((local_scores >= float(p["min_score"])).sum(axis=0)).ravel().astype(np.int64)
        )
        counts += counts_local
    return local_vps, taken, counts, counts_local, low


def plan(proxy: trimesh.Trimesh, intrinsics: Intrinsics, params: Mapping, seed: int) -> Plan:
    """Plan Yan et al.'s flight on a proxy mesh.

    Args:
        proxy: proxy triangle mesh in world metres (Z up, ground at z = 0).
        intrinsics: the camera.
        params: see ``DEFAULTS`` and ``conf/planner/yan.yaml`` (metres, degrees).
        seed: seeds the surface samples and the candidate sampling.

    Returns:
        The plan (kinds ``local`` and ``global``) in TSP order.
    """
    p = _merged(params)
    validate_proxy(proxy)
    rng = np.random.default_rng(seed)
    timings: dict[str, float] = {}
    d_min, d_opt, d_max = distance_limits(p, intrinsics)
    pitch_lim = (float(p["pitch_min_deg"]), float(p["pitch_max_deg"]))

    t0 = time.perf_counter()
    points, normals = sample_surface(proxy, int(p["n_samples"]), seed)
    limits = VisibilityLimits(d_min, d_max, float(p["max_incidence_deg"]))
    model = VisibilityModel(proxy, points, normals, intrinsics, limits)
    confidence, confidence_source = sample_confidence(proxy, points, p)
    quality = sample_quality(
        points, normals, float(p["quality_radius_m"]), float(p["theta_t_deg"]), confidence
    )
    timings["samples"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    space = view_sampling_space(model, proxy, p)
    n_cand = min(int(p["n_candidates"]), len(space))
    pick = rng.choice(len(space), size=n_cand, replace=False)
    jitter = (rng.random((n_cand, 3)) - 0.5) * float(p["voxel_size_m"])
    positions = space[pick] + jitter
    positions[:, 2] = np.maximum(positions[:, 2], float(p["min_altitude_m"]))
    candidates = aim_at(positions, model.closest_points(positions), *pitch_lim)
    timings["candidates"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    local_vps, taken, counts, counts_local, low = _local_views(
        model, positions, points, quality, p, (d_min, d_opt, d_max), pitch_lim
    )
    timings["local"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    scores = view_scores(model, candidates, d_min, d_opt, float(p["theta_t_deg"]), int(p["batch_size"]))
    chosen = select_global(scores, counts, positions, taken, p)
    timings["global"] = time.perf_counter() - t0

    selected = np.concatenate([local_vps, candidates[chosen]])
    kinds = ["local"] * len(local_vps) + ["global"] * len(chosen)
    if len(selected) == 0:
        raise PlanningError("yan: no candidate observes any surface sample; check target_distance_m")
    t0 = time.perf_counter()
    start = None if p["takeoff_xyz"] is None else np.asarray(p["takeoff_xyz"], dtype=float)
    order = order_in_clusters(selected[:, :3], start, int(p["tsp_runs"]), int(p["tsp_cluster_size"]), rng)
    timings["tsp"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ordered = selected[order]
    ordered_vis = view_scores(model, ordered, d_min, d_opt, float(p["theta_t_deg"]), int(p["batch_size"]))
    ordered_vis = (ordered_vis >= float(p["min_score"])).astype(np.float32).tocsr()
    need = int(p["min_observations"])
    keep = key_images(ordered_vis, float(p["key_max_overlap"]), int(p["key_min_samples"]), need)
    timings["key_images"] = time.perf_counter() - t0
    timings["total"] = sum(timings.values())
    final_counts = np.asarray(ordered_vis[keep].sum(axis=0)).ravel()
    # Samples the candidate set can observe ``need`` times: the greedy selection must cover them.
    coverable = np.asarray((scores >= float(p["min_score"])).sum(axis=0)).ravel() + counts_local >= need
    covered = float(np.mean(final_counts[coverable] >= need)) if coverable.any() else 0.0
    if covered < float(p["min_coverage"]):
        raise PlanningError(
            f"yan: the selection covers {covered:.3f} of the coverable samples {need} times, below "
            f"min_coverage = {p['min_coverage']}"
        )
    info = {
        "parameters": {k: v for k, v in p.items() if k != "progress"},
        "timings_s": timings,
        "d_min_m": d_min,
        "d_opt_m": d_opt,
        "d_max_m": d_max,
        "n_samples": int(len(points)),
        "n_low_quality": int(len(low)),
        "confidence_source": confidence_source,
        "n_view_space_voxels": int(len(space)),
        "n_candidates": int(n_cand),
        "n_local": int(len(local_vps)),
        "n_global": int(len(chosen)),
        "n_before_key_images": int(len(selected)),
        "n_key_images": int(keep.sum()),
        "fraction_coverable": float(np.mean(coverable)),
        "fraction_coverable_covered": covered,
        "fraction_observed_min": float(np.mean(final_counts >= int(p["min_observations"]))),
        "fraction_observed_once": float(np.mean(final_counts >= 1)),
        "rays_cast": model.rays_cast,
    }
    return Plan(viewpoints=ordered[keep], kinds=[kinds[i] for i in order[keep]], planner="yan", info=info)
