"""Benchmark: how big the result pages are and how long a browser takes to open them (issue 42, item 4).

For the paper's 1200 x 800 mm sail and a long plate (6000 x 2000 mm by default), a results directory
is built (tests/support/results_fixture.py: a formed plate with a known dent and bump, the cell's
detection layout scaled to the plate: 23 lines on the sail, 95 on the 6 m plate, as many map points as
the pipeline stores) or taken from ``--sail-dir`` / ``--long-dir`` (a ``cellctl inspect`` output).
Then, for each plate:

* ``report.html`` is written as the daemon's render child writes it (``write_report``), its bytes
  counted (``html_bytes``, and per figure kind in ``html_figure_bytes``), and opened from disk in
  Chromium (Playwright, Debian's /usr/bin/chromium, headless): ``html_load_s`` is navigation to the
  load event with every figure laid out and a frame painted;
* the HMI's result page (``#result/JOB``) is opened from an HMI server in this process (the tests'
  ``LocalHmi``: no cell) logged in as a viewer: ``hmi_load_s`` is navigation to the page having drawn
  its top view and every line's plot, ``hmi_bytes`` what the page fetched as sent over the wire
  (compressed where the server compresses; ``hmi_route_bytes`` per route: the page's static files,
  the job, the map).

Each load runs ``--repeat`` times in a fresh browser page; the first and the median are printed.
The target (issue 42): both pages of the 6 m plate load in under 2 s. Prints one JSON object.

    python benchmarks/result_pages.py [--long-mm 6000x2000] [--repeat 3] [--sail-dir D] [--long-dir D]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import structlog  # noqa: E402

from analysis.pipeline import MAX_MAP_POINTS  # noqa: E402
from analysis.report.write import write_report  # noqa: E402
from tests.support.chromium import chromium_context  # noqa: E402
from tests.support.hmi_server import USERS, LocalHmi  # noqa: E402
from tests.support.results_fixture import write_plate_results  # noqa: E402

JOB_ID = "20261207T120000-bench042"
# every figure laid out and a frame painted after the load event
_PAINTED_JS = "() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(() => r(true))))"
_HMI_DRAWN_JS = """() => {
  const top = document.getElementById('result-top');
  const rows = document.querySelectorAll('#result-lines tr[data-line]').length;
  return top && top.dataset.regions !== undefined && rows > 0
    && document.querySelectorAll('#result-plots canvas').length === rows;
}"""


def _results(kind: str, out: Path, length_mm: float, width_mm: float, given: str | None) -> Path:
    if given:
        shutil.copytree(
            given, out, ignore=shutil.ignore_patterns("cloud.ply", "report.*"), dirs_exist_ok=True
        )
        # report.json is the results' own (the pipeline's), not a rendered report file
        shutil.copy2(Path(given) / "report.json", out / "report.json")
        return out
    write_plate_results(out, length_mm, width_mm, n_points=MAX_MAP_POINTS, plate_id=f"BENCH-{kind}")
    (out / "cloud.ply").unlink()  # not read by either page; only linked
    return out


def _figure_bytes(html: str) -> dict[str, int]:
    out: dict[str, int] = {}
    for kind, body in re.findall(r'<figure class="plot" data-plot="([a-z-]+)"(.*?)</figure>', html, re.S):
        out[kind] = out.get(kind, 0) + len(body.encode("utf-8"))
    return out


def _load_html(browser: Any, html: Path) -> float:
    page = browser.new_page()
    try:
        t0 = time.perf_counter()
        page.goto(html.as_uri(), wait_until="load", timeout=120_000)
        page.evaluate(_PAINTED_JS)
        return time.perf_counter() - t0
    finally:
        page.close()


def _load_hmi(browser: Any, hmi: LocalHmi) -> tuple[float, dict[str, int]]:
    page = browser.new_page()
    sizes: dict[str, int] = {}

    def on_response(resp: Any) -> None:
        path = resp.url.split("//", 1)[1].split("/", 1)[1] if "//" in resp.url else resp.url
        route = re.sub(r"jobs/[^/]+", "jobs/JOB", "/" + path.split("?")[0].split("#")[0])
        try:
            n = resp.request.sizes()["responseBodySize"]  # as sent: compressed where the server compresses
        except Exception:  # a websocket upgrade or a redirect has no body
            n = 0
        sizes[route] = sizes.get(route, 0) + n

    try:
        page.on("response", on_response)
        t0 = time.perf_counter()
        page.goto(f"{hmi.url}/#result/{JOB_ID}", wait_until="load", timeout=120_000)
        page.wait_for_function(_HMI_DRAWN_JS, timeout=120_000, polling=20)
        page.evaluate(_PAINTED_JS)
        return time.perf_counter() - t0, sizes
    finally:
        page.close()


def _logs_to_stderr() -> None:
    # the benchmark's stdout is its JSON line only (LocalHmi resets structlog to its defaults when it stops)
    structlog.configure(logger_factory=structlog.PrintLoggerFactory(sys.stderr))


def _measure(browser: Any, root: Path, kind: str, results: Path, repeat: int) -> dict[str, Any]:
    _logs_to_stderr()
    t0, c0 = time.perf_counter(), time.process_time()
    write_report(results)
    render = (time.perf_counter() - t0, time.process_time() - c0)
    html_path = results / "report.html"
    html = html_path.read_text(encoding="utf-8")
    report = json.loads((results / "report.json").read_text(encoding="utf-8"))
    html_s = [_load_html(browser, html_path) for _ in range(repeat)]

    hroot = root / f"hmi-{kind}"
    hmi = LocalHmi(hroot)
    hmi.add_done_job(JOB_ID, results, report["plate_id"])
    with hmi:
        user = "vic"
        resp = browser.request.post(hmi.url + "/api/login", data={"user": user, "password": USERS[user][1]})
        assert resp.status == 200, resp.text()
        loads = [_load_hmi(browser, hmi) for _ in range(repeat)]
    hmi_s = [t for t, _ in loads]
    routes = loads[0][1]
    return {
        "plate_size_mm": report["plate_size_mm"],
        "lines": len(report["lines"]),
        "render_s": round(render[0], 2),
        "render_cpu_s": round(render[1], 2),
        "html_bytes": len(html.encode("utf-8")),
        "html_figure_bytes": _figure_bytes(html),
        "html_load_s": round(html_s[0], 3),
        "html_load_median_s": round(statistics.median(html_s), 3),
        "html_load_runs_s": [round(t, 3) for t in html_s],
        "hmi_bytes": sum(routes.values()),
        "hmi_route_bytes": dict(sorted(routes.items(), key=lambda kv: -kv[1])),
        "hmi_load_s": round(hmi_s[0], 3),
        "hmi_load_median_s": round(statistics.median(hmi_s), 3),
        "hmi_load_runs_s": [round(t, 3) for t in hmi_s],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-mm", default="6000x2000", help="the long plate, LENGTHxWIDTH mm")
    ap.add_argument("--repeat", type=int, default=3, help="loads of each page (fresh page each)")
    ap.add_argument("--sail-dir", help="a results directory of the sail (cellctl inspect's --out)")
    ap.add_argument("--long-dir", help="a results directory of a long plate (cellctl inspect's --out)")
    args = ap.parse_args()
    length_mm, width_mm = (float(v) for v in args.long_mm.lower().split("x"))
    _logs_to_stderr()
    out: dict[str, Any] = {"benchmark": "result_pages", "target_load_s": 2.0}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        with chromium_context(root / "chromium-profile", viewport={"width": 1400, "height": 1000}) as browser:
            for kind, size, given in (
                ("sail", (1200.0, 800.0), args.sail_dir),
                ("long", (length_mm, width_mm), args.long_dir),
            ):
                results = _results(kind, root / kind, *size, given)
                out[kind] = {
                    "source": given or "fixture",
                    **_measure(browser, root, kind, results, args.repeat),
                }
    out["load_avg_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
