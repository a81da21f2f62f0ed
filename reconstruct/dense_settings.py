"""The dense stage's settings (``reconstruct.dense`` of ``conf/reconstruct/default.yaml``), typed and
checked once where they are built: ``DenseSettings.from_config(node)`` refuses an unknown key, a
value of the wrong kind or out of range, naming the setting. What each value does and why it was
chosen is said beside it in the YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from scene.config import typed_settings

BACKENDS = ("auto", "cpu", "cuda")


def _at_least(name: str, value, low) -> None:
    if value < low:
        raise ValueError(f"{name} must be >= {low}, got {value}")


def _positive(name: str, value) -> None:
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value}")


@dataclass(frozen=True)
class SgbmSettings:
    """OpenCV StereoSGBM's parameters (px, counts)."""

    block_size: int
    uniqueness_ratio: int
    speckle_window_size: int
    speckle_range: int
    disp12_max_diff: int

    def __post_init__(self) -> None:
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"block_size must be an odd number >= 1, got {self.block_size}")
        for name in ("uniqueness_ratio", "speckle_window_size", "speckle_range"):
            _at_least(name, getattr(self, name), 0)


@dataclass(frozen=True)
class FusionSettings:
    """COLMAP's stereo fusion (``pycolmap.StereoFusionOptions``) and the memory it may use."""

    min_num_pixels: int
    max_reproj_error: float
    max_depth_error: float
    max_normal_error: float
    max_memory_gb: float | None = None
    check_num_images: int | None = None

    def __post_init__(self) -> None:
        _at_least("min_num_pixels", self.min_num_pixels, 1)
        for name in ("max_reproj_error", "max_depth_error", "max_normal_error"):
            _positive(f"{name}", getattr(self, name))
        if self.max_memory_gb is not None:
            _positive("max_memory_gb", self.max_memory_gb)
        if self.check_num_images is not None:
            _at_least("check_num_images", self.check_num_images, 1)


@dataclass(frozen=True)
class PatchMatchSettings:
    """The CUDA back-end's ``pycolmap.PatchMatchOptions``."""

    window_radius: int
    num_iterations: int

    def __post_init__(self) -> None:
        _at_least("window_radius", self.window_radius, 1)
        _at_least("num_iterations", self.num_iterations, 1)


@dataclass(frozen=True)
class DenseSettings:
    """``reconstruct.dense``: depth maps (CPU SGBM or CUDA PatchMatch) and their fusion."""

    backend: str
    max_image_size: int
    num_partners: int
    min_triangulation_angle_deg: float
    max_triangulation_angle_deg: float
    min_shared_points: int
    partner_ideal_angle_deg: float
    min_baseline_axis_angle_deg: float
    reference_views_per_point: int | None
    reference_min_new_points: int
    max_num_disparities: int
    min_texture_std: float
    texture_window_px: int
    normal_window_px: int
    num_threads: int
    sgbm: SgbmSettings
    min_consistent_partners: int
    consistency_rel_tol: float
    fusion: FusionSettings
    patch_match: PatchMatchSettings

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        for name in ("max_image_size", "num_partners", "min_shared_points", "texture_window_px"):
            _at_least(name, getattr(self, name), 1)
        _at_least("normal_window_px", self.normal_window_px, 1)
        if not 0 <= self.min_triangulation_angle_deg < self.max_triangulation_angle_deg <= 180:
            raise ValueError(
                "min_triangulation_angle_deg and max_triangulation_angle_deg must satisfy 0 <= min < max "
                f"<= 180, got {self.min_triangulation_angle_deg}, {self.max_triangulation_angle_deg}"
            )
        _positive("partner_ideal_angle_deg", self.partner_ideal_angle_deg)
        if not 0 <= self.min_baseline_axis_angle_deg <= 90:
            raise ValueError(
                f"min_baseline_axis_angle_deg must lie in [0, 90], got {self.min_baseline_axis_angle_deg}"
            )
        if self.reference_views_per_point is not None:
            _at_least("reference_views_per_point", self.reference_views_per_point, 1)
        _at_least("reference_min_new_points", self.reference_min_new_points, 0)
        if self.max_num_disparities < 16 or self.max_num_disparities % 16:
            raise ValueError(
                f"max_num_disparities must be a multiple of 16 (SGBM), got {self.max_num_disparities}"
            )
        _at_least("min_texture_std", self.min_texture_std, 0)
        if self.num_threads == 0 or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or >= 1, got {self.num_threads}")
        _at_least("min_consistent_partners", self.min_consistent_partners, 1)
        _positive("consistency_rel_tol", self.consistency_rel_tol)

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "reconstruct.dense") -> DenseSettings:
        """From the ``reconstruct.dense`` mapping; a ``ValueError`` names the bad setting."""
        return typed_settings(cls, node, prefix)
