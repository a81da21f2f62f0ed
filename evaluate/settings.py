"""Typed, validated evaluation settings (the ``evaluate`` config group, ``conf/evaluate/default.yaml``).

The dataclass defaults equal the YAML defaults (a test checks it), so library calls without a
config score exactly like ``python run.py``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields

from scene.config import plain

MESH_INPUTS = ("vertices", "surface")


@dataclass(frozen=True)
class VisualisationSettings:
    """Error visualisation (the paper's Figure 3): colour scale, views, splatting.

    Attributes:
        enabled: write coloured PLYs and PNG views.
        vmax_m: distance in metres at the top of the colour scale; keep it equal for every method of
            one scene so their pictures compare.
        colormap: matplotlib colour map name.
        coverage_threshold_m: a ground-truth sample counts as covered within this distance (m).
        width, height, hfov_deg: the virtual camera of the PNG views (pixels, degrees).
        oblique_pitch_deg: pitch of the four oblique views (degrees, negative looks down).
        point_radius_px: splat radius in pixels (0 = one pixel per point).
        max_render_points: points drawn per picture (a deterministic subsample above it).
        seed: seed of that subsample.
    """

    enabled: bool = True
    vmax_m: float = 0.2
    colormap: str = "turbo"
    coverage_threshold_m: float = 0.050
    width: int = 1024
    height: int = 768
    hfov_deg: float = 50.0
    oblique_pitch_deg: float = -35.0
    point_radius_px: int = 1
    max_render_points: int = 2_000_000
    seed: int = 0

    def __post_init__(self) -> None:
        _positive("evaluate.visualise.vmax_m", self.vmax_m)
        _positive("evaluate.visualise.coverage_threshold_m", self.coverage_threshold_m)
        _positive("evaluate.visualise.width", self.width)
        _positive("evaluate.visualise.height", self.height)
        _positive("evaluate.visualise.max_render_points", self.max_render_points)
        if not 0.0 < self.hfov_deg < 180.0:
            raise ValueError(f"evaluate.visualise.hfov_deg must lie in (0, 180), got {self.hfov_deg}")
        if not -90.0 <= self.oblique_pitch_deg < 0.0:
            raise ValueError(
                f"evaluate.visualise.oblique_pitch_deg must lie in [-90, 0), got {self.oblique_pitch_deg}"
            )
        if not 0 <= self.point_radius_px <= 5:
            raise ValueError(
                f"evaluate.visualise.point_radius_px must lie in [0, 5], got {self.point_radius_px}"
            )
        # heavy (matplotlib): imported on use
        import matplotlib

        if self.colormap not in matplotlib.colormaps:
            raise ValueError(f"evaluate.visualise.colormap: unknown matplotlib colour map {self.colormap!r}")


@dataclass(frozen=True)
class EvaluationSettings:
    """How a reconstruction is scored against the ground truth (see ``conf/evaluate/default.yaml``).

    Attributes:
        accuracy_percentiles: percentiles q (%) of the accuracy distance.
        completeness_thresholds_m: thresholds t (m) of completeness, precision and F-score.
        gt_sample_density_per_m2: ground-truth surface samples per square metre.
        gt_sample_seed: seed of those samples (the same samples for every method of a scene).
        distance_cap_m: bound (m) of the ground-truth-to-reconstruction nearest-neighbour search; the
            Chamfer halves clip distances at it. None searches without bound (slow beside big holes).
        mesh_input: ``vertices`` (score a mesh file's vertices) or ``surface`` (sample its faces).
        mesh_sample_density_per_m2: samples per square metre when ``mesh_input`` is ``surface``.
        max_gt_samples: refuse a density that would draw more ground-truth samples than this.
        chunk_points: points per distance query chunk (bounds memory).
        export_gt_mesh: write the ground truth restricted to the region as a PLY beside the record.
        ground_height_m: ground-truth surface facing up below this height (m) is ground, above it
            roof (completeness per surface class).
        facing_normal_z: a triangle faces up when its normal's z is at least this, down when at most
            minus this, sideways otherwise (0.5: slopes up to 60 degrees are roofs).
        exclude_enclosed: score completeness only over ground-truth samples some exterior line of
            sight reaches (``scene.enclosure.exposed_samples``); enclosed ones are counted apart.
        visualise: the error pictures.
    """

    accuracy_percentiles: tuple[float, ...] = (90.0, 95.0)
    completeness_thresholds_m: tuple[float, ...] = (0.050, 0.075)
    gt_sample_density_per_m2: float = 1000.0
    gt_sample_seed: int = 0
    distance_cap_m: float | None = 1.0
    mesh_input: str = "vertices"
    mesh_sample_density_per_m2: float = 10000.0
    max_gt_samples: int = 40_000_000
    chunk_points: int = 1_000_000
    export_gt_mesh: bool = True
    ground_height_m: float = 0.25
    facing_normal_z: float = 0.5
    exclude_enclosed: bool = True
    visualise: VisualisationSettings = field(default_factory=VisualisationSettings)

    def __post_init__(self) -> None:
        percentiles = tuple(float(q) for q in self.accuracy_percentiles)
        thresholds = tuple(float(t) for t in self.completeness_thresholds_m)
        object.__setattr__(self, "accuracy_percentiles", percentiles)
        object.__setattr__(self, "completeness_thresholds_m", thresholds)
        if not percentiles or not all(0.0 < q <= 100.0 for q in percentiles):
            raise ValueError(f"evaluate.accuracy_percentiles must be in (0, 100], got {list(percentiles)}")
        if not thresholds or not all(math.isfinite(t) and t > 0.0 for t in thresholds):
            raise ValueError(f"evaluate.completeness_thresholds_m must be positive, got {list(thresholds)}")
        for name, keys in (
            ("accuracy_percentiles", map(percentile_key, percentiles)),
            ("completeness_thresholds_m", map(threshold_key, thresholds)),
        ):
            keys = list(keys)
            if len(set(keys)) != len(keys):
                raise ValueError(f"evaluate.{name} has duplicates: {keys}")
        _positive("evaluate.gt_sample_density_per_m2", self.gt_sample_density_per_m2)
        _positive("evaluate.mesh_sample_density_per_m2", self.mesh_sample_density_per_m2)
        _positive("evaluate.max_gt_samples", self.max_gt_samples)
        _positive("evaluate.chunk_points", self.chunk_points)
        if not 0.0 < float(self.facing_normal_z) < 1.0:
            raise ValueError(f"evaluate.facing_normal_z must be in (0, 1), got {self.facing_normal_z!r}")
        if not math.isfinite(float(self.ground_height_m)):
            raise ValueError(f"evaluate.ground_height_m must be finite, got {self.ground_height_m!r}")
        if self.distance_cap_m is not None:
            _positive("evaluate.distance_cap_m", self.distance_cap_m)
            if self.distance_cap_m < max(thresholds):
                raise ValueError(
                    f"evaluate.distance_cap_m ({self.distance_cap_m}) must be at least the largest "
                    f"completeness threshold ({max(thresholds)})"
                )
        if self.mesh_input not in MESH_INPUTS:
            raise ValueError(f"evaluate.mesh_input must be one of {MESH_INPUTS}, got {self.mesh_input!r}")

    @classmethod
    def from_config(cls, cfg: Mapping | EvaluationSettings | None) -> EvaluationSettings:
        """Settings from a Mapping/DictConfig (``cfg.evaluate``); None gives the defaults.

        Raises:
            ValueError: an unknown key (a typo) or an invalid value, naming it.
        """
        if cfg is None:
            return cls()
        if isinstance(cfg, cls):
            return cfg
        values = plain(cfg)
        if not isinstance(values, dict):
            raise ValueError(f"evaluate config must be a mapping, got {type(cfg).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown evaluate setting(s) {unknown}; known: {sorted(known)}")
        vis = values.pop("visualise", None) or {}
        vis_known = {f.name for f in fields(VisualisationSettings)}
        vis_unknown = sorted(set(vis) - vis_known)
        if vis_unknown:
            raise ValueError(
                f"unknown evaluate.visualise setting(s) {vis_unknown}; known: {sorted(vis_known)}"
            )
        return cls(**values, visualise=VisualisationSettings(**vis))


def percentile_key(q: float) -> str:
    """Record key of the accuracy at percentile q: 90 -> ``acc90_m``, 99.5 -> ``acc99p5_m``."""
    return f"acc{_compact(q)}_m"


def threshold_key(t_m: float) -> str:
    """Threshold suffix in millimetres, three digits: 0.05 -> ``050``, 0.1 -> ``100``, 0.0075 -> ``007p5``."""
    mm = round(float(t_m) * 1000.0, 6)
    if mm == round(mm):
        return f"{int(round(mm)):03d}"
    whole, frac = f"{mm:.6f}".rstrip("0").split(".")
    return f"{int(whole):03d}p{frac}"


def _compact(value: float) -> str:
    value = round(float(value), 6)
    return str(int(value)) if value == int(value) else f"{value:g}".replace(".", "p")


def _positive(name: str, value) -> None:
    if value is None or not math.isfinite(float(value)) or float(value) <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
