"""The report's words and numbers, shared by the HTML page and the PDF: escaping, number formats,
the tolerance classes, the registration's and the coverage's lines.
"""

from __future__ import annotations

import html
import math
from typing import Any

import numpy as np

from analysis.contracts.job import Report, ScanCoverage

FAMILIES: tuple[tuple[str, str], ...] = (
    ("transverse", "Table 3. Transverse detection lines"),
    ("longitudinal", "Table 4. Longitudinal detection lines"),
    ("diagonal", "Table 5. Diagonal detection lines"),
)


def _tolerances(report: Report) -> tuple[float, float, str]:
    tol = report.tolerances
    return float(tol.deviation_standard_mm), float(tol.deviation_limit_mm), tol.standard


def _e(v: Any) -> str:
    return html.escape(str(v), quote=True)


def _f(v: Any, digits: int = 2) -> str:
    return f"{v:.{digits}f}" if isinstance(v, int | float) and not isinstance(v, bool) else "—"


def _zmax_class(z: float, std: float, lim: float) -> str:
    return "ok" if z <= std else "warn" if z <= lim else "bad"


def _sign_text(sign: str) -> str:
    return "plate below template (gap)" if sign == "below" else "plate above template"


def _not_scanned_items(cov: ScanCoverage) -> list[tuple[str, str]]:
    """The coverage table's rows of a partial scan: what it did not cover (none for a whole scan)."""
    if not cov.partial:
        return []
    names = ", ".join(f"{x.name} ({100 * x.scanned_fraction:.0f} % seen)" for x in cov.lines_not_scanned)
    return [
        ("partial scan", "the scan covers only part of the plate: registered on the planned placement"),
        ("lines not scanned (not judged)", _e(names) or "none"),
    ]


def _registration_items(report: Report) -> list[tuple[str, str]]:
    reg = report.registration
    items = [
        ("coarse fit RMS (mm)", _f(reg.coarse_rms_mm, 3)),
        ("ICP RMS (mm)", _f(reg.icp_rms_mm, 3)),
        ("non-penetrating fit RMS (mm)", _f(reg.nonpen_rms_mm, 3)),
        ("penetrating points before the fit", _e(reg.penetration_points_before)),
        ("penetrating points after the fit", _e(reg.penetration_points)),
    ]
    rest = reg.rest_surface
    if rest is not None:
        items.append(
            ("resting surface: patch (mm), points at least", f"{_f(rest.cell_mm, 1)}, {_e(rest.min_points)}")
        )
        items.append(("resting surface: noise sigma, bias bound (mm)", f"{_f(rest.noise_mm, 4)}, {_f(rest.bound_mm, 4)} ({_e(rest.confidence)})"))  # fmt: skip
    T = np.asarray(reg.transform, dtype=float)  # 4 x 4: the schema says so
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(T[:3, :3]) - 1) / 2))))
    items.append(("design → measured: rotation (deg)", f"{angle:.3f}"))
    items.append(("design → measured: translation (mm)", _e(", ".join(f"{v:.2f}" for v in T[:3, 3]))))
    return items
