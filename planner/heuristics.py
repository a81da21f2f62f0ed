"""The paper's reconstruction heuristics (Eq. 1-9), dense reference form over whole matrices.

Notation: V viewpoints, P sampled surface points, ``visible`` the (V, P) matrix A,
``direction`` (V, P, 3) the unit vectors u_v from each point to each camera centre,
``cos_incidence`` (V, P) the dot product n . u_v, ``distance`` (V, P) in metres.

Point level, ``point_score: literal`` (Eq. 1-5 as printed):
                        R_point = S_front * S_distance * S_parallax * S_count
  S_front     = max over visible views of max(0, n . u_v)                                  (Eq. 2)
  S_distance  = max over visible views of the per-observation distance score: 1 inside the
                target range [d_lo, d_hi], linear down to 0 at d_lo - d_margin and d_hi + d_margin
                (the paper: "maximum score within the target range ... linearly penalised until
                they exceed a tolerated margin"; it does not say how views combine: the best
                observation is used, as for frontality)
  S_parallax  = w1(sigma_alpha) * w3(sigma_alpha) with Smith et al.'s logistic constants   (Eq. 3)
  sigma_alpha = sqrt(sum_v arccos(u_v . u_bar)^2 / (|V_p| + eps)), u_bar the normalised sum  (Eq. 4)
  S_count     = min(1, |V_p| / k_count)                                                    (Eq. 5)
Point level, ``point_score: per_view`` (the default; the paper leaves the aggregation open):
  q_vp        = F(theta_vp) * D(d_vp): each observation's frontality and distance score together, F = 1
                up to ``frontal_full_deg`` off the normal, linear in cos theta to 0 at ``frontal_cone_deg``
  S_quality   = (1 / k_count) * sum of the k_count largest q_vp over the views (missing ones count 0)
  S_parallax  = w1 w3 of sigma_alpha over the good views (q_vp > 0) only
  R_point     = S_quality * S_parallax
  Dense matching needs several views that are each close and frontal: in the literal form one close
  frontal view plus two far or grazing ones give the full score (each factor takes its own best view
  and every view in the 80 deg, 1.7 d_t reach counts); here they give 1/3 of it.
Viewpoint-set level (Eq. 6-9): R_viewpoint = (S_visibility + S_overlap + S_conn) / 3
  S_visibility = sum(A) / (|V| |P|)                                                        (Eq. 7)
  r_ij = |common visible points| / min(n_i, n_j);  f = clip((r - r_min) / (r_max - r_min), 0, 1)
  S_overlap    = mean_i (1/k) sum of the top-k f(r_ij), j != i (fewer than k others: missing = 0)
  S_conn       = |largest connected component| / |V|, edges where f(r_ij) > tau_edge         (Eq. 9)
  With ``matchable_overlap`` (default) f is multiplied by the pair's matchability g_ij: SIFT links
  two views of the same points only when they see them from similar directions and scales. From
  the point m_ij halfway between the centroids of the two views' visible points, g_ij = 1 when the
  camera centres are at most ``match_angle_full_deg`` apart and their distances differ at most
  ``match_scale_full`` x, falling linearly to 0 at ``match_angle_zero_deg`` and ``match_scale_zero``.
  Eq. 8 as printed (g = 1) rates a near-horizontal wall view and a nadir view that share a roof
  edge as well linked; SfM does not register such views.
Global: R = sum_p R_point + |P| R_viewpoint                                               (Eq. 10)

The model-coverage pass scores points with ``coverage_point_scores`` instead (see there).
The incremental evaluator in ``planner.objective`` computes exactly these numbers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from scene.plan import PlanningError

# Smith et al. 2018 (see reference/baselines.md): triangulation and matchability penalties.
SMITH_K1 = 32.0
SMITH_ALPHA1 = math.pi / 16.0
SMITH_K3 = 8.0
SMITH_ALPHA3 = math.pi / 4.0


def smith_w1(alpha):
    """Triangulation term w1(alpha) = 1 / (1 + exp(-k1 (alpha - alpha1))), alpha in radians."""
    return 1.0 / (1.0 + np.exp(-SMITH_K1 * (np.asarray(alpha, dtype=float) - SMITH_ALPHA1)))


def smith_w3(alpha):
    """Matchability term w3(alpha) = 1 - 1 / (1 + exp(-k3 (alpha - alpha3))), alpha in radians."""
    return 1.0 - 1.0 / (1.0 + np.exp(-SMITH_K3 * (np.asarray(alpha, dtype=float) - SMITH_ALPHA3)))


POINT_SCORES = ("per_view", "literal")


@dataclass(frozen=True)
class HeuristicParams:
    """Constants of Eq. 1-9 (distances in metres).

    Attributes:
        k_count: views for a full observation count score (paper: 3).
        target_lo_m, target_hi_m: distance range with full distance score.
        d_margin_m: the distance score falls linearly to 0 over this margin outside the range.
        r_min, r_max: overlap-ratio ramp of the pairwise overlap score f.
        top_k: number of best pairwise overlap scores averaged per viewpoint.
        tau_edge: a pair is a graph edge when its overlap score exceeds this.
        eps: the epsilon of Eq. 4.
        coverage_closeness_weight: model-coverage point score weight of the distance term.
        point_score: ``per_view`` (default, see the module docstring) or ``literal`` (Eq. 1-5).
        frontal_full_deg: per-view frontality is 1 up to this angle off the normal ...
        frontal_cone_deg: ... and falls (linear in cos) to 0 at this angle (``per_view`` only).
        matchable_overlap: weight pair overlaps by their matchability g_ij (module docstring).
        match_angle_full_deg, match_angle_zero_deg: g's ramp over the angle between the cameras.
        match_scale_full, match_scale_zero: g's ramp over the ratio of their distances.
    """

    k_count: int = 3
    target_lo_m: float = 8.0
    target_hi_m: float = 12.0
    d_margin_m: float = 5.0
    r_min: float = 0.1
    r_max: float = 0.5
    top_k: int = 4
    tau_edge: float = 0.25
    eps: float = 1e-9
    coverage_closeness_weight: float = 0.1
    point_score: str = "per_view"
    frontal_full_deg: float = 30.0
    frontal_cone_deg: float = 60.0
    matchable_overlap: bool = True
    match_angle_full_deg: float = 30.0
    match_angle_zero_deg: float = 45.0
    match_scale_full: float = 1.5
    match_scale_zero: float = 2.0

    def __post_init__(self) -> None:
        if not 0.0 <= float(self.match_angle_full_deg) < float(self.match_angle_zero_deg) <= 180.0:
            raise PlanningError(
                "need 0 <= match_angle_full_deg < match_angle_zero_deg <= 180, got "
                f"{self.match_angle_full_deg}, {self.match_angle_zero_deg}"
            )
        if not 1.0 <= float(self.match_scale_full) < float(self.match_scale_zero):
            raise PlanningError(
                "need 1 <= match_scale_full < match_scale_zero, got "
                f"{self.match_scale_full}, {self.match_scale_zero}"
            )
        if self.point_score not in POINT_SCORES:
            raise PlanningError(f"point_score must be one of {POINT_SCORES}, got {self.point_score!r}")
        if not 0.0 <= float(self.frontal_full_deg) < float(self.frontal_cone_deg) <= 90.0:
            raise PlanningError(
                "need 0 <= frontal_full_deg < frontal_cone_deg <= 90, got "
                f"{self.frontal_full_deg}, {self.frontal_cone_deg}"
            )
        if int(self.k_count) < 1:
            raise PlanningError(f"k_count must be >= 1, got {self.k_count}")
        if not (0.0 < float(self.target_lo_m) <= float(self.target_hi_m)):
            raise PlanningError(
                f"impossible distance range: need 0 < target_lo_m <= target_hi_m, "
                f"got {self.target_lo_m}, {self.target_hi_m}"
            )
        if not float(self.d_margin_m) > 0.0:
            raise PlanningError(f"d_margin_m must be > 0, got {self.d_margin_m}")
        if not (0.0 <= float(self.r_min) < float(self.r_max) <= 1.0):
            raise PlanningError(f"need 0 <= r_min < r_max <= 1, got {self.r_min}, {self.r_max}")
        if int(self.top_k) < 1:
            raise PlanningError(f"top_k must be >= 1, got {self.top_k}")
        if not (0.0 <= float(self.tau_edge) < 1.0):
            raise PlanningError(f"tau_edge must lie in [0, 1), got {self.tau_edge}")
        if not (0.0 <= float(self.coverage_closeness_weight) <= 1.0):
            raise PlanningError(
                f"coverage_closeness_weight must lie in [0, 1], got {self.coverage_closeness_weight}"
            )

    @classmethod
    def from_mapping(cls, m: Mapping) -> HeuristicParams:
        return cls(**{k: m[k] for k in cls.__dataclass_fields__ if k in m})


def distance_score(distance, target_lo_m: float, target_hi_m: float, d_margin_m: float) -> np.ndarray:
    """Per-observation distance score: 1 in [lo, hi], linear to 0 over ``d_margin_m`` outside."""
    d = np.asarray(distance, dtype=np.float32)
    outside = np.maximum(np.maximum(target_lo_m - d, d - target_hi_m), 0.0)
    return np.clip(1.0 - outside / d_margin_m, 0.0, 1.0).astype(np.float32)


def frontality_score(cos_incidence, frontal_full_deg: float, frontal_cone_deg: float) -> np.ndarray:
    """Per-observation frontality F: 1 up to ``frontal_full_deg`` off the normal, linear in the
    cosine down to 0 at ``frontal_cone_deg`` and beyond (float32, like the geometry)."""
    lo, hi = math.cos(math.radians(frontal_cone_deg)), math.cos(math.radians(frontal_full_deg))
    c = np.asarray(cos_incidence, dtype=np.float32)
    return np.clip((c - np.float32(lo)) / np.float32(hi - lo), 0.0, 1.0).astype(np.float32)


def view_quality(visible, distance, cos_incidence, params: HeuristicParams) -> np.ndarray:
    """q_vp (V, P) = F(theta) * D(d) of every visible observation, 0 where not visible (float32)."""
    front = frontality_score(cos_incidence, params.frontal_full_deg, params.frontal_cone_deg)
    dscore = distance_score(distance, params.target_lo_m, params.target_hi_m, params.d_margin_m)
    return np.where(np.asarray(visible, bool), front * dscore, 0.0).astype(np.float32)


def top_k_mean(values: np.ndarray, k: int) -> np.ndarray:
    """Mean of the k largest values along axis 0 of (V, P), missing values counting 0 (P,)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) > k:
        v = -np.partition(-v, k - 1, axis=0)[:k]
    return v.sum(axis=0) / float(k)


def view_geometry(visible, distance, direction, points) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre and the centroid of the visible points (each (V, 3), metres) of every view,
    from its observations of the samples ``points`` (P, 3); zeros for a view that sees none."""
    vis = np.asarray(visible, bool)
    n = np.maximum(vis.sum(axis=1), 1)[:, None]
    pts = np.asarray(points, dtype=np.float64)
    look = (vis.astype(np.float64) @ pts) / n
    offset = np.asarray(direction, dtype=np.float64) * np.asarray(distance, dtype=np.float64)[..., None]
    centre = look + np.einsum("vp,vpk->vk", vis, offset) / n
    return centre, look


def pair_matchability(centre_a, look_a, centre_b, look_b, params: HeuristicParams) -> np.ndarray:
    """g_ij of views a and b (broadcasting over leading axes of the (..., 3) arrays): 1 when seen
    from their common area the cameras are close in direction and scale, 0 when they are not."""
    mid = 0.5 * (np.asarray(look_a) + np.asarray(look_b))
    ra, rb = np.asarray(centre_a) - mid, np.asarray(centre_b) - mid
    la, lb = np.linalg.norm(ra, axis=-1), np.linalg.norm(rb, axis=-1)
    cos = np.einsum("...k,...k->...", ra, rb) / np.maximum(la * lb, 1e-12)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ratio = np.maximum(la, lb) / np.maximum(np.minimum(la, lb), 1e-12)
    a_full, a_zero = float(params.match_angle_full_deg), float(params.match_angle_zero_deg)
    s_full, s_zero = float(params.match_scale_full), float(params.match_scale_zero)
    g_angle = np.clip((a_zero - angle) / (a_zero - a_full), 0.0, 1.0)
    g_scale = np.clip((s_zero - ratio) / (s_zero - s_full), 0.0, 1.0)
    return g_angle * g_scale


def angular_spread(direction: np.ndarray, visible: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """sigma_alpha (P,) in radians of the viewing directions (V, P, 3) of the visible views (Eq. 4)."""
    vis = np.asarray(visible, bool)
    u = np.asarray(direction, dtype=np.float64) * vis[..., None]
    total = u.sum(axis=0)
    norm = np.linalg.norm(total, axis=-1)
    u_bar = total / np.where(norm > 0, norm, 1.0)[:, None]
    angles = np.arccos(np.clip(np.einsum("vpk,pk->vp", u, u_bar), -1.0, 1.0))
    sq = np.where(vis, angles**2, 0.0).sum(axis=0)
    return np.sqrt(sq / (vis.sum(axis=0) + eps))


def point_scores(
    visible: np.ndarray,
    distance: np.ndarray,
    direction: np.ndarray,
    cos_incidence: np.ndarray,
    params: HeuristicParams,
) -> dict[str, np.ndarray]:
    """Point scores (each (P,)): ``front``, ``distance``, ``parallax``, ``count``, ``sigma``,
    ``R_point``; with ``point_score: per_view`` also ``quality`` (S_quality), and ``count`` and
    ``parallax`` then use the good views (q_vp > 0) only."""
    vis = np.asarray(visible, bool)
    n_pts = vis.shape[1]
    if vis.shape[0] == 0:
        zero = np.zeros(n_pts)
        return {
            "front": zero,
            "distance": zero,
            "quality": zero,
            "parallax": smith_w1(zero) * smith_w3(zero),
            "count": zero,
            "sigma": zero,
            "R_point": zero,
        }
    front = np.where(vis, np.maximum(cos_incidence, 0.0), 0.0).max(axis=0)
    dscore = distance_score(distance, params.target_lo_m, params.target_hi_m, params.d_margin_m)
    dist = np.where(vis, dscore, 0.0).max(axis=0)
    if params.point_score == "per_view":
        quality = view_quality(vis, distance, cos_incidence, params)
        counted = quality > 0  # the good views: close and frontal
        s_quality = top_k_mean(quality, int(params.k_count))
    else:
        counted = vis
    sigma = angular_spread(direction, counted, params.eps)
    parallax = smith_w1(sigma) * smith_w3(sigma)
    count = np.minimum(1.0, counted.sum(axis=0) / float(params.k_count))
    if params.point_score != "per_view":
        s_quality = front * dist * count
    return {
        "front": front.astype(float),
        "distance": dist.astype(float),
        "quality": np.asarray(s_quality, dtype=float),
        "parallax": parallax,
        "count": count,
        "sigma": sigma,
        "R_point": s_quality * parallax,
    }


def coverage_point_scores(visible: np.ndarray, distance: np.ndarray, params: HeuristicParams) -> np.ndarray:
    """Model-coverage point score (P,): min(1, |V_p| / k_count) * ((1 - w) + w * S_distance).

    The paper's coverage score "prioritises the number of visible sampled points, with a small
    preference for closer valid observations": the count term rewards every new observer up to
    ``k_count``; the distance term (weight ``w = coverage_closeness_weight``, evaluated with the
    coverage pass's range and margin in ``params``) prefers the closer ones.
    """
    vis = np.asarray(visible, bool)
    if vis.shape[0] == 0:
        return np.zeros(vis.shape[1])
    dscore = distance_score(distance, params.target_lo_m, params.target_hi_m, params.d_margin_m)
    dist = np.where(vis, dscore, 0.0).max(axis=0)
    count = np.minimum(1.0, vis.sum(axis=0) / float(params.k_count))
    w = float(params.coverage_closeness_weight)
    return count * ((1.0 - w) + w * dist)


def overlap_ratios(visible: np.ndarray) -> np.ndarray:
    """r_ij (V, V): common visible points / the smaller visible count; 0 on the diagonal and if empty."""
    a = np.asarray(visible, dtype=np.float32)
    common = np.rint(a @ a.T).astype(np.float64)  # exact counts; the ratio in float64
    n = np.asarray(visible, bool).sum(axis=1)
    smaller = np.minimum(n[:, None], n[None, :])
    r = np.where(smaller > 0, common / np.maximum(smaller, 1), 0.0)
    np.fill_diagonal(r, 0.0)
    return r.astype(float)


def overlap_pair_scores(ratios: np.ndarray, r_min: float, r_max: float) -> np.ndarray:
    """f(r): clipped linear ramp from 0 at ``r_min`` to 1 at ``r_max``."""
    return np.clip((np.asarray(ratios, dtype=float) - r_min) / (r_max - r_min), 0.0, 1.0)


def overlap_score(pair_scores: np.ndarray, top_k: int) -> float:
    """S_overlap (Eq. 8): mean over viewpoints of the mean of their top-k pair scores (self excluded)."""
    f = np.array(pair_scores, dtype=float)
    n = len(f)
    if n == 0:
        return 0.0
    np.fill_diagonal(f, 0.0)
    k = int(top_k)
    if n - 1 <= k:
        top = f.sum(axis=1)
    else:
        top = -np.partition(-f, k - 1, axis=1)[:, :k].sum(axis=1)
    return float(top.sum() / (k * n))


def connectivity_score(pair_scores: np.ndarray, tau_edge: float) -> float:
    """S_conn (Eq. 9): fraction of viewpoints in the largest component of the graph f > tau_edge."""
    f = np.asarray(pair_scores, dtype=float)
    n = len(f)
    if n == 0:
        return 0.0
    edges = f > tau_edge
    np.fill_diagonal(edges, False)
    _, labels = connected_components(csr_matrix(edges), directed=False)
    return float(np.bincount(labels).max() / n)


def viewpoint_set_scores(
    visible: np.ndarray, params: HeuristicParams, geometry: tuple[np.ndarray, np.ndarray] | None = None
) -> dict[str, float]:
    """Eq. 6-9: ``visibility``, ``overlap``, ``connectivity`` and ``R_viewpoint``; ``geometry``
    (``view_geometry``) weights the pair scores by their matchability when
    ``params.matchable_overlap``."""
    vis = np.asarray(visible, bool)
    n_vp, n_pt = vis.shape
    if n_vp == 0:
        return {"visibility": 0.0, "overlap": 0.0, "connectivity": 0.0, "R_viewpoint": 0.0}
    f = overlap_pair_scores(overlap_ratios(vis), params.r_min, params.r_max)
    if params.matchable_overlap:
        if geometry is None:
            raise ValueError("matchable_overlap needs the views' geometry (view_geometry)")
        centre, look = geometry
        f = f * pair_matchability(centre[:, None], look[:, None], centre[None], look[None], params)
    s_vis = float(vis.sum() / (n_vp * n_pt))
    s_ovl = overlap_score(f, params.top_k)
    s_conn = connectivity_score(f, params.tau_edge)
    return {
        "visibility": s_vis,
        "overlap": s_ovl,
        "connectivity": s_conn,
        "R_viewpoint": (s_vis + s_ovl + s_conn) / 3.0,
    }


def global_score(
    visible: np.ndarray,
    distance: np.ndarray,
    direction: np.ndarray,
    cos_incidence: np.ndarray,
    params: HeuristicParams,
    points: np.ndarray | None = None,
) -> dict[str, float]:
    """Eq. 10: R = sum_p R_point + |P| R_viewpoint, with its parts (``R_point_sum``, Eq. 6-9 terms).
    ``points`` (P, 3): the samples, needed for the matchable overlap."""
    pts = point_scores(visible, distance, direction, cos_incidence, params)
    geometry = view_geometry(visible, distance, direction, points) if points is not None else None
    vset = viewpoint_set_scores(visible, params, geometry)
    n_pt = np.asarray(visible).shape[1]
    r_point_sum = float(pts["R_point"].sum())
    return {"R": r_point_sum + n_pt * vset["R_viewpoint"], "R_point_sum": r_point_sum, **vset}
