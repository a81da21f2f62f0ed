"""The SfM stage's settings (``reconstruct.sfm`` of ``conf/reconstruct/default.yaml``), typed and
checked once where they are built: ``SfmSettings.from_config(node)`` refuses an unknown key, a value
of the wrong kind or out of range, naming the setting. ``reconstruct.sfm.sfm_options`` maps them
onto pycolmap's option objects; what each value does and why is said beside it in the YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from scene.config import setting, typed_settings

MATCHING_METHODS = ("auto", "exhaustive", "spatial", "pose_prior", "sequential")
MAPPING_METHODS = ("incremental", "global")
# COLMAP's ba_global_max_refinements: bundle adjust + filter rounds per global BA of the incremental
# mapper (it stops earlier once fewer than 0.05 % of the observations change).
COLMAP_GLOBAL_BA_MAX_REFINEMENTS = 5
# COLMAP's local bundle adjustment after each registered image: the images sharing most points with
# it, Ceres iterations, bundle adjust + filter rounds. Settings added after records at these values.
COLMAP_LOCAL_BA = {"local_ba_num_images": 6, "local_ba_max_iterations": 25, "local_ba_max_refinements": 2}
# COLMAP's test before the incremental mapper registers a new image: RANSAC inliers of its 2D-3D
# correspondences, in number and as a share of them. Settings added after records at these values.
COLMAP_ABS_POSE = {"abs_pose_min_num_inliers": 30, "abs_pose_min_inlier_ratio": 0.25}


@dataclass(frozen=True)
class ExtractionSettings:
    """SIFT extraction (px, counts)."""

    max_image_size: int = setting(low=1)
    max_num_features: int = setting(low=1)
    first_octave: int = setting()


@dataclass(frozen=True)
class MatchingSettings:
    """Pair selection and matching (counts, metres, degrees)."""

    method: str = setting(choices=MATCHING_METHODS)
    exhaustive_max_images: int = setting(low=1)
    spatial_max_num_neighbors: int = setting(low=1)
    spatial_max_distance_m: float = setting(low=0)  # 0: no distance cut-off
    pose_prior_max_neighbors: int = setting(low=1)
    pose_prior_max_distance_m: float = setting(low=0)
    pose_prior_max_axis_angle_deg: float = setting(above=0, high=180)
    sequential_overlap: int = setting(low=1)
    max_ratio: float = setting(above=0, high=1)
    guided_matching: bool = setting()
    prior_check: dict | None = setting(None)  # reconstruct.pair_check.PairCheckSettings checks it


@dataclass(frozen=True)
class MappingSettings:
    """The mapper and its bundle adjustments (counts, ratios)."""

    method: str = setting(choices=MAPPING_METHODS)
    refine_focal_length: bool = setting()
    refine_principal_point: bool = setting()
    refine_extra_params: bool = setting()
    use_prior_position: bool = setting()
    robust_loss_on_prior_position: bool = setting()
    min_model_size: int = setting(low=2)
    global_ba_growth_ratio: float = setting(above=1)
    global_ba_max_iterations: int = setting(low=1)
    global_ba_skip_redundant_points: bool = setting()
    global_prior_ba: bool = setting()
    global_prior_ba_max_iterations: int = setting(low=1)
    global_ba_max_refinements: int = setting(COLMAP_GLOBAL_BA_MAX_REFINEMENTS, low=1)
    local_ba_num_images: int = setting(COLMAP_LOCAL_BA["local_ba_num_images"], low=1)
    local_ba_max_iterations: int = setting(COLMAP_LOCAL_BA["local_ba_max_iterations"], low=1)
    local_ba_max_refinements: int = setting(COLMAP_LOCAL_BA["local_ba_max_refinements"], low=1)
    abs_pose_min_num_inliers: int = setting(COLMAP_ABS_POSE["abs_pose_min_num_inliers"], low=4)
    abs_pose_min_inlier_ratio: float = setting(COLMAP_ABS_POSE["abs_pose_min_inlier_ratio"], above=0, high=1)


@dataclass(frozen=True)
class SfmSettings:
    """``reconstruct.sfm``: extraction, matching and mapping."""

    num_threads: int = setting(low=-1)  # -1: every core
    extraction: ExtractionSettings = setting()
    matching: MatchingSettings = setting()
    mapping: MappingSettings = setting()

    def __post_init__(self) -> None:
        if self.num_threads == 0:
            raise ValueError("num_threads must be -1 (every core) or >= 1, got 0")

    @classmethod
    def from_config(cls, node: Mapping, prefix: str = "reconstruct.sfm") -> SfmSettings:
        """From the ``reconstruct.sfm`` mapping; a ``ValueError`` names the bad setting."""
        return typed_settings(cls, node, prefix)
