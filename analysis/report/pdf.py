"""``report.pdf``: the HTML page's content on A4 pages for the QA archive (matplotlib's PdfPages)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from analysis.contracts.job import Report
from analysis.report.csv_table import CSV_COLUMNS
from analysis.report.load import PreviousRound, ResultsData, previous_by_line
from analysis.report.plots import _COLOURS, _colorbar, _draw_coverage, _draw_line, _draw_top_view
from analysis.report.text import (
    FAMILIES,
    _f,
    _not_scanned_items,
    _registration_items,
    _sign_text,
    _tolerances,
    _zmax_class,
)
from analysis.rework import GriddedField, ReworkRegion

_LINES_PER_PDF_PAGE = 3
_TABLE_ROWS_PER_PDF_PAGE = 34
_A4_PORTRAIT_IN = (8.27, 11.69)


def _pdf_text_page(fig: Figure, y: float, lines: list[tuple[str, dict]]) -> float:
    for text, kw in lines:
        size = kw.pop("size", 9)
        fig.text(0.07, y, text, fontsize=size, va="top", **kw)
        y -= (size + 5) / 72 / _A4_PORTRAIT_IN[1]
    return y


def _pdf_table(
    ax: Any, header: list[str], rows: list[list[str]], colours: list[list[str]], widths: list[float]
) -> None:
    ax.axis("off")
    if not rows:
        return
    t = ax.table(
        cellText=rows,
        colLabels=header,
        cellColours=colours,
        colWidths=widths,
        loc="upper center",
        cellLoc="center",
    )
    t.auto_set_font_size(False)
    t.set_fontsize(6.5)
    t.scale(1.0, 1.25)


def _pdf_previous_pages(pdf: PdfPages, report: Report, previous: PreviousRound) -> int:
    """The previous round's table in the PDF (the HTML's "Previous round" section); returns the pages."""
    n = previous.round
    header = [
        "line",
        f"Zmax r{n + 1}",
        f"SZ-avg r{n + 1}",
        f"verdict r{n + 1}",
        f"Zmax r{n}",
        f"SZ-avg r{n}",
        f"verdict r{n}",
    ]
    body, colours = [], []
    for ln, prev in previous_by_line(report, previous):
        body.append(
            [
                ln.name,
                _f(ln.zmax_mm, 2),
                _f(ln.sz_avg_mm, 2),
                "pass" if ln.passed else "FAIL",
                *(
                    ["—", "—", "—"]
                    if prev is None
                    else [_f(prev.zmax_mm, 2), _f(prev.sz_avg_mm, 2), "pass" if prev.passed else "FAIL"]
                ),
            ]
        )
        row_c = ["white"] * len(header)
        row_c[3] = "#d7f0dc" if ln.passed else "#fbd5d5"
        if prev is not None:
            row_c[6] = "#d7f0dc" if prev.passed else "#fbd5d5"
        colours.append(row_c)
    pages = 0
    for start in range(0, max(len(body), 1), _TABLE_ROWS_PER_PDF_PAGE):
        fig = Figure(figsize=_A4_PORTRAIT_IN)
        _pdf_text_page(
            fig,
            0.96,
            [
                ("Previous round", {"size": 14, "fontweight": "bold"}),
                (
                    f"Round {n + 1} of plate {report.plate_id}; round {n}: job {previous.job_id},"
                    f" {previous.created_utc}, verdict {previous.verdict}",
                    {},
                ),
            ],
        )
        _pdf_table(
            fig.add_axes((0.04, 0.05, 0.92, 0.83)),
            header,
            body[start : start + _TABLE_ROWS_PER_PDF_PAGE],
            colours[start : start + _TABLE_ROWS_PER_PDF_PAGE],
            [0.16, 0.14, 0.14, 0.14, 0.14, 0.14, 0.14],
        )
        pdf.savefig(fig)
        pages += 1
    return pages


def render_pdf(
    data: ResultsData,
    regions: list[ReworkRegion],
    field: GriddedField,
    path: Path,
    previous: PreviousRound | None = None,
) -> int:
    """``report.pdf`` (A4 portrait): summary and map, rework and coverage, tables, the previous round
    (when there is one), line plots.

    Returns the number of pages.
    """
    rep = data.report
    std, lim, standard = _tolerances(rep)
    lines = rep.lines
    pages = 0
    with (
        matplotlib.rc_context({"pdf.fonttype": 3}),
        PdfPages(path, metadata={"Title": "Inspection report"}) as pdf,
    ):
        # 1: summary and the deviation map
        fig = Figure(figsize=_A4_PORTRAIT_IN)
        verdict = rep.verdict
        y = _pdf_text_page(
            fig,
            0.96,
            [
                (f"Inspection report — plate {rep.plate_id}", {"size": 16, "fontweight": "bold"}),
                (
                    f"Verdict: {verdict.upper()}",
                    {
                        "size": 20,
                        "fontweight": "bold",
                        "color": _COLOURS.get(verdict, _COLOURS["warn"]),
                    },
                ),
                (
                    f"cell {rep.cell_id}   job {rep.job_id}   {rep.created_utc}",
                    {},
                ),
                (f"Standard: {standard or '—'} (standard ±{std:g} mm, limit ±{lim:g} mm)", {}),
                (
                    f"Lines within tolerance: {sum(1 for ln in lines if ln.passed)} of {len(lines)};"
                    f" failed: {', '.join(ln.name for ln in lines if not ln.passed) or 'none'};"
                    f" regions to rework: {len(regions)}",
                    {},
                ),
                *[(f"Registration, {k}: {v}", {"size": 7}) for k, v in _registration_items(rep)],
                (
                    f"Coverage: seen {100 * rep.coverage.fraction:.1f} %"
                    + f", unseen area {_f(rep.coverage.holes_mm2, 0)} mm²"
                    + "".join(f"; {k}: {v}" for k, v in _not_scanned_items(rep.coverage)),
                    {},
                ),
                (
                    "Timings: " + ", ".join(f"{k} {_f(v, 2)} s" for k, v in rep.timings_s.items()),
                    {"size": 7},
                ),
            ],
        )
        top = y - 0.04
        ax = fig.add_axes((0.09, 0.06, 0.74, top - 0.06))
        ax.set_anchor("N")  # the map's aspect is fixed: keep it under the text, not mid-page
        im = _draw_top_view(ax, data, field, regions)
        _colorbar(fig, im, cax=fig.add_axes((0.86, top - 0.32, 0.02, 0.3)))
        ax.set_title("Deviation map, top view (from the reference corner)", fontsize=9, loc="left")
        pdf.savefig(fig)
        pages += 1
        # 2: where to rework and coverage
        fig = Figure(figsize=_A4_PORTRAIT_IN)
        _pdf_text_page(
            fig,
            0.96,
            [
                ("Where to rework", {"size": 14, "fontweight": "bold"}),
                (f"Regions more than {std:g} mm off the template; mm from the reference corner.", {}),
            ],
        )
        header = [
            "region",
            "where the plate is",
            "peak d",
            "mean d",
            "area mm²",
            "size x×y mm",
            "centre x, y",
            "beyond limit",
        ]
        rows = [
            [
                r.label,
                _sign_text(r.sign),
                f"{r.peak_mm:+.2f}",
                f"{r.mean_mm:+.2f}",
                f"{r.area_mm2:.0f}",
                f"{r.bbox_mm[2] - r.bbox_mm[0]:.0f}×{r.bbox_mm[3] - r.bbox_mm[1]:.0f}",
                f"{r.centre_xy_mm[0]:.0f}, {r.centre_xy_mm[1]:.0f}",
                "yes" if r.beyond_limit else "no",
            ]
            for r in regions[:30]
        ]
        colours = [["#fbd5d5" if r.beyond_limit else "#fff1cc"] * len(header) for r in regions[:30]]
        if rows:
            _pdf_table(
                fig.add_axes((0.05, 0.5, 0.9, 0.38)),
                header,
                rows,
                colours,
                [0.07, 0.25, 0.09, 0.09, 0.1, 0.13, 0.13, 0.1],
            )
        else:
            fig.text(0.07, 0.86, "No region lies beyond the standard range.", fontsize=9)
        ax = fig.add_axes((0.09, 0.07, 0.84, 0.36))
        _draw_coverage(ax, data)
        fig.text(
            0.07, 0.45, "Scan coverage (grey seen, red unseen 5 mm cells)", fontsize=11, fontweight="bold"
        )
        pdf.savefig(fig)
        pages += 1
        # 3..: the paper's tables
        header = ["line", *[t for t, _ in CSV_COLUMNS[3:10]], "verdict"]
        body, colours = [], []
        for fam, title in FAMILIES:
            fam_lines = [ln for ln in lines if ln.family == fam]
            if not fam_lines:
                continue
            body.append([title.split(" detection")[0], *[""] * (len(header) - 1)])
            colours.append(["#eeeeee"] * len(header))
            for ln in fam_lines:
                body.append(
                    [
                        ln.name,
                        *[_f(getattr(ln, key), 4) for _, key in CSV_COLUMNS[3:9]],
                        _f(ln.length_mm, 1),
                        "pass" if ln.passed else "FAIL",
                    ]
                )
                z = _zmax_class(float(ln.zmax_mm), std, lim)
                row_c = ["white"] * len(header)
                row_c[3] = {"ok": "#eaf6ec", "warn": "#fff1cc", "bad": "#fbd5d5"}[z]
                row_c[-1] = "#d7f0dc" if ln.passed else "#fbd5d5"
                colours.append(row_c)
        for start in range(0, max(len(body), 1), _TABLE_ROWS_PER_PDF_PAGE):
            fig = Figure(figsize=_A4_PORTRAIT_IN)
            _pdf_text_page(fig, 0.96, [("Detection lines (Tables 3–5)", {"size": 14, "fontweight": "bold"})])
            _pdf_table(
                fig.add_axes((0.04, 0.05, 0.92, 0.86)),
                header,
                body[start : start + _TABLE_ROWS_PER_PDF_PAGE],
                colours[start : start + _TABLE_ROWS_PER_PDF_PAGE],
                [0.15, 0.11, 0.12, 0.1, 0.08, 0.12, 0.1, 0.1, 0.08],
            )
            pdf.savefig(fig)
            pages += 1
        if previous is not None:
            pages += _pdf_previous_pages(pdf, rep, previous)
        # then the line plots, three per page
        for start in range(0, len(lines), _LINES_PER_PDF_PAGE):
            fig = Figure(figsize=_A4_PORTRAIT_IN)
            fig.text(
                0.07,
                0.975,
                "Detection lines: sections and deviation",
                fontsize=11,
                fontweight="bold",
                va="top",
            )
            for j, k in enumerate(range(start, min(start + _LINES_PER_PDF_PAGE, len(lines)))):
                top = 0.93 - j * 0.31
                ax_z = fig.add_axes((0.1, top - 0.12, 0.84, 0.1))
                ax_d = fig.add_axes((0.1, top - 0.25, 0.84, 0.12), sharex=ax_z)
                _draw_line(ax_z, ax_d, data, k)
                ax_z.tick_params(labelbottom=False)
            pdf.savefig(fig)
            pages += 1
    return pages
