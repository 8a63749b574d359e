"""A complete ``report.json`` made from the few figures a test cares about.

The readers of a job directory (the plate history, the HMI, the report renderer) load ``report.json``
as an :class:`analysis.contracts.job.Report`, which refuses a document missing a field the schema requires. A
test that only cares about a plate's verdict and its lines' Zmax gives those; :func:`report_dict`
fills in the rest with plain, valid values (a 400 x 300 mm plate registered in place).
"""

from __future__ import annotations

import json
from typing import Any

from analysis.contracts.job import Report

_LINE_DEFAULTS: dict[str, Any] = {
    "sz_mm2": 0.0,
    "zmax_at_mm": 0.0,
    "ci": 0.0,
    "sc_avg_per_mm": 0.0,
    "cmax_per_mm": 0.0,
    "length_mm": 300.0,
}


def report_dict(lines: list[dict[str, Any]], verdict: str | None = None, **fields: Any) -> dict[str, Any]:
    """A valid report's JSON object: ``lines`` (each at least family, index, zmax_mm, sz_avg_mm,
    pass; the other figures default), ``verdict`` (default: pass when every line passes), and any
    top-level ``fields`` replaced (``plate_id``, ``tolerances``, ``plate_size_mm``, ...)."""
    if verdict is None:
        verdict = "pass" if all(ln["pass"] for ln in lines) else "fail"
    doc: dict[str, Any] = {
        "plate_id": "P1",
        "verdict": verdict,
        "registration": {
            "coarse_rms_mm": 0.1, "icp_rms_mm": 0.1, "nonpen_rms_mm": 0.1, "penetration_points": 0,
            "penetration_points_before": 0, "surface_points": 1000, "surface_cell_mm": 2.0,
            "raw_points_below_4sigma": 0, "corner_shift": 0,
            "transform": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        },
        "corners_mm": [[0.0, 0.0, 0.0], [400.0, 0.0, 0.0], [400.0, 300.0, 0.0], [0.0, 300.0, 0.0]],
        "plate_size_mm": [400.0, 300.0],
        "lines": [{**_LINE_DEFAULTS, **ln} for ln in lines],
        "tolerances": {"standard": "CSQS 2016, doubly curved plate", "deviation_standard_mm": 2.0,
                       "deviation_limit_mm": 3.0, "judge_at": "limit", "cmax_limit_per_mm": None},
        "coverage": {"fraction": 1.0, "holes_mm2": 0.0},
        "surface": {"points": 1000, "noise_sigma_mm": 0.05, "max_deviation_mm": None},
        "inputs": {"points": 1000, "design": "p.ply"},
    }  # fmt: skip
    doc.update(fields)
    Report.model_validate(doc)  # a helper that wrote an invalid report would test nothing
    return doc


def report_json(lines: list[dict[str, Any]], verdict: str | None = None, **fields: Any) -> str:
    """:func:`report_dict` as the text of a ``report.json``."""
    return json.dumps(report_dict(lines, verdict, **fields))
