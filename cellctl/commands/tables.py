"""Plain-text tables for terminals: the per-line verdict table of the paper's Tables 3-5."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from analysis.contracts.job import Report

_COLUMNS = (
    ("line", "name", "{}"),
    ("SZ mm2", "sz_mm2", "{:.2f}"),
    ("SZ-avg mm", "sz_avg_mm", "{:.4f}"),
    ("Zmax mm", "zmax_mm", "{:.4f}"),
    ("CI", "ci", "{:.4f}"),
    ("SC-avg 1/mm", "sc_avg_per_mm", "{:.5f}"),
    ("Cmax 1/mm", "cmax_per_mm", "{:.5f}"),
    ("length mm", "length_mm", "{:.1f}"),
    ("result", "passed", "{}"),
)


def line_table(report: Report) -> str:
    """The report's lines as an aligned text table, one family after another, verdict last."""
    rows = [[title for title, _, _ in _COLUMNS]]
    for line in report.lines:
        row = []
        for _, attr, fmt in _COLUMNS:
            v = getattr(line, attr)
            if attr == "passed":
                row.append("pass" if v else "FAIL")
            elif v is None:
                row.append("-")
            else:
                row.append(fmt.format(v))
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(_COLUMNS))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))
             for r in rows]  # fmt: skip
    lines.insert(1, "  ".join("-" * w for w in widths))
    tol = report.tolerances
    lines.append("")
    lines.append(
        f"verdict: {report.verdict.upper()}  "
        f"({tol.standard}: standard {tol.deviation_standard_mm} mm, limit {tol.deviation_limit_mm} mm)"
    )
    cov = report.coverage
    if cov.partial:  # a scan cut short: what it did not cover is said, not judged
        missing = ", ".join(
            f"{x.name} ({100 * x.scanned_fraction:.0f} % seen)" for x in cov.lines_not_scanned
        )
        lines.append(f"partial scan, not judged: {missing or 'none'}")
    return "\n".join(lines)
