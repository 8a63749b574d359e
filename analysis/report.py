"""The inspection report's files, made from a results directory.

A results directory (one per job or per ``cellctl inspect --out DIR``) holds ``report.json`` (a
:class:`~analysis.contracts.job.Report`), ``results.npz`` (arrays for plots) and ``cloud.ply``, both read
through :mod:`analysis.contracts.results`. This module turns them into what people read:

* ``report.html``: one self-contained page (inline CSS, inline SVG plots with their raster parts
  as data: URLs, no script, no web font, nothing fetched), so it opens from a USB stick;
* ``report.pdf``: the same content on A4 pages for the QA archive (matplotlib's PdfPages);
* ``report.csv``: the paper's Tables 3-5, one row per detection line.

Everything is computed from the stored results, so ``cellctl report DIR`` regenerates the same
report at any time. Plots use matplotlib's object API (no pyplot, no global figure state), which
keeps the functions safe to call from a worker thread.

Plate frame: x along the plate's length and y along its width, in mm from the reference corner.
Deviation: ``d = z_design - z_measured`` (mm); d > 0 means the plate lies below the template.
"""

from __future__ import annotations

import csv
import html
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import structlog
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

from analysis.contracts.job import LineReport, Report, ScanCoverage
from analysis.contracts.results import LineSeries, ReportError, read_report, read_results_arrays
from analysis.rework import GriddedField, ReworkRegion, find_rework_regions, grid_deviation

log = structlog.get_logger(__name__)

__all__ = [
    "CSV_COLUMNS",
    "LineSeries",
    "PreviousLine",
    "PreviousRound",
    "ReportError",
    "ResultsData",
    "load_results",
    "previous_by_line",
    "render_html",
    "render_pdf",
    "write_csv",
    "write_report",
]

# The paper's Tables 3-5 columns, in order, with the :class:`~analysis.contracts.job.LineReport` field of each.
CSV_COLUMNS: tuple[tuple[str, str], ...] = (
    ("family", "family"),
    ("line", "index"),
    ("name", "name"),
    ("SZ (mm2)", "sz_mm2"),
    ("SZ-average (mm)", "sz_avg_mm"),
    ("Zmax (mm)", "zmax_mm"),
    ("CI", "ci"),
    ("SC-average (mm-1)", "sc_avg_per_mm"),
    ("Cmax (mm-1)", "cmax_per_mm"),
    ("length (mm)", "length_mm"),
    ("pass", "passed"),
)

FAMILIES: tuple[tuple[str, str], ...] = (
    ("transverse", "Table 3. Transverse detection lines"),
    ("longitudinal", "Table 4. Longitudinal detection lines"),
    ("diagonal", "Table 5. Diagonal detection lines"),
)
_LINES_PER_PDF_PAGE = 3
_TABLE_ROWS_PER_PDF_PAGE = 34
_A4_PORTRAIT_IN = (8.27, 11.69)
_HOLE_CELL_MM = 5.0  # the pipeline's coverage cell
_COLOURS = {
    "pass": "#1a7f37",
    "fail": "#c62828",
    "warn": "#b26a00",
    "design": "#1f4e9c",
    "measured": "#d35400",
}
# Diverging map, red where the plate stands above the template (d < 0), blue where it lies below.
_CMAP = "RdBu"


# ----------------------------------------------------------------------------------------- csv


def write_csv(report: Report, path: str | Path) -> Path:
    """``report.csv``: one row per detection line, the paper's Table 3-5 columns."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow([title for title, _ in CSV_COLUMNS])
        for line in report.lines:
            row = []
            for _, field in CSV_COLUMNS:
                v = getattr(line, field)
                row.append(
                    f"{v:.4f}"
                    if isinstance(v, float)
                    else ("yes" if v is True else "no" if v is False else v)
                )
            w.writerow(row)
    return path


# ----------------------------------------------------------------------------------- loading


@dataclass(frozen=True)
class ResultsData:
    """A results directory, loaded and checked (:func:`load_results`).

    report: report.json (lines carry a ``name``, derived from family and index if absent).
    plate_xy_mm: (n, 2) float64 positions from the reference corner; plate_deviation_mm: (n,) float64.
    plate_size_mm: (2,) length, width. lines: one :class:`LineSeries` per report line, or None where
    the results hold no section for it. holes_xy_mm: (h, 2) centres of unseen design cells.
    """

    results_dir: Path
    report: Report
    plate_xy_mm: np.ndarray
    plate_deviation_mm: np.ndarray
    plate_size_mm: np.ndarray
    lines: list[LineSeries | None]
    holes_xy_mm: np.ndarray


@dataclass(frozen=True)
class PreviousLine:
    """One line of the previous round: its name (``T1``, ``L2``, ``D1``), Zmax and SZ-average (mm),
    and whether it passed."""

    name: str
    zmax_mm: float
    sz_avg_mm: float
    passed: bool


@dataclass(frozen=True)
class PreviousRound:
    """The plate's previous forming round (the caller finds it; this module reads no job directory).

    round: its number among the plate's analysed rounds (1 = the first); this report is round + 1.
    """

    round: int
    job_id: str
    created_utc: str
    verdict: str
    lines: tuple[PreviousLine, ...]


def previous_by_line(report: Report, previous: PreviousRound) -> list[tuple[LineReport, PreviousLine | None]]:
    """This report's lines, each with the previous round's line of the same name (None: no match)."""
    by_name = {ln.name: ln for ln in previous.lines}
    return [(ln, by_name.get(ln.name)) for ln in report.lines]


def _not_scanned_items(cov: ScanCoverage) -> list[tuple[str, str]]:
    """The coverage table's rows of a partial scan: what it did not cover (none for a whole scan)."""
    if not cov.partial:
        return []
    names = ", ".join(f"{x.name} ({100 * x.scanned_fraction:.0f} % seen)" for x in cov.lines_not_scanned)
    return [
        ("partial scan", "the scan covers only part of the plate: registered on the planned placement"),
        ("lines not scanned (not judged)", _e(names) or "none"),
    ]


def load_results(results_dir: str | Path) -> ResultsData:
    """Read and check ``report.json`` and ``results.npz`` of a results directory
    (:func:`analysis.contracts.results.read_report`, :func:`analysis.contracts.results.read_results_arrays`).

    Raises :class:`ReportError` naming the file and the field or array at fault.
    """
    d = Path(results_dir)
    if not d.is_dir():
        raise ReportError(f"{d}: not a results directory (no such directory)")
    report = read_report(d / "report.json")
    arrays = read_results_arrays(d / "results.npz", n_lines=len(report.lines))
    return ResultsData(
        d, report, arrays.plate_xy_mm, arrays.plate_deviation_mm, arrays.plate_size_mm, arrays.lines,
        arrays.holes_xy_mm,
    )  # fmt: skip


# ------------------------------------------------------------------------------------- figures


def _tolerances(report: Report) -> tuple[float, float, str]:
    tol = report.tolerances
    return float(tol.deviation_standard_mm), float(tol.deviation_limit_mm), tol.standard


def _display_cell_mm(data: ResultsData) -> float:
    # about nine points per cell, so a random subsample leaves (almost) no cell empty: e^-9
    n = max(len(data.plate_xy_mm), 1)
    return float(np.clip(3.0 * math.sqrt(data.plate_size_mm.prod() / n), 2.0, 25.0))


def _draw_top_view(ax: Any, data: ResultsData, field: GriddedField, regions: list[ReworkRegion]) -> Any:
    """Deviation colour map, detection lines with names and Zmax marks, rework regions, the reference corner."""
    std, lim, _ = _tolerances(data.report)
    L, W = (float(v) for v in data.plate_size_mm)
    mean = field.mean_mm
    finite = mean[np.isfinite(mean)]
    vmax = max(1.2 * lim, float(np.percentile(np.abs(finite), 99.5)) if finite.size else 0.0)
    nx, ny = mean.shape
    c = field.cell_mm
    footprint = Rectangle((0, 0), L, W, facecolor="#d9d9d9", edgecolor="none", zorder=0)
    ax.add_patch(footprint)
    im = ax.imshow(
        np.ma.masked_invalid(mean.T),
        origin="lower",
        extent=(0, nx * c, 0, ny * c),
        cmap=_CMAP,
        norm=Normalize(-vmax, vmax),
        interpolation="nearest",
        zorder=1,
    )
    im.set_clip_path(footprint)  # the last row and column of cells may reach past the plate's edge
    if finite.size and (np.nanmax(np.abs(mean)) > std):
        xc = (np.arange(nx) + 0.5) * c
        yc = (np.arange(ny) + 0.5) * c
        ax.contour(
            xc,
            yc,
            np.ma.masked_invalid(mean.T),
            levels=sorted({-lim, -std, std, lim}),
            colors="k",
            linewidths=[0.8, 0.6, 0.6, 0.8],
            linestyles=["solid", "dashed", "dashed", "solid"],
            zorder=2,
        )
    ax.add_patch(Rectangle((0, 0), L, W, facecolor="none", edgecolor="k", linewidth=1.0, zorder=3))
    pad = 0.045 * max(L, W)
    for line in data.report.lines:
        if line.start_plate_mm is None or line.end_plate_mm is None:
            continue
        a = np.asarray(line.start_plate_mm, dtype=float)
        b = np.asarray(line.end_plate_mm, dtype=float)
        colour = _COLOURS["pass"] if line.passed else _COLOURS["fail"]
        ax.plot([a[0], b[0]], [a[1], b[1]], color="k", linewidth=0.7, zorder=4)
        if line.family == "diagonal":
            at = a + 0.22 * (b - a)
        else:
            # just outside the plate before the line's start, so labels never cover the map
            at = a - (b - a) / max(float(np.linalg.norm(b - a)), 1e-9) * pad * 0.55
        ax.text(
            at[0],
            at[1],
            line.name,
            ha="center",
            va="center",
            fontsize=6.5,
            color=colour,
            fontweight="bold",
            zorder=6,
            bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": colour, "linewidth": 0.5},
        )
        chord = float(np.linalg.norm(b - a))
        if chord > 0:
            p = a + (b - a) * min(max(float(line.zmax_at_mm) / chord, 0.0), 1.0)
            ax.plot(p[0], p[1], marker="x", color=colour, markersize=4, mew=1.0, zorder=5)
    for r in regions:
        x0, y0, x1, y1 = r.bbox_mm
        ax.add_patch(
            Rectangle(
                (x0, y0),
                x1 - x0,
                y1 - y0,
                facecolor="none",
                edgecolor="#6a1b9a",
                linewidth=1.0,
                linestyle="--",
                zorder=5,
            )
        )
        ax.text(
            x1, y1, r.label, fontsize=7, color="#6a1b9a", fontweight="bold", ha="left", va="bottom", zorder=6
        )
    ax.plot(0, 0, marker="^", color="#6a1b9a", markersize=9, clip_on=False, zorder=7)
    ax.annotate(
        "REF (0, 0)",
        (0, 0),
        xytext=(-4, -14),
        textcoords="offset points",
        fontsize=7,
        color="#6a1b9a",
        fontweight="bold",
        ha="right",
        va="top",
        annotation_clip=False,
    )
    ax.set_xlim(-pad * 1.3, L + pad * 0.4)
    ax.set_ylim(-pad * 1.3, W + pad * 0.4)
    ax.set_aspect("equal")
    ax.set_xlabel("x along the length from the reference corner (mm)", fontsize=8)
    ax.set_ylabel("y along the width (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    return im


def _colorbar(fig: Figure, im: Any, **kw: Any) -> None:
    cb = fig.colorbar(im, **kw)
    cb.set_label("d = z_design − z_measured (mm)\n+ plate below template   − plate above", fontsize=7)
    cb.ax.tick_params(labelsize=7)


def _draw_line(ax_z: Any, ax_d: Any, data: ResultsData, k: int) -> None:
    """Design and measured sections (top), deviation with the tolerance band and Zmax (bottom)."""
    line = data.report.lines[k]
    series = data.lines[k]
    std, lim, _ = _tolerances(data.report)
    verdict = "PASS" if line.passed else "FAIL"
    where = ""
    if line.start_plate_mm is not None and line.end_plate_mm is not None:
        a, b = line.start_plate_mm, line.end_plate_mm
        where = f"  ({a[0]:.0f}, {a[1]:.0f}) → ({b[0]:.0f}, {b[1]:.0f}) mm"
    # a text, not set_title: the title's automatic placement measures every tick label again
    ax_z.text(
        0.0,
        1.04,
        f"{line.name}  {line.family} {line.index}  {verdict}{where}",
        transform=ax_z.transAxes,
        fontsize=8,
        color=_COLOURS["pass"] if line.passed else _COLOURS["fail"],
        fontweight="bold",
    )
    zmax = float(line.zmax_mm)
    ymax = max(1.15 * lim, 1.2 * zmax)
    if series is None or not len(series.s_mm):
        ax_z.text(
            0.5,
            0.5,
            "no section data stored for this line",
            ha="center",
            va="center",
            transform=ax_z.transAxes,
            fontsize=8,
        )
        s = np.zeros(0)
    else:
        s = series.s_mm
        ax_z.plot(s, series.design_z_mm, color=_COLOURS["design"], linewidth=1.0, label="design (template)")
        seen = float(np.mean(np.isfinite(series.measured_z_mm)))
        # say how much of the line the scan covered: a curve with gaps is not a curve with data
        ax_z.plot(
            s,
            series.measured_z_mm,
            color=_COLOURS["measured"],
            linewidth=0.9,
            label="measured" if seen > 0.995 else f"measured ({100 * seen:.0f} % of the line)",
        )
        ax_z.legend(fontsize=6, loc="best", frameon=False)
        finite = np.abs(series.deviation_mm[np.isfinite(series.deviation_mm)])
        if finite.size:
            ymax = max(ymax, 1.2 * float(finite.max()))
    ax_d.axhspan(-std, std, color=_COLOURS["pass"], alpha=0.12, linewidth=0)
    for lo, hi in ((std, lim), (-lim, -std)):
        ax_d.axhspan(lo, hi, color=_COLOURS["warn"], alpha=0.15, linewidth=0)
    for lo, hi in ((lim, ymax), (-ymax, -lim)):
        ax_d.axhspan(lo, hi, color=_COLOURS["fail"], alpha=0.10, linewidth=0)
    for y, ls in ((std, "--"), (-std, "--"), (lim, "-"), (-lim, "-")):
        ax_d.axhline(y, color="0.35", linewidth=0.6, linestyle=ls)
    ax_d.axhline(0, color="0.6", linewidth=0.5)
    if len(s):
        ax_d.plot(s, series.deviation_mm, color="k", linewidth=0.9)
        at = float(line.zmax_at_mm)
        sign = np.sign(np.interp(at, s, np.nan_to_num(series.deviation_mm))) or 1.0
        ax_d.plot(at, sign * zmax, marker="v" if sign > 0 else "^", color=_COLOURS["fail"], markersize=6)
        left = at > 0.5 * (float(s[0]) + float(s[-1]))  # keep the label inside the axes
        ax_d.annotate(
            f"Zmax {zmax:.2f} mm at {at:.0f} mm",
            (at, sign * zmax),
            xytext=(-6 if left else 6, -4 if sign > 0 else 4),
            textcoords="offset points",
            fontsize=6.5,
            ha="right" if left else "left",
            va="top" if sign > 0 else "bottom",
        )
        ax_d.set_xlim(float(s[0]), float(s[-1]))
        ax_z.set_xlim(float(s[0]), float(s[-1]))
    ax_d.set_ylim(-ymax, ymax)
    ax_d.set_xlabel("position along the line from its start (mm)", fontsize=7)
    ax_d.set_ylabel("d (mm)", fontsize=7)
    ax_z.set_ylabel("height (mm)", fontsize=7)
    for ax in (ax_z, ax_d):
        ax.yaxis.set_major_locator(MaxNLocator(5))
        ax.tick_params(labelsize=6.5)
        ax.grid(True, linewidth=0.3, alpha=0.5)


def _draw_coverage(ax: Any, data: ResultsData) -> None:
    """Where the scan saw the plate (grey), holes in the design's coverage (red)."""
    L, W = (float(v) for v in data.plate_size_mm)
    # the holes are the pipeline's (computed on the whole cloud), not gaps of the stored subsample
    ax.add_patch(Rectangle((0, 0), L, W, facecolor="#cfcfcf", edgecolor="none"))
    h = data.holes_xy_mm
    if len(h):
        # the unseen cells rasterised on their own 5 mm grid: one image, whatever their number
        hc = _HOLE_CELL_MM
        hx, hy = int(np.ceil(L / hc)), int(np.ceil(W / hc))
        ij = np.clip((h / hc).astype(np.int64), 0, [hx - 1, hy - 1])
        grid = np.zeros((hx, hy))
        grid[ij[:, 0], ij[:, 1]] = 1.0
        ax.imshow(
            np.ma.masked_equal(grid.T, 0.0),
            origin="lower",
            extent=(0, hx * hc, 0, hy * hc),
            cmap=ListedColormap([_COLOURS["fail"]]),
            vmin=0,
            vmax=1,
            interpolation="nearest",
            zorder=2,  # over the footprint patch
        )
    ax.add_patch(Rectangle((0, 0), L, W, facecolor="none", edgecolor="k", linewidth=1.0))
    ax.plot(0, 0, marker="^", color="#6a1b9a", markersize=8, clip_on=False)
    pad = 0.03 * max(L, W)
    ax.set_xlim(-pad, L + pad)
    ax.set_ylim(-pad, W + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x from the reference corner (mm)", fontsize=8)
    ax.set_ylabel("y (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title(
        f"seen: {100 * data.report.coverage.fraction:.1f} % of the design's top surface",
        fontsize=8,
        loc="left",
    )


def _svg(fig: Figure) -> str:
    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    # inline: drop the XML declaration and DOCTYPE, keep the <svg> element
    return text[text.index("<svg") :]


# ---------------------------------------------------------------------------------------- html

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Arial,sans-serif;margin:0;color:#222;background:#fafafa}
header{padding:16px 24px;color:#fff}
header.pass{background:#1a7f37} header.fail{background:#c62828} header.incomplete{background:#b26a00}
header h1{margin:0;font-size:28px} header p{margin:4px 0 0;font-size:15px}
main{padding:8px 24px 40px;max-width:1400px}
section{background:#fff;border:1px solid #ddd;border-radius:6px;margin:16px 0;padding:12px 16px}
h2{font-size:19px;margin:4px 0 10px}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#eee} td.t{text-align:left}
tr.pass td.v{background:#d7f0dc;color:#135b28;font-weight:bold}
tr.fail td.v{background:#fbd5d5;color:#8e1b1b;font-weight:bold}
td.ok{background:#eaf6ec} td.warn{background:#fff1cc} td.bad{background:#fbd5d5;font-weight:bold}
.plots{display:grid;grid-template-columns:repeat(auto-fill,minmax(560px,1fr));gap:10px}
figure.plot{margin:0;background:#fff}
figure.plot svg{width:100%;height:auto;display:block}
figcaption{font-size:12px;color:#555;margin:2px 0 6px}
.big{font-size:16px} .muted{color:#666}
"""


def _e(v: Any) -> str:
    return html.escape(str(v), quote=True)


def _f(v: Any, digits: int = 2) -> str:
    return f"{v:.{digits}f}" if isinstance(v, int | float) and not isinstance(v, bool) else "—"


def _zmax_class(z: float, std: float, lim: float) -> str:
    return "ok" if z <= std else "warn" if z <= lim else "bad"


def _sign_text(sign: str) -> str:
    return "plate below template (gap)" if sign == "below" else "plate above template"


def _lines_table_html(report: Report, family: str) -> str:
    std, lim, _ = _tolerances(report)
    rows = []
    for line in report.lines:
        if line.family != family:
            continue
        cls = "pass" if line.passed else "fail"
        pos = ""
        if line.start_plate_mm is not None and line.end_plate_mm is not None:
            a, b = line.start_plate_mm, line.end_plate_mm
            pos = f"({a[0]:.0f}, {a[1]:.0f}) → ({b[0]:.0f}, {b[1]:.0f})"
        rows.append(
            f'<tr class="{cls}" data-line="{_e(line.name)}"><td class="t">{_e(line.name)}</td>'
            f"<td>{_e(line.index)}</td><td>{_f(line.sz_mm2, 4)}</td><td>{_f(line.sz_avg_mm, 4)}</td>"
            f'<td class="{_zmax_class(float(line.zmax_mm), std, lim)}">{_f(line.zmax_mm, 4)}</td>'
            f"<td>{_f(line.ci, 4)}</td><td>{_f(line.sc_avg_per_mm, 4)}</td>"
            f"<td>{_f(line.cmax_per_mm, 4)}</td><td>{_f(line.length_mm, 1)}</td>"
            f'<td class="t">{pos}</td><td class="v">{"pass" if line.passed else "FAIL"}</td></tr>'
        )
    if not rows:
        return ""
    title = dict(FAMILIES)[family]
    return (
        f'<h3>{_e(title)}</h3><table class="lines" data-family="{family}"><thead><tr>'
        "<th>line</th><th>#</th><th>SZ (mm²)</th><th>SZ-average (mm)</th><th>Zmax (mm)</th><th>CI</th>"
        "<th>SC-average (mm⁻¹)</th><th>Cmax (mm⁻¹)</th><th>length (mm)</th>"
        "<th>start → end from reference corner (mm)</th><th>verdict</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table>"
    )


TEMPLATE_FIT_TEXT = {
    "rigid": "one template resting on the whole plate (rigid 3D fit)",
    "per_line": "a template per line, resting on its own section (2D fit)",
}


def _compare_html(report: Report) -> str:
    """The other template fit's figures beside the judged ones, when the report carries them."""
    other = report.template_fit_compare
    if other is None:
        return ""
    mine = {ln.name: ln for ln in report.lines}

    def judged_figure(name: str, field: str) -> float | None:
        return getattr(mine[name], field) if name in mine else None

    rows = "".join(
        f'<tr data-line="{_e(ln.name)}"><td class="t">{_e(ln.name)}</td>'
        f"<td>{_f(judged_figure(ln.name, 'zmax_mm'), 4)}</td><td>{_f(ln.zmax_mm, 4)}</td>"
        f"<td>{_f(judged_figure(ln.name, 'sz_avg_mm'), 4)}</td><td>{_f(ln.sz_avg_mm, 4)}</td>"
        f"<td>{_f(judged_figure(ln.name, 'cmax_per_mm'), 4)}</td><td>{_f(ln.cmax_per_mm, 4)}</td>"
        f'<td class="v">{"pass" if ln.passed else "FAIL"}</td></tr>'
        for ln in other.lines
    )
    judged, alt = report.template_fit, other.template_fit
    return (
        f'<section id="template-fits"><h2>Both template fits</h2><p class="muted">Judged: '
        f"{_e(TEMPLATE_FIT_TEXT.get(judged, judged))}. Shown beside it, not judged: "
        f"{_e(TEMPLATE_FIT_TEXT.get(alt, alt))} (verdict {_e(other.verdict)}).</p>"
        f'<table class="lines" data-compare="{_e(alt)}"><thead><tr><th>line</th>'
        f"<th>Zmax {_e(judged)} (mm)</th><th>Zmax {_e(alt)} (mm)</th><th>SZ-average {_e(judged)} (mm)</th>"
        f"<th>SZ-average {_e(alt)} (mm)</th><th>Cmax {_e(judged)} (mm⁻¹)</th><th>Cmax {_e(alt)} (mm⁻¹)</th>"
        f"<th>{_e(alt)} verdict</th></tr></thead><tbody>{rows}</tbody></table></section>"
    )


def _previous_html(report: Report, previous: PreviousRound | None) -> str:
    """The "Previous round" section: this round's and the previous round's figures per line."""
    if previous is None:
        return ""
    rows = []
    for ln, prev in previous_by_line(report, previous):
        now_v = "pass" if ln.passed else "FAIL"
        if prev is None:
            cells = '<td>—</td><td>—</td><td class="t">—</td>'
        else:
            cells = (
                f"<td>{_f(prev.zmax_mm, 2)}</td><td>{_f(prev.sz_avg_mm, 2)}</td>"
                f'<td class="t">{"pass" if prev.passed else "FAIL"}</td>'
            )
        rows.append(
            f'<tr data-line="{_e(ln.name)}"><td class="t">{_e(ln.name)}</td>'
            f'<td>{_f(ln.zmax_mm, 2)}</td><td>{_f(ln.sz_avg_mm, 2)}</td><td class="t">{now_v}</td>'
            f"{cells}</tr>"
        )
    n = previous.round
    return (
        f'<section id="previous-round" data-round="{n + 1}"><h2>Previous round</h2>'
        f"<p>This is round {n + 1} of plate {_e(report.plate_id)}; round {n}: job {_e(previous.job_id)}, "
        f"{_e(previous.created_utc)}, verdict {_e(previous.verdict)}.</p>"
        f'<table class="previous"><thead><tr><th>line</th><th>Zmax (mm), round {n + 1}</th>'
        f"<th>SZ-average (mm), round {n + 1}</th><th>verdict, round {n + 1}</th>"
        f"<th>Zmax (mm), round {n}</th><th>SZ-average (mm), round {n}</th><th>verdict, round {n}</th>"
        "</tr></thead><tbody>" + "".join(rows) + "</tbody></table></section>"
    )


def _rework_html(regions: list[ReworkRegion], std: float) -> str:
    if not regions:
        return f"<p>No region of the plate lies beyond the standard range (±{std:g} mm).</p>"
    rows = "".join(
        f'<tr data-region="{r.label}"><td class="t">{r.label}</td><td class="t">{_sign_text(r.sign)}</td>'
        f'<td class="{"bad" if r.beyond_limit else "warn"}">{r.peak_mm:+.2f}</td><td>{r.mean_mm:+.2f}</td>'
        f"<td>{r.area_mm2:.0f}</td><td>{r.bbox_mm[2] - r.bbox_mm[0]:.0f} × {r.bbox_mm[3] - r.bbox_mm[1]:.0f}</td>"
        f"<td>({r.centre_xy_mm[0]:.0f}, {r.centre_xy_mm[1]:.0f})</td>"
        f"<td>({r.peak_xy_mm[0]:.0f}, {r.peak_xy_mm[1]:.0f})</td>"
        f"<td>{'yes' if r.beyond_limit else 'no'}</td></tr>"
        for r in regions
    )
    return (
        '<table class="rework"><thead><tr><th>region</th><th>where the plate is</th><th>peak d (mm)</th>'
        "<th>mean d (mm)</th><th>area (mm²)</th><th>size x × y (mm)</th><th>centre x, y (mm)</th>"
        "<th>deepest point x, y (mm)</th><th>beyond limit</th></tr></thead><tbody>"
        + rows
        + "</tbody></table>"
    )


EXPORTS = ("report.json", "report.csv", "report.pdf", "cloud.ply")


def _export_links(results_dir: Path) -> str:
    notes = {"cloud.ply": " (registered cloud, per-point deviation as a scalar field)"}
    # report.pdf is written after the page, so list it whatever exists now
    return ", ".join(
        f'<a href="{name}">{name}</a>{notes.get(name, "")}'
        for name in EXPORTS
        if name == "report.pdf" or (results_dir / name).exists()
    )


def _kv_table(items: list[tuple[str, str]]) -> str:
    return (
        "<table>" + "".join(f'<tr><th class="t">{_e(k)}</th><td>{v}</td></tr>' for k, v in items) + "</table>"
    )


def _registration_items(report: Report) -> list[tuple[str, str]]:
    reg = report.registration
    items = [
        ("coarse fit RMS (mm)", _f(reg.coarse_rms_mm, 3)),
        ("ICP RMS (mm)", _f(reg.icp_rms_mm, 3)),
        ("non-penetrating fit RMS (mm)", _f(reg.nonpen_rms_mm, 3)),
        ("penetrating points before the fit", _e(reg.penetration_points_before)),
        ("penetrating points after the fit", _e(reg.penetration_points)),
    ]
    rest = reg.rest_surface
    if rest is not None:
        items.append(
            ("resting surface: patch (mm), points at least", f"{_f(rest.cell_mm, 1)}, {_e(rest.min_points)}")
        )
        items.append(("resting surface: noise sigma, bias bound (mm)", f"{_f(rest.noise_mm, 4)}, {_f(rest.bound_mm, 4)} ({_e(rest.confidence)})"))  # fmt: skip
    T = np.asarray(reg.transform, dtype=float)  # 4 x 4: the schema says so
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(T[:3, :3]) - 1) / 2))))
    items.append(("design → measured: rotation (deg)", f"{angle:.3f}"))
    items.append(("design → measured: translation (mm)", _e(", ".join(f"{v:.2f}" for v in T[:3, 3]))))
    return items


def render_html(
    data: ResultsData,
    regions: list[ReworkRegion],
    svgs: dict[str, str],
    previous: PreviousRound | None = None,
) -> str:
    """The self-contained report page (a string). ``svgs``: "top", "coverage", "line{k}" -> inline SVG.
    ``previous``: the plate's previous round (a "Previous round" section); None for a first round."""
    rep = data.report
    std, lim, standard = _tolerances(rep)
    lines = rep.lines
    n_pass = sum(1 for ln in lines if ln.passed)
    worst = max(lines, key=lambda ln: ln.zmax_mm, default=None)
    verdict = rep.verdict
    head = (
        f'<header class="{verdict}"><h1>{_e(verdict.upper())} — plate {_e(rep.plate_id)}</h1>'
        f"<p>cell {_e(rep.cell_id)} · job {_e(rep.job_id)} · "
        f"{_e(rep.created_utc)} · judged against {_e(standard or '—')} "
        f"(standard ±{std:g} mm, limit ±{lim:g} mm)</p></header>"
    )
    summary = _kv_table(
        [
            ("lines within tolerance", f"{n_pass} of {len(lines)}"),
            ("worst line", f"{_e(worst.name)}: Zmax {worst.zmax_mm:.2f} mm" if worst else "—"),
            ("regions to rework", str(len(regions))),
            (
                "template fit",
                _e(TEMPLATE_FIT_TEXT.get(rep.template_fit, rep.template_fit)),
            ),
            ("failed lines", _e(", ".join(ln.name for ln in lines if not ln.passed) or "none")),
        ]
    )
    line_figs = "".join(
        f'<figure class="plot" data-plot="line" data-line="{_e(ln.name)}">{svgs[f"line{k}"]}'
        f"<figcaption>{_e(ln.name)}: design and measured section, deviation with the tolerance band "
        f"(green: within ±{std:g} mm, amber: up to ±{lim:g} mm, red: beyond).</figcaption></figure>"
        for k, ln in enumerate(lines)
    )
    cov = rep.coverage
    timings = rep.timings_s
    inputs = rep.inputs.model_dump(mode="json")
    corner_rows = _kv_table(
        [
            (f"corner {i}{' (reference)' if i == 0 else ''}", _e(", ".join(_f(v, 1) for v in c)))
            for i, c in enumerate(rep.corners_mm)
        ]
    )
    body = f"""
<section id="summary"><h2>Summary</h2>{summary}</section>
<section id="top-view"><h2>Deviation map, top view</h2>
<figure class="plot" data-plot="top-view">{svgs["top"]}<figcaption>Deviation of the measured plate from the
registered design, seen from above, from the reference corner (REF). Dashed contours: ±{std:g} mm (standard
range); solid: ±{lim:g} mm (limit). Lines are labelled green (pass) or red (fail); × marks each line's Zmax;
purple boxes are the regions to rework.</figcaption></figure></section>
<section id="rework"><h2>Where to rework</h2>
<p class="muted">Regions where the plate is more than {std:g} mm off the template, positions in mm from the
reference corner (x along the length, y along the width).</p>{_rework_html(regions, std)}</section>
<section id="tables"><h2>Detection lines (the paper's Tables 3–5)</h2>
{"".join(_lines_table_html(rep, fam) for fam, _ in FAMILIES)}</section>
{_previous_html(rep, previous)}
{_compare_html(rep)}
<section id="lines"><h2>Detection lines, one plot each</h2><div class="plots">{line_figs}</div></section>
<section id="registration"><h2>Registration</h2>{_kv_table(_registration_items(rep))}
<h3>Measured corners (mm, measuring frame)</h3>{corner_rows}</section>
<section id="coverage"><h2>Scan coverage</h2>
{
        _kv_table(
            [
                ("seen fraction of the design's top surface", _f(100 * cov.fraction, 1) + " %"),
                ("unseen area (mm²)", _f(cov.holes_mm2, 0)),
                *_not_scanned_items(cov),
            ]
        )
    }
<figure class="plot" data-plot="coverage">{svgs["coverage"]}<figcaption>Grey: seen; red: unseen
5 mm cells of the design.</figcaption></figure></section>
<section id="details"><h2>Timings and inputs</h2>
{_kv_table([(k, _f(v, 2) + " s") for k, v in timings.items()])}
{_kv_table([(k, _e(v)) for k, v in inputs.items()])}
<p class="muted">Exports beside this page (links to the files in the same folder, nothing is fetched
when the page opens): {_export_links(data.results_dir)}.</p></section>
"""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">'
        f"<title>Inspection {_e(rep.plate_id)}: {verdict.upper()}</title><style>{_CSS}</style></head>"
        f"<body>{head}<main>{body}</main></body></html>\n"
    )


# ----------------------------------------------------------------------------------------- pdf


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


# -------------------------------------------------------------------------------------- driver


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
