"""``report.html``: one self-contained page (inline CSS, inline SVG plots with their raster parts as
data: URLs, no script, no web font, nothing fetched), so it opens from a USB stick.

A large plate's page has many line plots (95 on a 6000 x 2000 mm plate): the browser lays out and
paints only those near the screen (``content-visibility: auto``), so the page opens in the time of
its first screen, not of all its plots (issue 42; docs/operations.md "Result pages of a large plate").
"""

from __future__ import annotations

from pathlib import Path

from analysis.contracts.job import Report
from analysis.report.load import PreviousRound, ResultsData, previous_by_line
from analysis.report.plots import TOP_VIEW_MAX_REGIONS
from analysis.report.text import (
    FAMILIES,
    _e,
    _f,
    _not_scanned_items,
    _registration_items,
    _sign_text,
    _tolerances,
    _zmax_class,
)
from analysis.rework import ReworkRegion

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
.plots figure.plot{content-visibility:auto;contain-intrinsic-size:auto 360px}
figcaption{font-size:12px;color:#555;margin:2px 0 6px}
.big{font-size:16px} .muted{color:#666}
"""


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


EXPORTS = (
    "report.json",
    "report.csv",
    "report.pdf",
    "cloud.ply",
    "lines-ship.csv",
    "heating-plan.json",
    "heating-plan.dxf",
)


def _export_links(results_dir: Path) -> str:
    notes = {
        "cloud.ply": " (registered cloud, per-point deviation as a scalar field)",
        "lines-ship.csv": " (line ends in the design file's frame; `cellctl export` for the cloud in it)",
    }
    # report.pdf is written after the page, so list it whatever exists now
    return ", ".join(
        f'<a href="{name}">{name}</a>{notes.get(name, "")}'
        for name in EXPORTS
        if name == "report.pdf" or (results_dir / name).exists()
    )


def _heating_html(data: ResultsData) -> str:
    """The heating plan's section: one sentence a line in the crew's order, the predicted round, the
    planner's notes, or why there is no plan; nothing when the results hold no plan."""
    plan = data.heating_plan
    if plan is None:
        return ""
    if plan.status != "plan":
        body = f"<p>No heating plan: {_e(plan.reason or '')}</p>"
    else:
        items = "".join(
            f'<li data-heat="{_e(ln.id)}">{_e(ln.sentence())} · {ln.heat_input_j_mm:.0f} J/mm, '
            f"bend {ln.bend_deg:.2f}°, shrink {ln.shrink_mm:.2f} mm</li>"
            for ln in plan.lines
        )
        p = plan.predicted
        after = (
            f"<p>Predicted after this round: verdict {_e(p.verdict.upper())}, RMS {p.rms_before_mm:.2f} → "
            f"{p.rms_after_mm:.2f} mm over the plate; Zmax per line: "
            + _e(", ".join(f"{k} {v:.2f}" for k, v in p.zmax_mm.items() if v is not None))
            + " mm.</p>"
            if p
            else ""
        )
        notes = "".join(f"<li>{_e(n)}</li>" for n in plan.notes)
        body = f"<ol>{items}</ol>{after}" + (f'<ul class="muted">{notes}</ul>' if notes else "")
    return (
        '<section id="heating"><h2>Heating plan: the next round of line heating</h2>'
        '<p class="muted">Lines in mm from the reference corner as the plate lies, numbered on the top view '
        "in the order to heat them (orange: top face, cyan: bottom face); heating-plan.dxf marks them.</p>"
        f"{body}</section>"
    )


def _kv_table(items: list[tuple[str, str]]) -> str:
    return (
        "<table>" + "".join(f'<tr><th class="t">{_e(k)}</th><td>{v}</td></tr>' for k, v in items) + "</table>"
    )


def _boxed_text(n_regions: int) -> str:
    if n_regions <= TOP_VIEW_MAX_REGIONS:
        return ""
    return f" (the {TOP_VIEW_MAX_REGIONS} worst of {n_regions}; the table below lists them all)"


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
purple boxes are the regions to rework{_boxed_text(len(regions))}{
        "; numbered solid lines are the heating plan" if data.heating_plan and data.heating_plan.lines else ""
    }.</figcaption></figure></section>
<section id="rework"><h2>Where to rework</h2>
<p class="muted">Regions where the plate is more than {std:g} mm off the template, positions in mm from the
reference corner (x along the length, y along the width).</p>{_rework_html(regions, std)}</section>
{_heating_html(data)}
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
