"""The dense stage's settings (``reconstruct.dense`` of ``conf/reconstruct/default.yaml``), typed and
checked once where they are built: ``DenseSettings.from_config(node)`` refuses an unknown key, a
value of the wrong kind or out of range, naming the setting. What each value does and why it was
chosen is said beside it in the YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from scene.config import setting, typed_settings

BACKENDS = ("auto", "cpu", "cuda", "oracle")


# OpenCV's suggested SGBM penalties for one channel, per pixel of the block: P1 = 8 x block_size^2.
OPENCV_P1_PER_BLOCK_PIXEL = 8.0
OPENCV_P2_PER_BLOCK_PIXEL = 32.0


@dataclass(frozen=True)
class SgbmSettings:
    """OpenCV StereoSGBM's parameters (px, counts)."""

    block_size: int = setting(low=1, odd=True)
    uniqueness_ratio: int = setting(low=0)
    speckle_window_size: int = setting(low=0)
    speckle_range: int = setting(low=0)
    disp12_max_diff: int = setting()
    mirror_pass: bool = setting(False)  # stereo.matching.sgbm_disparity: also match upside down, average
    crop_to_overlap: bool = setting(False)  # stereo.matching.matchable_window: match only what can match
    p1_per_block_pixel: float = setting(OPENCV_P1_PER_BLOCK_PIXEL, low=0)  # P1 / block_size^2 (steps of 1)
    p2_per_block_pixel: float = setting(OPENCV_P2_PER_BLOCK_PIXEL, low=0)  # P2 / block_size^2 (larger)

    def __post_init__(self) -> None:
        if self.p2_per_block_pixel < self.p1_per_block_pixel:
            raise ValueError(
                "p2_per_block_pixel must be at least p1_per_block_pixel (OpenCV's SGBM needs P2 >= P1), "
                f"got {self.p2_per_block_pixel:g} and {self.p1_per_block_pixel:g}"
            )


@dataclass(frozen=True)
class FusionSettings:
    """COLMAP's stereo fusion (``pycolmap.StereoFusionOptions``) and the memory it may use (GB)."""

    min_num_pixels: int = setting(low=1)
    max_reproj_error: float = setting(above=0)
    max_depth_error: float = setting(above=0)
    max_normal_error: float = setting(above=0)
    max_memory_gb: float | str | None = setting(None, above=0)  # a number (GB), auto or null
    check_num_images: int | None = setting(None, low=1)
    support_share: float = setting(0.0, low=0, high=1)  # reconstruct.fusion_support; 0: off
    method: str = setting("colmap", choices=("colmap", "rays"))  # rays: reconstruct.fusion_rays
    ray_neighbours: int = setting(12, low=1)
    ray_voxel_m: float = setting(0.0, low=0)
    conditioning_ratio: float = setting(0.0, low=0)  # reconstruct.fusion_rays.well_conditioned; 0: off
    conditioning_cell_m: float = setting(0.05, above=0)
    slant_window_px: float = setting(0.0, low=0)  # reconstruct.stereo_noise.slant_depth_sigma; 0: off
    gate_disparity_px: float = setting(0.0, low=0)  # reconstruct.fusion_rays._gate_claims; 0: off
    support_radius_m: float = setting(0.03, above=0)

    def __post_init__(self) -> None:
        if isinstance(self.max_memory_gb, str) and self.max_memory_gb != "auto":
            raise ValueError(f"max_memory_gb must be a number (GB), auto or null, got {self.max_memory_gb!r}")


@dataclass(frozen=True)
class GeometricConsistencySettings:
    """Multi-view geometric consistency of each depth (``reconstruct.depth_filter``)."""

    min_views: int = setting(low=0)  # 0: off
    num_views: int = setting(low=1)
    rel_tol: float = setting(above=0)


@dataclass(frozen=True)
class OracleSettings:
    """The oracle back-end's stereo noise (``reconstruct.oracle``): disparity noise in pixels."""

    disparity_sigma_px: float = setting(low=0)


@dataclass(frozen=True)
class PatchMatchSettings:
    """The CUDA back-end's ``pycolmap.PatchMatchOptions``."""

    window_radius: int = setting(low=1)
    num_iterations: int = setting(low=1)


@dataclass(frozen=True)
class DenseSettings:
    """``reconstruct.dense``: depth maps (CPU SGBM or CUDA PatchMatch) and their fusion."""

    backend: str = setting(choices=BACKENDS)
    max_image_size: int = setting(low=1)
    num_partners: int = setting(low=1)
    min_triangulation_angle_deg: float = setting(low=0)
    max_triangulation_angle_deg: float = setting(high=180)
    min_shared_points: int = setting(low=1)
    partner_ideal_angle_deg: float = setting(above=0)
    min_baseline_axis_angle_deg: float = setting(low=0, high=90)
    reference_views_per_point: int | None = setting(low=1)
    reference_min_new_points: int = setting(low=0)
    max_num_disparities: int = setting(low=16, multiple_of=16)  # SGBM's own rule
    min_texture_std: float = setting(low=0)
    texture_window_px: int = setting(low=1)
    normal_window_px: int = setting(low=1)
    num_threads: int = setting(low=-1)  # -1: every core
    sgbm: SgbmSettings = setting()
    min_consistent_partners: int = setting(low=1)
    consistency_rel_tol: float = setting(above=0)
    edge_margin_px: int = setting(low=0)
    geometric_consistency: GeometricConsistencySettings = setting()
    fusion: FusionSettings = setting()
    patch_match: PatchMatchSettings = setting()
    oracle: OracleSettings = setting()
    partner_weights: str = setting("equal", choices=("equal", "precision"))
    partners_must_rectify: bool = setting(False)  # reconstruct.workspace.select_partners
    max_rectified_area_ratio: float = setting(4.0, above=1)  # reconstruct.rectify
    downscale_before_undistorting: bool = setting(False)  # reconstruct.workspace.prepare_workspace

    def __post_init__(self) -> None:
        if not self.min_triangulation_angle_deg < self.max_triangulation_angle_deg:
            raise ValueError(
                "min_triangulation_angle_deg must be below max_triangulation_angle_deg, got "
                f"{self.min_triangulation_angle_deg} and {self.max_triangulation_angle_deg}"
            )
        if self.num_threads == 0:
            raise ValueError("num_threads must be -1 (every core) or >= 1, got 0")

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "reconstruct.dense") -> DenseSettings:
        """From the ``reconstruct.dense`` mapping; a ``ValueError`` names the bad setting."""
        return typed_settings(cls, node, prefix)
