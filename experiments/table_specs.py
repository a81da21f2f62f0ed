"""What the paper's tables hold: each column's metric, its format and direction (``MetricSpec``),
Table I, Table II, the surfaces table and the ablation table, with their captions.
``experiments.tables`` summarises the runs into them and writes them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from evaluate.metrics import SURFACE_CLASSES

# Bibliography keys of the baselines in the paper's LaTeX (Table II cites them beside the name).
METHOD_CITATIONS = {"smith": "Smith2018", "yan": "Yan2021"}

# Longest error text in a table's footnote (the CSVs keep it whole).
NOTE_MAX_CHARS = 240

SUMMARY_COLUMNS = (
    "scene",
    "planner",
    "budget",
    "method",
    "metric",
    "label",
    "mean",
    "std",
    "n",
    "n_runs",
    "n_failed",
    "best",
    "errors",
)


@dataclass(frozen=True)
class MetricSpec:
    """One column of a table.

    Attributes:
        column: field of ``metrics.json``.
        label: Markdown/CSV header.
        latex: LaTeX header.
        decimals: digits after the point when shown (bolding compares the shown values).
        better: ``"lower"``, ``"higher"`` or None (no bolding).
        scale: factor from the stored unit to the shown one (seconds -> minutes: 1/60).
        thousands: show a thousands separator (3,795).
    """

    column: str
    label: str
    latex: str
    decimals: int
    better: str | None = None
    scale: float = 1.0
    thousands: bool = False

    def format(self, value: float) -> str:
        """``value`` (already scaled) as shown in the table."""
        return f"{value:,.{self.decimals}f}" if self.thousands else f"{value:.{self.decimals}f}"


TABLE_I = (
    MetricSpec("acc90_m", "Error 90% (m)", r"\makecell{Error\\90\% (m)}", 3, "lower"),
    MetricSpec("acc95_m", "Error 95% (m)", r"\makecell{Error\\95\% (m)}", 3, "lower"),
    MetricSpec("comp_050", "Comp. 0.050m (%)", r"\makecell{Comp.\\0.050m (\%)}", 2, "higher"),
    MetricSpec("comp_075", "Comp. 0.075m (%)", r"\makecell{Comp.\\0.075m (\%)}", 2, "higher"),
    # Beside the paper's columns: the walls (where planners differ most) and the matcher's ceiling
    # of the same flight (the oracle beside every seed-0 cell), so a reader sees plan from matcher.
    MetricSpec("comp_050_walls", "Walls 0.050m (%)", r"\makecell{Walls\\0.050m (\%)}", 2, "higher"),
    MetricSpec(
        "oracle_comp_050", "Oracle comp. 0.050m (%)", r"\makecell{Oracle comp.\\0.050m (\%)}", 2, "higher"
    ),
)
TABLE_II = (
    MetricSpec("n_images", "Number of images", "Number of Images", 0, thousands=True),
    # drone/model.py with conf/drone: all flights, battery swaps excluded
    MetricSpec(
        "flight_time_s", "Flight time (minutes)", r"\makecell{Flight\\time (minutes)}", 1, scale=1.0 / 60.0
    ),
    MetricSpec("n_batteries", "Batteries", "Batteries", 0),
    MetricSpec(
        "align_time_s",
        "Alignment time (minutes)",
        r"\makecell{Alignment\\time (minutes)}",
        2,
        scale=1.0 / 60.0,
    ),
    # CPU time (process + children) is what a shared machine cannot blur; wall time moves with load.
    MetricSpec(
        "align_cpu_s",
        "Alignment CPU (minutes)",
        r"\makecell{Alignment\\CPU (minutes)}",
        2,
        scale=1.0 / 60.0,
    ),
    MetricSpec(
        "dense_time_s", "Dense time (minutes)", r"\makecell{Dense\\time (minutes)}", 2, scale=1.0 / 60.0
    ),
    MetricSpec("dense_cpu_s", "Dense CPU (minutes)", r"\makecell{Dense\\CPU (minutes)}", 2, scale=1.0 / 60.0),
)
TABLE_SURFACES = tuple(
    MetricSpec(
        f"comp_050_{name}",
        f"{name.capitalize()} 0.050m (%)",
        rf"\makecell{{{name.capitalize()}\\0.050m (\%)}}",
        2,
        "higher",
    )
    for name in SURFACE_CLASSES
)
# The ablation of ours (experiment=ablation): its variants are the planners that preset sweeps
# (conf/planner/ours_<what they undo>.yaml), read from it so that the two never disagree; other
# planners named ours_* (ours_plus and its time weights) are methods of their own, not variants.
ABLATION_PRESET = Path(__file__).resolve().parents[1] / "conf" / "experiment" / "ablation.yaml"


def ablation_planners() -> tuple[str, ...]:
    """The planners the ablation preset sweeps (``ours`` and its variants), in its order."""
    swept = OmegaConf.load(ABLATION_PRESET).hydra.sweeper.params.planner
    return tuple(name.strip() for name in str(swept).split(","))


TABLE_ABLATION = (
    MetricSpec("n_images", "Images", "Images", 0, thousands=True),
    MetricSpec("registered_fraction", "Registered", "Registered", 3, "higher"),
    MetricSpec("acc90_m", "Error 90% (m)", r"\makecell{Error\\90\% (m)}", 3, "lower"),
    MetricSpec("comp_050", "Comp. 0.050m (%)", r"\makecell{Comp.\\0.050m (\%)}", 2, "higher"),
    MetricSpec("comp_050_walls", "Walls 0.050m (%)", r"\makecell{Walls\\0.050m (\%)}", 2, "higher"),
    MetricSpec(
        "predicted_well_observed_walls_pct",
        "Walls planned well (%)",
        r"\makecell{Walls planned\\well (\%)}",
        1,
        "higher",
    ),
)
TABLE_ABLATION_CAPTION = (
    "Ablation of ours: each variant undoes one choice (conf/planner/ours_*.yaml). Walls planned well: "
    "proxy wall samples with >= 3 planned views within 1.3 d_t and 60 deg of the normal."
)
TABLE_I_CAPTION = "Reconstruction accuracy and completeness results for the three scenes."
TABLE_II_CAPTION = (
    "Number of input images, alignment (SfM) and dense time for each flight path method; CPU time "
    "is process + children on the study machine."
)
TABLE_SURFACES_CAPTION = (
    "Completeness at 0.050 m per kind of ground-truth surface (evaluate.metrics.surface_classes)."
)
