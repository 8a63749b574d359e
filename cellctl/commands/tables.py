"""Plain-text tables for terminals: the per-line verdict table of the paper's Tables 3-5."""

from __future__ import annotations

from typing import Any

_COLUMNS = (
    ("line", "name", "{}"),
    ("SZ mm2", "sz_mm2", "{:.2f}"),
    ("SZ-avg mm", "sz_avg_mm", "{:.4f}"),
    ("Zmax mm", "zmax_mm", "{:.4f}"),
    ("CI", "ci", "{:.4f}"),
    ("SC-avg 1/mm", "sc_avg_per_mm", "{:.5f}"),
    ("Cmax 1/mm", "cmax_per_mm", "{:.5f}"),
    ("length mm", "length_mm", "{:.1f}"),
    ("result", "pass", "{}"),
)


def line_table(report: dict[str, Any]) -> str:
    """The report's lines as an aligned text table, one family after another, verdict last."""
    rows = [[title for title, _, _ in _COLUMNS]]
    for line in report.get("lines", []):
        row = []
        for _, key, fmt in _COLUMNS:
            v = line.get(key)
            if key == "pass":
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
    tol = report.get("tolerances", {})
    lines.append("")
    lines.append(
        f"verdict: {str(report.get('verdict', '?')).upper()}  "
        f"({tol.get('standard', 'tolerances')}: standard {tol.get('deviation_standard_mm')} mm, "
        f"limit {tol.get('deviation_limit_mm')} mm)"
    )
    cov = report.get("coverage") or {}
    if cov.get("partial"):  # a scan cut short: what it did not cover is said, not judged
        missing = ", ".join(
            f"{x.get('name')} ({100 * float(x.get('scanned_fraction') or 0):.0f} % seen)"
            for x in cov.get("lines_not_scanned") or []
        )
        lines.append(f"partial scan, not judged: {missing or 'none'}")
    return "\n".join(lines)
