"""The report's figures, drawn with matplotlib's object API (no pyplot, no global figure state, so
safe from a worker thread): the top view of the deviation with the rework regions, one plot per
detection line, the scan's coverage; :func:`_svg` inlines a figure in the HTML page.

Every figure has a budget that holds whatever the plate's size (issue 42; docs/operations.md
"Result pages of a large plate"): the top view's deviation raster has at most
:data:`TOP_VIEW_MAX_CELLS` cells and is embedded, with its tolerance contours, as one image at the
figure's resolution, with the worst :data:`TOP_VIEW_MAX_REGIONS` rework regions boxed; each line's curves have at most :data:`LINE_PLOT_MAX_SAMPLES` samples (the
envelope of the deviation, :meth:`~analysis.contracts.results.LineSeries.decimated`); the coverage's
unseen cells are one image. The full data stays in results.npz and cloud.ply.
"""

from __future__ import annotations

import io
import math
import re
from typing import Any

import matplotlib
import numpy as np
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

from analysis.report.load import ResultsData
from analysis.report.text import _tolerances
from analysis.rework import GriddedField, ReworkRegion, bounded_cell_mm

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


#: the top view's deviation raster: at most this many cells (a 7-inch axes at 100 dpi is ~700 px wide)
TOP_VIEW_MAX_CELLS = 120_000
#: the top view boxes at most this many rework regions, the worst (the report's table lists them all)
TOP_VIEW_MAX_REGIONS = 40
#: each detection line's plot: at most this many samples per curve (its axes are ~560 px wide: the
#: lowest and highest deviation of ~330 bins, about one bin per 1.7 px)
LINE_PLOT_MAX_SAMPLES = 1000


def _display_cell_mm(data: ResultsData) -> float:
    # about nine points per cell, so a random subsample leaves (almost) no cell empty: e^-9
    n = max(len(data.plate_xy_mm), 1)
    cell = float(np.clip(3.0 * math.sqrt(data.plate_size_mm.prod() / n), 2.0, 25.0))
    return bounded_cell_mm(data.plate_size_mm, TOP_VIEW_MAX_CELLS, cell)


#: the heating lines' colours on the top view: the face up, the face down
HEATING_COLOURS = {"top": "#ff7f0e", "bottom": "#17becf"}


def _draw_heating_lines(ax: Any, data: ResultsData) -> None:
    """The heating plan's lines (heating-plan.json), solid, coloured by face, numbered in order at
    their start; nothing without a plan."""
    plan = data.heating_plan
    if plan is None or plan.status != "plan":
        return
    for line in plan.lines:
        (x0, y0), (x1, y1) = line.start_plate_mm, line.end_plate_mm
        colour = HEATING_COLOURS[line.face]
        ax.plot([x0, x1], [y0, y1], color=colour, linewidth=2.2, solid_capstyle="round", zorder=5)
        ax.text(x0, y0, str(line.order), ha="center", va="center", fontsize=6.5, fontweight="bold", color="white",
                zorder=7, bbox={"boxstyle": "circle,pad=0.2", "facecolor": colour, "edgecolor": "none"})  # fmt: skip


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
    # the footprint, the raster and the contours (zorder < 2.5) become one image at the figure's
    # resolution: a noisy field's contours would otherwise be paths of as many vertices as cells
    ax.set_rasterization_zorder(2.5)
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
    _draw_heating_lines(ax, data)
    for r in regions[:TOP_VIEW_MAX_REGIONS]:  # worst first: a rough plate's hundreds stay in the table
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
    full = data.lines[k]
    series = full.decimated(LINE_PLOT_MAX_SAMPLES) if full is not None else None
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
        assert full is not None  # the decimated series is the full one's
        seen = float(np.mean(np.isfinite(full.measured_z_mm)))  # of every sample, not of the plotted
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


_NO_METADATA = {"Date": None, "Creator": None, "Format": None, "Type": None}


def _svg(fig: Figure) -> str:
    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(buf, format="svg", metadata=_NO_METADATA)
    text = buf.getvalue()
    # inline: drop the XML declaration and DOCTYPE, keep the <svg> element; the indentation between
    # elements is a tenth of a line plot's bytes and nothing a browser shows
    return re.sub(r">\s+<", "><", text[text.index("<svg") :])
