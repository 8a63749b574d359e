"""The analysis settings: everything the pipeline needs to know besides the data.

A frozen dataclass of frozen dataclasses (:class:`~analysis.templates.DetectionLayout`,
:class:`~analysis.metrics.Tolerances`): plain to build in a notebook, and validated field by field
(unknown fields refused) where it crosses a process boundary inside
:class:`analysis.contracts.job.AnalysisJob`. The cell fills it from ``cell.toml`` (``cellctl.analysis_job``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from analysis.metrics import Tolerances
from analysis.templates import DetectionLayout

__all__ = ["TEMPLATE_FITS", "InspectionSettings", "TemplateFit"]

# "rigid": one template rests on the whole plate (the paper's 3D fit); "per_line": one per detection
# line, on its own section (the paper's 2D case; analysis.template_fit)
TemplateFit = Literal["rigid", "per_line"]
TEMPLATE_FITS: tuple[str, ...] = ("rigid", "per_line")


@dataclass(frozen=True)
class InspectionSettings:
    """Detection lines, tolerances and the sampling of the pipeline (mm; fractions are relative)."""

    layout: DetectionLayout = field(default_factory=DetectionLayout)
    tolerances: Tolerances = field(default_factory=Tolerances)
    sample_step_mm: float = 1.0
    grid_mm: float = 1.0  # finest cell of the reconstructed measured surface
    min_points_per_cell: int = 16
    size_tolerance: float = 0.05  # relative: a design more than 5 % off the plate's size is refused
    design_grid_mm: float = 1.0
    # which face of the plate the design surface is and whether it faces up (analysis.design.moulded);
    # moulded_down: the design is offset by thickness_mm and turned over
    design_side: Literal["moulded_up", "moulded_down"] = "moulded_up"
    thickness_mm: float = 0.0
    # which template judges the plate; compare: the report also carries the other's figures
    template_fit: TemplateFit = "rigid"
    template_fit_compare: bool = False
    # the resting surface's stated bound on its noise bias (analysis.register.rest_surface), its largest patch
    rest_target_sigmas: float = 0.25
    rest_max_cell_mm: float = 20.0

    def __post_init__(self) -> None:
        if self.template_fit not in TEMPLATE_FITS:
            raise ValueError(
                f"template_fit must be one of {', '.join(TEMPLATE_FITS)}, got {self.template_fit!r}"
            )
        if not self.rest_target_sigmas > 0 or not self.rest_max_cell_mm > 0:
            raise ValueError("rest_target_sigmas and rest_max_cell_mm must be positive")
