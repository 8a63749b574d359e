"""The report's CSV: the paper's Tables 3-5, one row per detection line (``report.csv``)."""

from __future__ import annotations

import csv
from pathlib import Path

from analysis.contracts.job import Report

# The paper's Tables 3-5 columns, in order, with the :class:`~analysis.contracts.job.LineReport` field of each.
CSV_COLUMNS: tuple[tuple[str, str], ...] = (
    ("family", "family"),
    ("line", "index"),
    ("name", "name"),
    ("SZ (mm2)", "sz_mm2"),
    ("SZ-average (mm)", "sz_avg_mm"),
    ("Zmax (mm)", "zmax_mm"),
    ("CI", "ci"),
    ("SC-average (mm-1)", "sc_avg_per_mm"),
    ("Cmax (mm-1)", "cmax_per_mm"),
    ("length (mm)", "length_mm"),
    ("pass", "passed"),
)


def write_csv(report: Report, path: str | Path) -> Path:
    """``report.csv``: one row per detection line, the paper's Table 3-5 columns."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow([title for title, _ in CSV_COLUMNS])
        for line in report.lines:
            row = []
            for _, field in CSV_COLUMNS:
                v = getattr(line, field)
                row.append(
                    f"{v:.4f}"
                    if isinstance(v, float)
                    else ("yes" if v is True else "no" if v is False else v)
                )
            w.writerow(row)
    return path
