"""The report's files from a results directory with known truth: HTML, PDF, CSV, and the PLY export."""

from __future__ import annotations

import csv
import json
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from analysis.contracts.results import ReportError
from analysis.report.load import load_results
from analysis.report.write import write_report
from analysis.rework import find_rework_regions, grid_deviation
from analysis.templates import DetectionLayout
from tests.report.conftest import PLATE_ID
from tests.support.results_fixture import write_synthetic_results

SMALL = DetectionLayout(
    transverse_offsets_mm=(300.0, 900.0), longitudinal_offsets_mm=(300.0,), diagonals=False
)


def _pdf_pages(pdf: Path) -> list[str]:
    """Text of every page (poppler's pdftotext; pages are separated by form feeds)."""
    out = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], check=True, capture_output=True, text=True)
    return out.stdout.split("\f")[:-1]


def test_write_report_makes_csv_html_and_pdf(reported) -> None:
    _, written = reported
    assert [p.name for p in written] == ["report.csv", "report.html", "report.pdf"]
    assert all(p.stat().st_size > 0 for p in written)


def test_csv_has_one_row_per_line_with_the_reported_figures(reported) -> None:
    truth, _ = reported
    with (truth.results_dir / "report.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert [r["name"] for r in rows] == [ln.name for ln in truth.report.lines]
    for row, line in zip(rows, truth.report.lines, strict=True):
        assert float(row["Zmax (mm)"]) == pytest.approx(line.zmax_mm, abs=1e-4)
        assert float(row["SZ (mm2)"]) == pytest.approx(line.sz_mm2, abs=1e-4)
        assert row["pass"] == ("yes" if line.passed else "no")


def test_html_fetches_nothing_and_runs_no_script(reported) -> None:
    truth, _ = reported
    text = (truth.results_dir / "report.html").read_text(encoding="utf-8")
    refs = re.findall(r'(?:src|href)\s*=\s*"([^"]*)"', text)
    assert refs, "the plots' raster parts are data: URLs"
    # besides data: URLs and in-page references, only links to the exports in the same folder
    # (followed when clicked, never fetched on load)
    links = re.findall(r'<a href="([^"]*)"', text)
    assert sorted(links) == ["cloud.ply", "report.csv", "report.json", "report.pdf"]
    assert all((truth.results_dir / name).exists() for name in links)
    others = [r for r in refs if not (r.startswith("data:") or r.startswith("#")) and r not in links]
    assert others == []
    assert "<script" not in text.lower()
    assert "@import" not in text and "@font-face" not in text
    assert re.findall(r"url\((?!#|data:)", text) == []


def test_html_shows_the_plate_id_as_text_never_as_markup(reported) -> None:
    truth, _ = reported
    text = (truth.results_dir / "report.html").read_text(encoding="utf-8")
    assert PLATE_ID not in text
    assert "HULL-07 &lt;b&gt;&amp;&quot;x&quot;&lt;/b&gt;" in text


def test_rework_regions_find_the_dent_below_and_the_bump_above_the_template(reported) -> None:
    truth, _ = reported
    data = load_results(truth.results_dir)
    field = grid_deviation(data.plate_xy_mm, data.plate_deviation_mm, data.plate_size_mm, 10.0)
    regions = find_rework_regions(field, 2.0, 3.0)
    assert [r.sign for r in regions] == ["below", "above"]
    dent, bump = regions
    # located from the reference corner within a cell, peak within the averaging of one cell
    assert np.hypot(*np.subtract(dent.centre_xy_mm, truth.dent_xy_mm)) < 10.0
    assert np.hypot(*np.subtract(bump.centre_xy_mm, truth.bump_xy_mm)) < 10.0
    assert dent.peak_mm == pytest.approx(truth.dent_depth_mm, abs=0.15) and dent.beyond_limit
    assert bump.peak_mm == pytest.approx(-truth.bump_height_mm, abs=0.15) and not bump.beyond_limit
    html = (truth.results_dir / "report.html").read_text(encoding="utf-8")
    assert 'data-region="R1"' in html and "plate below template (gap)" in html
    assert "plate above template" in html


@pytest.mark.process
def test_pdf_has_summary_rework_tables_and_line_pages(reported) -> None:
    truth, _ = reported
    pages = _pdf_pages(truth.results_dir / "report.pdf")
    lines = truth.report.lines
    assert len(pages) == 2 + 1 + math.ceil(len(lines) / 3)
    assert PLATE_ID in pages[0]
    assert re.search(rf"Verdict:\s+{truth.report.verdict.upper()}\b", pages[0])
    assert "CSQS 2016" in pages[0]
    assert "Where to rework" in pages[1] and "R1" in pages[1] and "plate below template" in pages[1]
    assert "Scan coverage" in pages[1]
    assert "Tables 3" in pages[2]
    for line in lines:
        row = next(r for r in pages[2].splitlines() if re.match(rf"\s*{line.name}\s", r))
        assert f"{line.zmax_mm:.4f}" in row
        assert ("pass" if line.passed else "FAIL") in row
    plot_text = "\n".join(pages[3:])
    order = [plot_text.index(f"{ln.name} {ln.family} {ln.index}") for ln in lines]
    assert order == sorted(order)
    assert plot_text.count("Zmax") >= len(lines)


def test_ply_deviation_read_back_independently_matches_the_results(reported) -> None:
    truth, _ = reported
    ply = PlyData.read(str(truth.results_dir / "cloud.ply"))
    v = ply["vertex"]
    assert v["scalar_deviation"].dtype == np.float32
    z = np.load(truth.results_dir / "results.npz")
    # the cloud carries the same per-point deviations as the stored results
    np.testing.assert_array_equal(np.sort(v["scalar_deviation"]), np.sort(z["plate_deviation_mm"]))
    # and its worst point agrees with the worst line's Zmax (the dent's centre lies on T4 and L2)
    worst = max(ln.zmax_mm for ln in truth.report.lines)
    assert float(np.abs(v["scalar_deviation"]).max()) == pytest.approx(worst, abs=0.1)
    # near every large Zmax, the cloud's own deviation reads the same figure
    ref = np.asarray(truth.report.corners_mm[0][:2])
    xy = np.column_stack([v["x"], v["y"]]) - ref
    for line in truth.report.lines:
        if line.zmax_mm < 1.0:
            continue
        a, b = np.asarray(line.start_plate_mm), np.asarray(line.end_plate_mm)
        at = a + (b - a) * line.zmax_at_mm / np.linalg.norm(b - a)
        near = np.argsort(np.hypot(*(xy - at).T))[:5]
        assert float(np.abs(v["scalar_deviation"][near]).max()) == pytest.approx(line.zmax_mm, abs=0.1), (
            line.name
        )


@pytest.fixture(scope="module")
def small_results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("small")
    write_synthetic_results(out, n_points=4000, layout=SMALL)
    return out


def _corrupt(src: Path, dst: Path, edit) -> Path:
    shutil.copytree(src, dst)
    report = json.loads((dst / "report.json").read_text())
    edit(report)
    (dst / "report.json").write_text(json.dumps(report))
    return dst


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r.pop("verdict"), "report.json: verdict: Field required"),
        (
            lambda r: r.update(verdict="maybe"),
            "report.json: verdict: Input should be 'pass', 'fail' or 'incomplete'",
        ),
        (lambda r: r["lines"][1].pop("zmax_mm"), r"report\.json: lines\[1\]\.zmax_mm: Field required"),
        (
            lambda r: r["lines"][0].update(ci="12"),
            r"report\.json: lines\[0\]\.ci: Input should be a valid number",
        ),
        (
            lambda r: r["lines"][0].update(sz_mm2=True),
            r"report\.json: lines\[0\]\.sz_mm2: Input should be a valid number",
        ),
        (
            lambda r: r["lines"][0].update(family="radial"),
            r"report\.json: lines\[0\]\.family: Input should be 'transverse'",
        ),
        (lambda r: r["lines"][2].update(start_plate_mm=[1.0]), r"report\.json: lines\[2\]\.start_plate_mm: "),
        (
            lambda r: r["tolerances"].update(deviation_limit_mm=-3),
            r"report\.json: tolerances: .*deviation_limit_mm",
        ),
        # a field the schema does not know is refused, at the top and inside
        (lambda r: r.update(verdikt="pass"), r"report\.json: verdikt: Extra inputs are not permitted"),
        (
            lambda r: r["lines"][1].update(zmax="1.0"),
            r"report\.json: lines\[1\]\.zmax: Extra inputs are not permitted",
        ),
        (
            lambda r: r["coverage"].update(seen=0.9),
            r"report\.json: coverage\.seen: Extra inputs are not permitted",
        ),
        (lambda r: r.update(lines={}), r"report\.json: lines: Input should be a valid (list|array)"),
    ],
)
def test_a_malformed_report_json_is_refused_naming_the_field(small_results, tmp_path, edit, message) -> None:
    d = _corrupt(small_results, tmp_path / "r", edit)
    with pytest.raises(ReportError, match=message):
        write_report(d)
    assert not (d / "report.html").exists() and not (d / "report.pdf").exists()


def _as_before_the_schema(r: dict) -> None:
    """The shape of the reports written before the Report schema (before 2026-12-01, 51d72ca): no
    nominal placement in the inputs, no design record, template fit, resting surface or line fit."""
    for key in ("design", "template_fit", "template_fit_compare"):
        r.pop(key, None)
    r["registration"].pop("rest_surface", None)
    r["registration"].pop("candidates_icp_rms_mm", None)
    for key in ("placement", "placement_found"):
        r["inputs"].pop(key, None)
    for line in r["lines"]:
        for key in ("line_fit", "noise_mm", "grade", "position_mm"):
            line.pop(key, None)


def _without_line_names(r: dict) -> None:
    """Lines without a name (a report written by hand): the family and index give it, T1, L2."""
    _as_before_the_schema(r)
    for line in r["lines"]:
        line.pop("name")


@pytest.mark.parametrize("edit", [_as_before_the_schema, _without_line_names])
def test_a_report_json_of_an_earlier_version_still_loads_and_renders(small_results, tmp_path, edit) -> None:
    d = _corrupt(small_results, tmp_path / "r", edit)
    now = load_results(small_results).report
    then = load_results(d).report
    assert [ln.name for ln in then.lines] == [ln.name for ln in now.lines]
    assert [ln.zmax_mm for ln in then.lines] == [ln.zmax_mm for ln in now.lines]
    assert then.verdict == now.verdict and then.design.kind == "mesh" and then.template_fit == "rigid"
    assert [p.name for p in write_report(d)] == ["report.csv", "report.html", "report.pdf"]


@pytest.mark.parametrize(
    ("drop", "replace", "message"),
    [
        ("plate_deviation_mm", None, "plate_deviation_mm: array is missing"),
        ("plate_deviation_mm", np.zeros(3, np.float32), "3 values for"),
        ("plate_xy_mm", np.zeros((10, 3), np.float32), r"plate_xy_mm: expected shape \(n, 2\)"),
        ("plate_size_mm", np.array([1200.0, 0.0]), "plate_size_mm"),
        ("line1_measured_z_mm", np.zeros(5), "line1_"),
    ],
)
def test_malformed_results_npz_is_refused_naming_the_array(
    small_results, tmp_path, drop, replace, message
) -> None:
    d = tmp_path / "r"
    shutil.copytree(small_results, d)
    arrays = dict(np.load(d / "results.npz"))
    arrays.pop(drop)
    if replace is not None:
        arrays[drop] = replace
    np.savez(d / "results.npz", **arrays)
    with pytest.raises(ReportError, match=message):
        write_report(d)


def test_a_directory_without_results_is_refused_clearly(tmp_path) -> None:
    with pytest.raises(ReportError, match=r"report\.json: missing"):
        write_report(tmp_path)
    (tmp_path / "report.json").write_text("{not json")
    with pytest.raises(ReportError, match="not valid JSON"):
        write_report(tmp_path)


@pytest.mark.process
def test_a_plate_without_detection_lines_still_gets_a_report_that_says_so(tmp_path) -> None:
    none = DetectionLayout(transverse_count=0, longitudinal_count=0, diagonals=False)
    truth = write_synthetic_results(tmp_path, n_points=2000, layout=none)
    assert truth.report.verdict == "fail"  # no line judged is no pass
    write_report(tmp_path)
    html = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert "0 of 0" in html and 'data-plot="top-view"' in html and 'data-plot="line"' not in html
    assert len(_pdf_pages(tmp_path / "report.pdf")) == 3
