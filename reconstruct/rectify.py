"""Stereo rectification of two views (the CPU back-end's pairs), and whether a pair can be rectified.

Both views are turned to one orientation whose x axis is the baseline, so matching points share a
row. A pair whose baseline runs close to an optical axis cannot be: the turned image stretches
across many times its own size (its epipole lies in or near the image), and a matcher searching
that canvas finds little. Partner selection (``reconstruct.workspace.select_partners``) asks the
same question, so no partner slot goes to such a pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from reconstruct.workspace import View

# A rectified canvas (both views' column span x the reference's rows) larger than this many times
# the reference image comes from a near-degenerate pair (reconstruct.dense.max_rectified_area_ratio
# overrides it).
DEFAULT_MAX_AREA_RATIO = 4.0


@dataclass(frozen=True)
class RectifiedPair:
    """A reference view and a partner rectified to a common orientation, baseline along +x.

    ``H_ref``/``H_src`` map OpenCV pixels of each view to the rectified image (size ``size``);
    both rectified cameras share ``K_rect`` and ``rect_from_world``; the partner sits ``baseline``
    metres along +x, so disparity ``d = x_ref - x_src = f * baseline / Z``.
    """

    H_ref: np.ndarray
    H_src: np.ndarray
    K_rect: np.ndarray
    rect_from_world: np.ndarray
    baseline: float
    size: tuple[int, int]


def rectify_pair(
    ref: View,
    src: View,
    disparity_offset: int = 0,
    pad_left: int = 0,
    max_area_ratio: float = DEFAULT_MAX_AREA_RATIO,
) -> RectifiedPair | None:
    """Rectify ``src`` against ``ref`` (baseline along the rectified +x axis); None if degenerate.

    The partner's rectified image is shifted right by ``disparity_offset`` pixels (so SGBM can
    search from disparity 0) and the canvas gets ``pad_left`` empty columns on the left (SGBM
    leaves its first ``numDisparities`` columns unmatched). ``H_*`` and ``K_rect`` describe the
    reference; true disparity = SGBM disparity + ``disparity_offset``. None also when the canvas
    (both views' column span x the reference's rows) exceeds ``max_area_ratio`` times the reference.
    """
    baseline_w = src.center - ref.center
    baseline = float(np.linalg.norm(baseline_w))
    if baseline == 0:
        return None
    x_axis = baseline_w / baseline
    forward = ref.forward + src.forward
    y_axis = np.cross(forward, x_axis)
    if np.linalg.norm(y_axis) < 1e-6:
        return None
    y_axis /= np.linalg.norm(y_axis)
    z_axis = np.cross(x_axis, y_axis)
    rect_from_world = np.stack([x_axis, y_axis, z_axis])
    f = float(ref.K[0, 0])
    K0 = np.array([[f, 0.0, 0.0], [0.0, f, 0.0], [0.0, 0.0, 1.0]])
    offset = np.array([[1.0, 0.0, float(disparity_offset)], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    H_ref0 = K0 @ rect_from_world @ ref.rotation.T @ np.linalg.inv(ref.K)
    H_src0 = offset @ K0 @ rect_from_world @ src.rotation.T @ np.linalg.inv(src.K)
    ref_corners = _warp_corners(H_ref0, ref.width, ref.height)
    src_corners = _warp_corners(H_src0, src.width, src.height)
    if ref_corners is None or src_corners is None:
        return None
    # The reference's rows and columns, plus ``pad_left`` columns on the left: a reference pixel at
    # column x matches the partner at x - d with 0 <= d < pad_left, so partner content right of the
    # reference or farther left is never searched (and was up to 3x the SGBM work).
    x_min = ref_corners[:, 0].min() - pad_left
    x_max = ref_corners[:, 0].max()
    y_min, y_max = ref_corners[:, 1].min(), ref_corners[:, 1].max()
    width, height = int(math.ceil(x_max - x_min)) + 1, int(math.ceil(y_max - y_min)) + 1
    # Degenerate pairs are told by the span of both views' columns, as the partner would be warped.
    both_columns = np.concatenate([ref_corners[:, 0], src_corners[:, 0]])
    span = both_columns.max() - both_columns.min()
    if span * height > max_area_ratio * ref.width * ref.height:
        return None
    shift = np.array([[1.0, 0.0, -x_min], [0.0, 1.0, -y_min], [0.0, 0.0, 1.0]])
    return RectifiedPair(
        shift @ H_ref0, shift @ H_src0, shift @ K0, rect_from_world, baseline, (width, height)
    )


def _warp_corners(H: np.ndarray, width: int, height: int) -> np.ndarray | None:
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1], [0, height - 1, 1]], float)
    mapped = corners @ H.T
    if np.any(mapped[:, 2] <= 1e-9):
        return None
    return mapped[:, :2] / mapped[:, 2:]
