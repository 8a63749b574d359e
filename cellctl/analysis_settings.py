"""The analysis settings of cell.toml, as the analysis package's own plain settings objects.

`analysis` never imports `cellctl`; this is the one place the configuration is translated.
"""

from __future__ import annotations

from analysis.metrics import Tolerances
from analysis.pipeline import InspectionSettings
from analysis.templates import DetectionLayout
from cellctl.config import AnalysisSection


def inspection_settings(section: AnalysisSection) -> InspectionSettings:
    """InspectionSettings from the ``[analysis]`` section."""
    tol = section.tolerances
    return InspectionSettings(
        layout=DetectionLayout(
            transverse_count=section.transverse_count,
            transverse_spacing_mm=section.transverse_spacing_mm,
            longitudinal_count=section.longitudinal_count,
            longitudinal_spacing_mm=section.longitudinal_spacing_mm,
            diagonals=section.diagonals,
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


def inspection_settings_dict(section: AnalysisSection) -> dict:
    """The same as a JSON-able dict (for jobs sent to analysis workers)."""
    s = inspection_settings(section)
    return {
        "layout": {k: getattr(s.layout, k) for k in ("transverse_count", "transverse_spacing_mm",
                                                      "longitudinal_count", "longitudinal_spacing_mm", "diagonals")},
        "tolerances": {k: getattr(s.tolerances, k) for k in ("standard", "deviation_standard_mm",
                                                              "deviation_limit_mm")},
        "sample_step_mm": s.sample_step_mm,
        "template_fit": s.template_fit,
        "template_fit_compare": s.template_fit_compare,
    }  # fmt: skip
