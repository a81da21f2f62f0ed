"""The stereo depth-noise model every dense component shares (the oracle's noise, fusion's weights).

A disparity error of ``s`` pixels at depth ``z`` on a pair of baseline ``B`` and focal length ``f``
(pixels) moves the depth by ``z^2 / (f B) s``: far views and narrow baselines measure depth coarsely.

A window matcher (SGBM's block) also assumes the surface is level with the image across its window.
On a surface whose normal makes the angle ``theta`` with the ray, the depth varies across ``w``
pixels of window by ``w z tan(theta) / f``, and the matched depth is uncertain by about that much:
a grazing view of the ground measures it poorly however close and wide its pair is.
"""

from __future__ import annotations

import numpy as np


def stereo_depth_sigma(depth: np.ndarray, focal_px: float, baseline_m: float, disparity_sigma_px: float):
    """Depth noise (m) of a stereo pair at ``depth`` (m): z^2 / (f B) times the disparity noise (px)."""
    z = np.asarray(depth, dtype=np.float64)
    return z * z / (float(focal_px) * float(baseline_m)) * float(disparity_sigma_px)


def slant_depth_sigma(depth: np.ndarray, focal_px: float, cos_incidence: np.ndarray, window_px: float):
    """Depth spread (m) across ``window_px`` pixels of a matching window on a surface seen at
    incidence ``acos(cos_incidence)`` (ray vs normal): ``window_px z tan(theta) / f``. ``cos_incidence``
    is clipped to [0.1, 1] (84 deg), where a tangent plane still meets the ray."""
    z = np.asarray(depth, dtype=np.float64)
    cos = np.clip(np.abs(np.asarray(cos_incidence, dtype=np.float64)), 0.1, 1.0)
    return float(window_px) * z / float(focal_px) * np.sqrt(1.0 - cos * cos) / cos
