"""Two reports' line figures, compared: the analysis of one cloud two ways (before and after a change,
streamed and whole) that must give the same figures (issue 42: within 0.005 mm on every line).

Per line (matched by name) every figure in millimetres (``*_mm``: Zmax, Sz average, length, noise,
the line's position) is held to ``tol_mm``; where along the line Zmax lies (``zmax_at_mm``) is
reported apart (a flat maximum's place moves by samples for a difference of nanometres in the
heights), as are the other figures (Sz in mm^2, CI, curvatures), by their largest difference. Also
the verdict, the lines' names and grades. ``scripts/report_figures_diff.py`` is its command line;
tests/analysis/test_long_plate_ci.py holds the streamed analysis of a long plate to it.
"""

from __future__ import annotations

#: figures that are places along a line, not heights: reported, not held to the tolerance
PLACES = frozenset({"zmax_at_mm"})


def _numbers(line: dict) -> dict[str, float]:
    return {k: float(v) for k, v in line.items() if isinstance(v, int | float) and not isinstance(v, bool)}


def compare(before: dict, after: dict, tol_mm: float) -> dict:
    """``before`` and ``after`` are two ``report.json`` objects (a Report's ``model_dump(mode="json")``).
    Returns ``lines``, ``same_lines``, ``same_verdict``, ``same_grades``, ``max_diff_mm`` (the largest
    difference of a millimetre figure, with its line and figure), ``max_diff_other`` (per other
    figure, ``zmax_at_mm`` among them), ``tol_mm`` and ``ok``."""
    a = {ln["name"]: ln for ln in before["lines"]}
    b = {ln["name"]: ln for ln in after["lines"]}
    worst_mm = (0.0, "", "")
    worst_other: dict[str, float] = {}
    for name in sorted(a.keys() & b.keys()):
        na, nb = _numbers(a[name]), _numbers(b[name])
        for key in na.keys() & nb.keys():
            d = abs(na[key] - nb[key])
            if key.endswith("_mm") and key not in PLACES:
                if d > worst_mm[0]:
                    worst_mm = (d, name, key)
            else:
                worst_other[key] = max(worst_other.get(key, 0.0), d)
    same_names = a.keys() == b.keys()
    same_grades = all(
        a[k]["grade"] == b[k]["grade"] and a[k]["pass"] == b[k]["pass"] for k in a.keys() & b.keys()
    )
    same_verdict = before["verdict"] == after["verdict"]
    return {
        "lines": len(a),
        "same_lines": same_names,
        "same_verdict": same_verdict,
        "same_grades": same_grades,
        "max_diff_mm": {"diff": worst_mm[0], "line": worst_mm[1], "figure": worst_mm[2]},
        "max_diff_other": worst_other,
        "tol_mm": tol_mm,
        "ok": same_names and same_verdict and same_grades and worst_mm[0] <= tol_mm,
    }
