"""Benchmark: render a full inspection report (23 detection lines, 300,000 plate points).

Builds a results directory for the paper's 1200 x 800 mm sail plate with a known dent and bump
(tests/support/results_fixture.py: heights from analysis.design.plates, figures from analysis.metrics),
then times ``analysis.report.write.write_report`` (CSV + self-contained HTML + PDF) on it.
Prints one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import structlog  # noqa: E402

from analysis.report.write import write_report  # noqa: E402
from tests.support.results_fixture import write_synthetic_results  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=2, help="renders timed; the best is reported")
    args = ap.parse_args()
    # the benchmark's stdout is its JSON line only
    structlog.configure(logger_factory=structlog.PrintLoggerFactory(sys.stderr))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        truth = write_synthetic_results(out, n_points=args.points)
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            c0 = time.process_time()
            written = write_report(out)
            times.append((time.perf_counter() - t0, time.process_time() - c0))
        sizes = {p.name: p.stat().st_size for p in written}
        pdf_pages = len(re.findall(rb"/Type\s*/Page[^s]", (out / "report.pdf").read_bytes()))
    best_wall, best_cpu = min(times)
    print(
        json.dumps(
            {
                "benchmark": "report",
                "lines": len(truth.report.lines),
                "points": args.points,
                "render_wall_s": round(best_wall, 3),
                "render_cpu_s": round(best_cpu, 3),
                "runs_wall_s": [round(w, 3) for w, _ in times],
                "html_bytes": sizes["report.html"],
                "pdf_bytes": sizes["report.pdf"],
                "csv_bytes": sizes["report.csv"],
                "pdf_pages": pdf_pages,
            }
        )
    )


if __name__ == "__main__":
    main()
