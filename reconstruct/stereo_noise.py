"""The stereo depth-noise model every dense component shares (the oracle's noise, fusion's weights).

A disparity error of ``s`` pixels at depth ``z`` on a pair of baseline ``B`` and focal length ``f``
(pixels) moves the depth by ``z^2 / (f B) s``: far views and narrow baselines measure depth coarsely.
"""

from __future__ import annotations

import numpy as np


def stereo_depth_sigma(depth: np.ndarray, focal_px: float, baseline_m: float, disparity_sigma_px: float):
    """Depth noise (m) of a stereo pair at ``depth`` (m): z^2 / (f B) times the disparity noise (px)."""
    z = np.asarray(depth, dtype=np.float64)
    return z * z / (float(focal_px) * float(baseline_m)) * float(disparity_sigma_px)
