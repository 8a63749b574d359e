"""Two results directories' (or report.json files') line figures, compared: the analysis of one cloud
before and after a change that must not change the figures (issue 42: within 0.005 mm on every line).

Per line (matched by name) every figure in millimetres (``*_mm``: Zmax, Sz average, length, noise,
the line's position) is held to ``--tol-mm``; where along the line Zmax lies (``zmax_at_mm``) is
reported apart (a flat maximum's place moves by samples for a difference of nanometres in the
heights), as are the other figures (Sz in mm^2, CI, curvatures), by their largest difference. Also the verdict, the lines' names and grades. Prints one JSON
object: ``max_diff_mm`` (the largest difference of a millimetre figure, with its line and figure),
``max_diff_other``, ``lines``, ``same_verdict``, ``same_grades``, ``ok``; exit 1 when not ok.

The comparison is :func:`analysis.report.figures_diff.compare`.

Run: ``.venv/bin/python scripts/report_figures_diff.py BEFORE_DIR AFTER_DIR [--tol-mm 0.005]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from analysis.report.figures_diff import compare


def _report(path: str) -> dict:
    p = Path(path)
    return json.loads((p / "report.json" if p.is_dir() else p).read_text())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("before", help="a results directory or its report.json")
    p.add_argument("after", help="a results directory or its report.json")
    p.add_argument("--tol-mm", type=float, default=0.005)
    args = p.parse_args()
    out = compare(_report(args.before), _report(args.after), args.tol_mm)
    print(json.dumps(out))
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
