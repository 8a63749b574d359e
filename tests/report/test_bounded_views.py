"""The decimated views of a result stay within their budgets whatever the plate's size (issue 42).

The report's top view (a raster with its tolerance contours, embedded as one image), each line's
plot (at most ``LINE_PLOT_MAX_SAMPLES`` samples per curve, the deviation's envelope kept) and the
HMI's map route (a raster of at most ``MAP_MAX_CELLS`` cells, lines of at most ``MAP_LINE_SAMPLES``
samples) on a 12 m plate with noisy data, which matplotlib's own path simplification cannot thin.
"""

from __future__ import annotations

import base64
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from analysis.contracts.results import LineSeries, ResultsArrays
from analysis.report.load import load_results
from analysis.report.plots import (
    LINE_PLOT_MAX_SAMPLES,
    TOP_VIEW_MAX_CELLS,
    _display_cell_mm,
    _draw_line,
    _draw_top_view,
    _svg,
)
from analysis.rework import bounded_cell_mm, grid_deviation
from analysis.templates import DetectionLayout
from tests.support.results_fixture import write_plate_results

LONG_MM = (12_000.0, 3_000.0)
# a few lines, long ones: the longitudinal lines run the plate's 12 m (12 000 samples each)
FEW_LINES = DetectionLayout(
    transverse_offsets_mm=(3000.0, 9000.0), longitudinal_offsets_mm=(1500.0,), diagonals=False
)


def _noisy(n: int, seed: int = 0, gap: tuple[int, int] | None = None) -> LineSeries:
    rng = np.random.default_rng(seed)
    s = np.arange(n, dtype=np.float64)
    design = 40.0 * np.sin(s / 3000.0)
    measured = design - 0.8 * np.sin(s / 700.0) + rng.normal(0.0, 0.05, n)
    if gap is not None:
        measured[gap[0] : gap[1]] = np.nan
    return LineSeries(s, design, measured, design - measured)


def test_decimated_series_keeps_its_ends_envelope_and_gaps_within_the_budget() -> None:
    full = _noisy(12_000, gap=(5000, 5100))
    spike_at = 7777
    full.deviation_mm[spike_at] = 4.2  # a narrow peak: the line's Zmax
    cut = full.decimated(1000)
    assert len(cut.s_mm) <= 1000
    assert cut.s_mm[0] == full.s_mm[0] and cut.s_mm[-1] == full.s_mm[-1]
    assert np.all(np.diff(cut.s_mm) > 0)
    assert np.nanmax(cut.deviation_mm) == np.nanmax(full.deviation_mm) == 4.2
    assert np.nanmin(cut.deviation_mm) == np.nanmin(full.deviation_mm)
    assert spike_at in cut.s_mm
    # the gap stays a gap: a sample without data inside it, the samples beside it with data
    inside = (cut.s_mm >= 5000) & (cut.s_mm < 5100)
    assert np.isnan(cut.measured_z_mm[inside]).any()
    assert np.isfinite(cut.measured_z_mm[cut.s_mm < 5000][-1])
    # the heights are those of the same samples
    k = np.searchsorted(full.s_mm, cut.s_mm)
    np.testing.assert_array_equal(cut.design_z_mm, full.design_z_mm[k])
    # within the budget, the series itself
    small = _noisy(800)
    assert small.decimated(1000) is small


@pytest.mark.parametrize(
    "size_mm", [(1200.0, 800.0), (6000.0, 2000.0), (12_000.0, 3_000.0), (24_000.0, 4_000.0)]
)
def test_bounded_cell_keeps_any_plate_within_the_cell_budget(size_mm: tuple[float, float]) -> None:
    for budget in (20_000, TOP_VIEW_MAX_CELLS):
        c = bounded_cell_mm(np.array(size_mm), budget, 2.0)
        assert np.ceil(size_mm[0] / c) * np.ceil(size_mm[1] / c) <= budget
        assert c >= 2.0
    # a plate whose grid fits keeps the cell asked for
    assert bounded_cell_mm(np.array([1200.0, 800.0]), 1_000_000, 5.0) == 5.0


@pytest.fixture(scope="module")
def long_noisy(tmp_path_factory: pytest.TempPathFactory):
    """A 12 m results directory: 600 000 noisy map points, three lines, the longest 12 000 samples."""
    out = tmp_path_factory.mktemp("long-results")
    write_plate_results(out, *LONG_MM, n_points=20_000, layout=FEW_LINES)
    data = load_results(out)
    rng = np.random.default_rng(1)
    n = 600_000
    xy = rng.uniform([0.0, 0.0], LONG_MM, size=(n, 2))
    # a field that crosses the standard range everywhere: its contours, as paths, would be huge
    dev = 3.5 * np.sin(xy[:, 0] / 90.0) * np.cos(xy[:, 1] / 70.0) + rng.normal(0.0, 0.3, n)
    lines = [
        _noisy(len(series.s_mm), seed=k) if series is not None else None
        for k, series in enumerate(data.lines)
    ]
    ResultsArrays(xy, dev, data.plate_size_mm, lines, data.holes_xy_mm).save(out / "results.npz")
    return out, load_results(out)


def _path_vertices(svg: str) -> list[int]:
    return [len(re.findall(r"[ML] ", d)) for d in re.findall(r'<path[^>]*?\sd="([^"]*)"', svg, re.S)]


_PNG = re.compile(r'xlink:href="data:image/png;base64,([^"]+)"')


def _raster_and_vector(svg: str) -> tuple[list[tuple[int, int]], int]:
    """The embedded images' sizes in pixels, and the bytes of everything else."""
    sizes = [struct.unpack(">II", base64.b64decode(b64)[16:24]) for b64 in _PNG.findall(svg)]  # IHDR
    return sizes, len(_PNG.sub("", svg).encode())


def test_the_top_view_of_a_12_m_plate_is_one_bounded_raster_with_few_vector_paths(long_noisy) -> None:
    _, data = long_noisy
    cell = _display_cell_mm(data)
    field = grid_deviation(data.plate_xy_mm, data.plate_deviation_mm, data.plate_size_mm, cell)
    assert field.mean_mm.size <= TOP_VIEW_MAX_CELLS
    fig = Figure(figsize=(9.0, 5.6))
    _draw_top_view(fig.add_axes((0.08, 0.08, 0.78, 0.9)), data, field, [])
    svg = _svg(fig)
    images, vector_bytes = _raster_and_vector(svg)
    assert len(images) == 1  # the raster and its contours, one picture
    assert images[0][0] <= 900 and images[0][1] <= 560  # no more pixels than the figure's at 100 dpi
    assert max(_path_vertices(svg)) < 100  # outlines, labels, marks; no contour as a path
    assert vector_bytes < 100_000


def test_each_line_plot_of_a_12_m_plate_holds_at_most_its_budget_of_samples(long_noisy) -> None:
    _, data = long_noisy
    assert max(len(s.s_mm) for s in data.lines if s is not None) > 10 * LINE_PLOT_MAX_SAMPLES
    for k in range(len(data.lines)):
        fig = Figure(figsize=(6.4, 3.4))
        ax_z = fig.add_axes((0.1, 0.57, 0.87, 0.34))
        ax_d = fig.add_axes((0.1, 0.13, 0.87, 0.42), sharex=ax_z)
        _draw_line(ax_z, ax_d, data, k)
        curves = [ln for ax in (ax_z, ax_d) for ln in ax.get_lines() if len(ln.get_xdata()) > 2]
        assert len(curves) == 3  # design, measured, deviation
        assert all(len(ln.get_xdata()) <= LINE_PLOT_MAX_SAMPLES for ln in curves)
        # the plot's deviation reaches the line's extremes
        dev = curves[2].get_ydata()
        assert np.nanmax(dev) == np.nanmax(data.lines[k].deviation_mm)
        svg = _svg(fig)
        assert max(_path_vertices(svg)) <= LINE_PLOT_MAX_SAMPLES
        assert len(svg.encode()) < 80_000


def test_the_page_of_a_12_m_plate_stays_within_its_figures_budgets(long_noisy, tmp_path: Path) -> None:
    from analysis.report.write import write_report

    out, _ = long_noisy
    d = tmp_path / "r"
    d.mkdir()
    for name in ("report.json", "results.npz"):
        (d / name).write_bytes((out / name).read_bytes())
    write_report(d)
    html = (d / "report.html").read_text(encoding="utf-8")
    figs = dict(re.findall(r'<figure class="plot" data-plot="(top-view|coverage)"(.*?)</figure>', html, re.S))
    for kind, fig in figs.items():
        images, vector_bytes = _raster_and_vector(fig)
        assert all(w <= 900 and h <= 560 for w, h in images), (kind, images)
        assert vector_bytes < 100_000, kind
    lines = re.findall(r'<figure class="plot" data-plot="line"(.*?)</figure>', html, re.S)
    assert len(lines) == 3 and all(len(f.encode()) < 80_000 for f in lines)
    # off-screen line plots are laid out only when scrolled to
    assert "content-visibility:auto" in html
