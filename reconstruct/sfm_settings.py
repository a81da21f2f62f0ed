"""The SfM stage's settings (``reconstruct.sfm`` of ``conf/reconstruct/default.yaml``), typed and
checked once where they are built: ``SfmSettings.from_config(node)`` refuses an unknown key, a value
of the wrong kind or out of range, naming the setting. ``reconstruct.sfm.sfm_options`` maps them
onto pycolmap's option objects; what each value does and why is said beside it in the YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from scene.config import typed_settings

MATCHING_METHODS = ("auto", "exhaustive", "spatial", "pose_prior", "sequential")
MAPPING_METHODS = ("incremental", "global")
# COLMAP's ba_global_max_refinements: bundle adjust + filter rounds per global BA of the incremental
# mapper (it stops earlier once fewer than 0.05 % of the observations change).
COLMAP_GLOBAL_BA_MAX_REFINEMENTS = 5
# COLMAP's local bundle adjustment after each registered image: the images sharing most points with
# it, Ceres iterations, bundle adjust + filter rounds. Settings added after records at these values.
COLMAP_LOCAL_BA = {"local_ba_num_images": 6, "local_ba_max_iterations": 25, "local_ba_max_refinements": 2}


def _at_least(name: str, value, low) -> None:
    if value < low:
        raise ValueError(f"{name} must be >= {low}, got {value}")


@dataclass(frozen=True)
class ExtractionSettings:
    """SIFT extraction (px, counts)."""

    max_image_size: int
    max_num_features: int
    first_octave: int

    def __post_init__(self) -> None:
        _at_least("max_image_size", self.max_image_size, 1)
        _at_least("max_num_features", self.max_num_features, 1)


@dataclass(frozen=True)
class MatchingSettings:
    """Pair selection and matching (counts, metres, degrees)."""

    method: str
    exhaustive_max_images: int
    spatial_max_num_neighbors: int
    spatial_max_distance_m: float
    pose_prior_max_neighbors: int
    pose_prior_max_distance_m: float
    pose_prior_max_axis_angle_deg: float
    sequential_overlap: int
    max_ratio: float
    guided_matching: bool
    prior_check: dict | None = None  # reconstruct.pair_check.PairCheckSettings checks it

    def __post_init__(self) -> None:
        if self.method not in MATCHING_METHODS:
            raise ValueError(f"method must be one of {MATCHING_METHODS}, got {self.method!r}")
        for name in ("exhaustive_max_images", "spatial_max_num_neighbors", "pose_prior_max_neighbors"):
            _at_least(name, getattr(self, name), 1)
        _at_least("sequential_overlap", self.sequential_overlap, 1)
        for name in ("spatial_max_distance_m", "pose_prior_max_distance_m"):
            _at_least(name, getattr(self, name), 0)
        if not 0 < self.pose_prior_max_axis_angle_deg <= 180:
            raise ValueError(
                "pose_prior_max_axis_angle_deg must lie in (0, 180], "
                f"got {self.pose_prior_max_axis_angle_deg}"
            )
        if not 0 < self.max_ratio <= 1:
            raise ValueError(f"max_ratio must lie in (0, 1], got {self.max_ratio}")


@dataclass(frozen=True)
class MappingSettings:
    """The mapper and its bundle adjustments (counts, ratios)."""

    method: str
    refine_focal_length: bool
    refine_principal_point: bool
    refine_extra_params: bool
    use_prior_position: bool
    robust_loss_on_prior_position: bool
    min_model_size: int
    global_ba_growth_ratio: float
    global_ba_max_iterations: int
    global_ba_skip_redundant_points: bool
    global_prior_ba: bool
    global_prior_ba_max_iterations: int
    global_ba_max_refinements: int = COLMAP_GLOBAL_BA_MAX_REFINEMENTS
    local_ba_num_images: int = COLMAP_LOCAL_BA["local_ba_num_images"]
    local_ba_max_iterations: int = COLMAP_LOCAL_BA["local_ba_max_iterations"]
    local_ba_max_refinements: int = COLMAP_LOCAL_BA["local_ba_max_refinements"]

    def __post_init__(self) -> None:
        if self.method not in MAPPING_METHODS:
            raise ValueError(f"method must be one of {MAPPING_METHODS}, got {self.method!r}")
        if self.global_ba_growth_ratio <= 1.0:
            raise ValueError(f"global_ba_growth_ratio must be > 1, got {self.global_ba_growth_ratio}")
        _at_least("min_model_size", self.min_model_size, 2)
        for name in (
            "global_ba_max_iterations",
            "global_prior_ba_max_iterations",
            "global_ba_max_refinements",
            *COLMAP_LOCAL_BA,
        ):
            _at_least(name, getattr(self, name), 1)


@dataclass(frozen=True)
class SfmSettings:
    """``reconstruct.sfm``: extraction, matching and mapping; ``num_threads`` -1 is every core."""

    num_threads: int
    extraction: ExtractionSettings
    matching: MatchingSettings
    mapping: MappingSettings

    def __post_init__(self) -> None:
        if self.num_threads == 0 or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or >= 1, got {self.num_threads}")

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "reconstruct.sfm") -> SfmSettings:
        """From the ``reconstruct.sfm`` mapping; a ``ValueError`` names the bad setting."""
        return typed_settings(cls, node, prefix)
