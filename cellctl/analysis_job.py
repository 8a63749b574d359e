"""A job's analysis parameters from the cell's configuration: the one typed path from ``cell.toml``
to the worker (``[analysis]`` -> :class:`~analysis.contracts.settings.InspectionSettings` inside an
:class:`~analysis.contracts.job.AnalysisJob`, which the JobSpec carries as JSON and the worker validates back).

`analysis` never imports `cellctl`; this is the one place the configuration is translated.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from analysis.contracts.job import AnalysisJob, PlacementFinding
from analysis.contracts.placement import Placement
from analysis.contracts.settings import InspectionSettings
from analysis.design.template_table import TableTemplate
from analysis.metrics import Tolerances
from analysis.templates import DetectionLayout
from cellctl.api.models import AnalysisOptions
from cellctl.config import AnalysisSection, CellConfig

__all__ = ["analysis_job", "inspection_settings"]


def inspection_settings(
    section: AnalysisSection, templates: Sequence[TableTemplate | dict[str, Any]] = ()
) -> InspectionSettings:
    """InspectionSettings from the ``[analysis]`` section, with a template table's rows (the
    trigger's or ``--template-table``) added to its line layout."""
    tol = section.tolerances
    return InspectionSettings(
        layout=DetectionLayout(
            transverse_count=None if section.transverse_count == "auto" else section.transverse_count,
            transverse_spacing_mm=section.transverse_spacing_mm,
            longitudinal_count=None if section.longitudinal_count == "auto" else section.longitudinal_count,
            longitudinal_spacing_mm=section.longitudinal_spacing_mm,
            diagonals=section.diagonals,
            templates=tuple(t if isinstance(t, TableTemplate) else TableTemplate(**t) for t in templates),
        ),
        tolerances=Tolerances(
            standard=tol.standard,
            deviation_standard_mm=tol.deviation_standard_mm,
            deviation_limit_mm=tol.deviation_limit_mm,
        ),
        sample_step_mm=section.sample_step_mm,
        template_fit=section.template_fit,
        template_fit_compare=section.template_fit_compare,
    )


def analysis_job(
    cfg: CellConfig,
    *,
    job_id: str,
    plate_id: str,
    design: str,
    placement: Placement | dict[str, Any] | None,
    out_dir: Path,
    analysis: AnalysisOptions | None = None,
    placement_found: PlacementFinding | None = None,
) -> AnalysisJob:
    """The parameters the daemon sends with a job's cloud: the trigger's design and placement (as
    the job record stores it), the cell's analysis settings with the trigger's per-plate analysis
    options (``analysis``: ``template_table`` rows, ``design_side``, ``thickness_mm``), and the job's results directory.
    ``placement_found``: the job record's ``info.placement_found`` (how the placement was found)."""
    analysis = analysis or AnalysisOptions()
    return AnalysisJob(
        job_id=job_id,
        plate_id=plate_id,
        cell_id=cfg.cell.id,
        design=design,
        placement=None if placement is None else Placement.model_validate(placement),
        placement_found=placement_found,
        settings=dataclasses.replace(
            inspection_settings(cfg.analysis, analysis.template_table),
            design_side=analysis.design_side,
            thickness_mm=analysis.thickness_mm,
        ),
        out_dir=str(out_dir),
    )
