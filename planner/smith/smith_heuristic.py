"""Smith et al. 2018 reconstructability heuristic (ACM TOG 37(6); public code nmoehrle/uavmvs).

For a surface sample s with normal n seen by a set of views, every unordered pair of observation rays
(i, j) contributes

    w1(alpha) * w2 * w3(alpha) * cos(theta_m)
    w1(alpha) = 1 / (1 + exp(-k1 (alpha - alpha1)))          k1 = 32, alpha1 = pi / 16  (triangulation)
    w3(alpha) = 1 - 1 / (1 + exp(-k3 (alpha - alpha3)))      k3 = 8,  alpha3 = pi / 4   (matchability)
    w2        = 1 - d_m / d_max,  d_m = the larger of the two distances                 (resolution)
    theta_m   = the larger of the two incidence angles

where alpha is the angle between the two rays at s. h(s) is the sum over pairs of at most
``MAX_RAYS`` = 32 rays (the public code's cap; we keep the 32 most frontal rays). The optimisation
objective is the mean over samples of max(h_target - h(s), 0)^2 with h_target = 3. As in the public
code, a sample seen by no view has h = -1 (``H_UNOBSERVED``), so a first observation is already a gain.

Observation rays are stored per sample as unit directions from the sample to the camera, the
resolution term ``scale = 1 - d / d_max`` and ``cos(theta)``.
"""

from __future__ import annotations

import numpy as np

# w1 (triangulation) and w3 (matchability) with Smith et al.'s constants live in planner.heuristics.
from planner.heuristics import smith_w1 as w1
from planner.heuristics import smith_w3 as w3

MIN_COS_INCIDENCE = 0.087  # ~ cos(85 deg), the public code's incidence limit
MAX_RAYS = 32
H_TARGET = 3.0
H_UNOBSERVED = -1.0


def pair_terms(dir_a, scale_a, cos_a, dir_b, scale_b, cos_b) -> np.ndarray:
    """Smith's pair term for broadcastable pairs of observation rays.

    Args:
        dir_a, dir_b: (..., 3) unit directions from the sample to each camera.
        scale_a, scale_b: (...) resolution terms ``1 - d / d_max`` of each ray.
        cos_a, cos_b: (...) cosines of each ray's incidence angle.

    Returns:
        (...) w1(alpha) * w2 * w3(alpha) * cos(theta_m), with w2 = min(scale), cos(theta_m) = min(cos).
    """
    cos_alpha = np.clip(np.sum(np.asarray(dir_a) * np.asarray(dir_b), axis=-1), -1.0, 1.0)
    alpha = np.arccos(cos_alpha)
    return w1(alpha) * w3(alpha) * np.minimum(scale_a, scale_b) * np.minimum(cos_a, cos_b)


def reconstructability(dirs, scales, coss, valid) -> np.ndarray:
    """h(s) for every sample from its observation rays.

    Args:
        dirs: (P, R, 3) unit directions sample -> camera.
        scales: (P, R) resolution terms ``1 - d / d_max``.
        coss: (P, R) incidence cosines.
        valid: (P, R) bool, which of the R slots hold a ray.

    Returns:
        (P,) h: the sum of the pair terms over all unordered pairs of valid rays; ``H_UNOBSERVED``
        for samples without any ray.
    """
    dirs = np.asarray(dirs, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    n_rays = valid.shape[1]
    if n_rays < 2:
        h = np.zeros(valid.shape[0])
    else:
        iu, ju = np.triu_indices(n_rays, k=1)
        terms = pair_terms(dirs[:, iu], scales[:, iu], coss[:, iu], dirs[:, ju], scales[:, ju], coss[:, ju])
        h = np.sum(np.where(valid[:, iu] & valid[:, ju], terms, 0.0), axis=1)
    return np.where(valid.any(axis=1), h, H_UNOBSERVED)


def objective_terms(h, h_target: float = H_TARGET) -> np.ndarray:
    """Per-sample objective max(h_target - h, 0)^2 (the optimisation minimises their mean)."""
    return np.maximum(float(h_target) - np.asarray(h, dtype=float), 0.0) ** 2


def top_rays(visible, cos, max_rays: int = MAX_RAYS) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the (at most ``max_rays``) most frontal visible views of every sample.

    Args:
        visible: (V, P) bool visibility.
        cos: (V, P) incidence cosines.
        max_rays: cap on the rays per sample.

    Returns:
        view index (P, R) and validity (P, R) with R = min(V, max_rays).
    """
    visible = np.asarray(visible, dtype=bool)
    n_views = visible.shape[0]
    key = np.where(visible, np.asarray(cos, dtype=float), -np.inf)
    r = min(n_views, int(max_rays))
    if r < n_views:
        idx = np.argpartition(-key, r - 1, axis=0)[:r]
    else:
        idx = np.broadcast_to(np.arange(n_views)[:, None], key.shape)
    idx = np.ascontiguousarray(idx.T)
    valid = np.take_along_axis(key.T, idx, axis=1) > -np.inf
    return idx, valid
