"""Every file of the report written from a results directory: :func:`write_report` (CSV, HTML, PDF)."""

from __future__ import annotations

import time
from pathlib import Path

import structlog
from matplotlib.figure import Figure

from analysis.report.csv_table import write_csv
from analysis.report.html_page import render_html
from analysis.report.load import PreviousRound, ResultsData, load_results
from analysis.report.pdf import render_pdf
from analysis.report.plots import (
    _colorbar,
    _display_cell_mm,
    _draw_coverage,
    _draw_line,
    _draw_top_view,
    _svg,
)
from analysis.report.text import _tolerances
from analysis.rework import find_rework_regions, grid_deviation

log = structlog.get_logger(__name__)


def _rework_cell_mm(data: ResultsData) -> float:
    return max(5.0, _display_cell_mm(data))


def write_report(results_dir: str | Path, previous: PreviousRound | None = None) -> list[Path]:
    """Make ``report.csv``, ``report.html`` and ``report.pdf`` in ``results_dir`` from its stored results.

    ``previous``: the plate's previous round, shown beside this round's figures per line (the caller
    finds it: ``cellctl report`` from the plate history); None for a first round.

    Returns the paths written. Raises :class:`ReportError` if the directory's results are
    incomplete or malformed (nothing is written then).
    """
    t0 = time.perf_counter()
    data = load_results(results_dir)
    d = data.results_dir
    std, lim, _ = _tolerances(data.report)
    display = grid_deviation(
        data.plate_xy_mm, data.plate_deviation_mm, data.plate_size_mm, _display_cell_mm(data)
    )
    rework_field = grid_deviation(
        data.plate_xy_mm, data.plate_deviation_mm, data.plate_size_mm, _rework_cell_mm(data)
    )
    regions = find_rework_regions(rework_field, std, lim)

    # Fixed axes positions, not constrained layout: layout solving redraws every tick label several
    # times and was a third of the render time.
    svgs: dict[str, str] = {}
    fig = Figure(figsize=(9.0, 5.6))
    im = _draw_top_view(fig.add_axes((0.08, 0.08, 0.78, 0.9)), data, display, regions)
    _colorbar(fig, im, cax=fig.add_axes((0.88, 0.2, 0.018, 0.62)))
    svgs["top"] = _svg(fig)
    fig = Figure(figsize=(7.0, 4.4))
    _draw_coverage(fig.add_axes((0.1, 0.12, 0.86, 0.8)), data)
    svgs["coverage"] = _svg(fig)
    for k in range(len(data.report.lines)):
        fig = Figure(figsize=(6.4, 3.4))
        ax_z = fig.add_axes((0.1, 0.57, 0.87, 0.34))
        ax_d = fig.add_axes((0.1, 0.13, 0.87, 0.42), sharex=ax_z)
        _draw_line(ax_z, ax_d, data, k)
        ax_z.tick_params(labelbottom=False)
        svgs[f"line{k}"] = _svg(fig)

    written = [write_csv(data.report, d / "report.csv")]
    html_path = d / "report.html"
    tmp = d / "report.html.tmp"
    tmp.write_text(render_html(data, regions, svgs, previous), encoding="utf-8")
    tmp.replace(html_path)
    written.append(html_path)
    pdf_path = d / "report.pdf"
    tmp = d / "report.pdf.tmp"
    pages = render_pdf(data, regions, display, tmp, previous)
    tmp.replace(pdf_path)
    written.append(pdf_path)
    log.info(
        "report_written",
        dir=str(d),
        lines=len(data.report.lines),
        regions=len(regions),
        pdf_pages=pages,
        seconds=round(time.perf_counter() - t0, 3),
    )
    return written
