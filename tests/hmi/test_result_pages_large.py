"""A 6000 x 2000 mm plate's result pages in a real browser: they load and show their figures, each
within its budget (issue 42, item 4).

Playwright drives Debian's Chromium (as test_hmi_screens.py does) against an HMI server in this
process with a fake link (tests/support/hmi_server.py), serving a done job whose results are those
of a formed 6 m plate (tests/support/results_fixture.py: 300 000 map points, the cell's 95 lines),
and opens the plate's report.html from disk. How fast they load is a benchmark's figure
(benchmarks/result_pages.py), not a test's.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from analysis.contracts.results import read_results_arrays
from analysis.report.write import write_report
from analysis.templates import DetectionLayout
from cellctl.hmi.server import MAP_LINE_SAMPLES, MAP_MAX_CELLS
from tests.support.hmi_server import USERS, LocalHmi
from tests.support.results_fixture import SyntheticResults, write_plate_results

pytestmark = [pytest.mark.process, pytest.mark.timeout(300)]  # Chromium is a process of its own

JOB = "20261207T120000-long0001"
SIZE_MM = (6000.0, 2000.0)
_DRAWN_JS = """() => {
  const top = document.getElementById('result-top');
  const rows = document.querySelectorAll('#result-lines tr[data-line]').length;
  return top.dataset.regions !== undefined && rows > 0
    && document.querySelectorAll('#result-plots canvas[data-samples]').length === rows;
}"""
# the share of the top view's plate rectangle painted in a band colour (not the page's ground)
_TOP_PAINTED_JS = """() => {
  const c = document.getElementById('result-top'), g = c.getContext('2d');
  const d = g.getImageData(0, 0, c.width, c.height).data;
  let band = 0;
  for (let i = 0; i < d.length; i += 4) {
    const [r, gr, b] = [d[i], d[i + 1], d[i + 2]];
    if ((r === 40 && gr === 170 && b === 70) || (r === 230 && gr === 170 && b === 30) || (r === 220 && gr === 50 && b === 50)) band++;
  }
  return band / (c.width * c.height);
}"""


@pytest.fixture(scope="module")
def long_results(tmp_path_factory: pytest.TempPathFactory) -> SyntheticResults:
    return write_plate_results(tmp_path_factory.mktemp("long-results"), *SIZE_MM, plate_id="P-LONG-6M")


@pytest.fixture(scope="module")
def hmi(tmp_path_factory, long_results: SyntheticResults) -> Iterator[LocalHmi]:
    h = LocalHmi(tmp_path_factory.mktemp("hmi-long"))
    h.add_done_job(JOB, long_results.results_dir, long_results.report.plate_id)
    with h:
        yield h


def test_the_map_route_of_a_6_m_plate_stays_within_its_budget(page, hmi, long_results) -> None:
    r = page.request.post(hmi.url + "/api/login", data={"user": "vic", "password": USERS["vic"][1]})
    assert r.status == 200
    resp = page.request.get(f"{hmi.url}/api/jobs/{JOB}/map")
    assert resp.status == 200
    m = json.loads(resp.body())
    assert m["nx"] * m["ny"] == len(m["deviation_mm"]) <= MAP_MAX_CELLS
    assert m["nx"] * m["cell_mm"] >= SIZE_MM[0] and m["ny"] * m["cell_mm"] >= SIZE_MM[1]
    lines = long_results.report.lines
    assert len(m["lines"]) == len(lines) == 95
    assert all(len(ln["s_mm"]) == len(ln["deviation_mm"]) <= MAP_LINE_SAMPLES for ln in m["lines"])
    # the stored sections are ~2000 samples, the longest 6000: each plot keeps its line's extremes
    stored = read_results_arrays(long_results.results_dir).lines
    for full, plotted in zip(stored, m["lines"], strict=True):
        dev = np.array([np.nan if v is None else v for v in plotted["deviation_mm"]])
        assert len(full.s_mm) > len(dev)
        assert np.nanmax(dev) == pytest.approx(np.nanmax(full.deviation_mm), abs=1e-3)
        assert np.nanmin(dev) == pytest.approx(np.nanmin(full.deviation_mm), abs=1e-3)
    # the dent's cells are in the raster, where the dent is (d = design - formed > 0 below the template)
    grid = np.array([np.nan if v is None else v for v in m["deviation_mm"]]).reshape(m["nx"], m["ny"])
    i, j = (int(v // m["cell_mm"]) for v in long_results.dent_xy_mm)
    assert grid[i, j] > 0.5 * abs(long_results.dent_depth_mm)


def test_the_result_page_of_a_6_m_plate_loads_and_shows_its_figures(
    page, hmi, long_results, tmp_path
) -> None:
    r = page.request.post(hmi.url + "/api/login", data={"user": "vic", "password": USERS["vic"][1]})
    assert r.status == 200
    page.goto(f"{hmi.url}/#result/{JOB}")
    page.wait_for_function(_DRAWN_JS, timeout=60_000)
    n_lines = len(long_results.report.lines)
    assert page.locator("#result-lines tr[data-line]").count() == n_lines
    top = page.locator("#result-top")
    cells = int(top.get_attribute("data-cells"))
    assert 0.9 * MAP_MAX_CELLS < cells <= MAP_MAX_CELLS  # the plate, all but the unscanned patch
    assert top.get_attribute("data-lines").count(",") == n_lines - 1  # every line drawn and named
    # the raster covers the plate's rectangle: a 3 : 1 plate fills about a third of the canvas
    assert page.evaluate(_TOP_PAINTED_JS) > 0.2
    assert 0.9 * MAP_MAX_CELLS < page.evaluate("S.res3d.count()") <= MAP_MAX_CELLS
    samples = page.eval_on_selector_all("#result-plots canvas", "cs => cs.map((c) => +c.dataset.samples)")
    assert len(samples) == n_lines and max(samples) <= MAP_LINE_SAMPLES and min(samples) > 100
    page.locator("#result-views").screenshot(path=str(tmp_path / "hmi-result-6m.png"))


# the report: a few lines, so that the session renders it (PDF too) in seconds; the lines run the 6 m
FEW_LINES = DetectionLayout(
    transverse_offsets_mm=(1500.0, 4500.0), longitudinal_offsets_mm=(500.0, 1000.0), diagonals=True
)


def test_the_report_of_a_6_m_plate_opens_and_shows_every_figure_when_scrolled_to(
    page, tmp_path: Path
) -> None:
    out = tmp_path / "results"
    write_plate_results(out, *SIZE_MM, layout=FEW_LINES)
    write_report(out)
    page.goto((out / "report.html").as_uri(), wait_until="load")
    figs = page.locator("figure.plot")
    kinds = figs.evaluate_all("fs => fs.map((f) => f.dataset.plot)")
    assert kinds.count("top-view") == 1 and kinds.count("coverage") == 1 and kinds.count("line") == 6
    for k in range(figs.count()):
        fig = figs.nth(k)
        fig.scroll_into_view_if_needed()
        png = tmp_path / f"figure{k}.png"
        fig.screenshot(path=str(png))
        rgb = imread(png)[..., :3]
        h, w = rgb.shape[:2]
        assert w > 400 and h > 150, (kinds[k], rgb.shape)
        ink = np.count_nonzero(rgb.sum(axis=2) < 2.4)  # darker than near-white: drawn, not a blank box
        assert ink > 0.01 * w * h, (kinds[k], ink, w * h)
