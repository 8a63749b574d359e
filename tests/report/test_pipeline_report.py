"""The report made from the analysis pipeline's real output: a synthetic scan inspected end to end."""

from __future__ import annotations

import csv
import math
import re
import subprocess

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial import cKDTree

from analysis import pipeline, synth
from analysis.design import plates
from analysis.report.load import load_results
from analysis.report.write import write_report
from analysis.rework import find_rework_regions, grid_deviation
from analysis.templates import DetectionLayout


@pytest.fixture(scope="module")
def inspected(tmp_path_factory: pytest.TempPathFactory):
    """A 600 x 400 mm sail plate with the default dent and bump, scanned coarsely and inspected."""
    spec = plates.plate_spec("sail", length_mm=600.0, width_mm=400.0)
    scan = synth.synthesize_scan(spec, settings=synth.ScanSettings.coarse(), seed=1)
    settings = pipeline.InspectionSettings(
        layout=DetectionLayout(
            transverse_count=3,
            transverse_spacing_mm=150.0,
            longitudinal_count=2,
            longitudinal_spacing_mm=150.0,
        ),
        grid_mm=2.0,  # the coarse scan's 2 mm profile step leaves every other 1 mm row empty
    )
    ins = pipeline.inspect_cloud(
        scan.cloud, plates.design_mesh(spec, pitch_mm=5.0), settings, plate_id="P-pipe"
    )
    out = tmp_path_factory.mktemp("pipeline")
    pipeline.write_results(ins, out)
    return scan, ins, out, write_report(out)


@pytest.mark.slow
def test_pipeline_results_make_a_complete_report(inspected) -> None:
    _, ins, out, written = inspected
    assert [p.name for p in written] == ["report.csv", "report.html", "report.pdf"]
    lines = ins.report.lines
    html = (out / "report.html").read_text(encoding="utf-8")
    for line in lines:
        assert f'data-plot="line" data-line="{line.name}"' in html
    text = subprocess.run(
        ["pdftotext", "-layout", str(out / "report.pdf"), "-"], check=True, capture_output=True, text=True
    ).stdout
    pages = text.split("\f")[:-1]
    assert len(pages) == 2 + 1 + math.ceil(len(lines) / 3)
    assert "P-pipe" in pages[0] and ins.report.verdict.upper() in pages[0]


@pytest.mark.slow
def test_pipeline_ply_deviation_read_back_matches_the_stored_results_and_line_figures(inspected) -> None:
    _, ins, out, _ = inspected
    v = PlyData.read(str(out / "cloud.ply"))["vertex"]
    dev = np.asarray(v["scalar_deviation"])
    assert dev.dtype == np.float32 and len(dev) == len(ins.deviation_mm)
    res = np.load(out / "results.npz")
    # the map holds the reconstructed surface (cell means): it agrees with the raw cloud around it
    xyz = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    plate_xy = (xyz @ ins.T_plate_design[:3, :3].T + ins.T_plate_design[:3, 3])[:, :2]
    ok = np.isfinite(dev)
    tree = cKDTree(plate_xy[ok])
    pick = np.random.default_rng(0).choice(len(res["plate_xy_mm"]), size=500, replace=False)
    nbrs = tree.query_ball_point(res["plate_xy_mm"][pick].astype(np.float64), r=3.0)
    raw_median = np.array([np.median(dev[ok][n]) if len(n) >= 3 else np.nan for n in nbrs])
    good = np.isfinite(raw_median)
    assert good.mean() > 0.9
    assert np.abs(raw_median[good] - res["plate_deviation_mm"][pick][good]).max() < 0.1
    # every large Zmax is found again in the cloud's own deviations near where the line has it
    for line in ins.report.lines:
        if line.zmax_mm < 1.0:
            continue
        a, b = np.asarray(line.start_plate_mm), np.asarray(line.end_plate_mm)
        at = a + (b - a) * line.zmax_at_mm / np.linalg.norm(b - a)
        near = ok & (np.hypot(*(plate_xy - at).T) < 3.0)
        assert near.sum() >= 5, line.name
        assert float(np.median(np.abs(dev[near]))) == pytest.approx(line.zmax_mm, abs=0.2), line.name


@pytest.mark.slow
def test_pipeline_rework_region_sits_on_the_true_dent(inspected) -> None:
    scan, ins, out, _ = inspected
    dent = scan.error.bumps[0]
    assert dent.amplitude_mm < 0
    # the dent's true place: design frame -> bed (truth) -> registered design frame -> plate frame
    p = np.array([dent.x_mm, dent.y_mm, 0.0, 1.0])
    p[2] = plates.formed_height_mm(scan.spec, scan.error, dent.x_mm, dent.y_mm)
    T = ins.T_plate_design @ np.linalg.inv(ins.T_measured_design) @ scan.T_bed_design
    expected_xy = (T @ p)[:2]
    data = load_results(out)
    field = grid_deviation(data.plate_xy_mm, data.plate_deviation_mm, data.plate_size_mm, 5.0)
    regions = find_rework_regions(field, 2.0, 3.0)
    deepest = regions[0]
    assert deepest.sign == "below"
    assert np.hypot(*(np.asarray(deepest.peak_xy_mm) - expected_xy)) < 15.0
    # the page's own first rework row (its map cell may differ) names the same place
    html = (out / "report.html").read_text(encoding="utf-8")
    row = html[html.index('<tr data-region="R1">') :].split("</tr>")[0]
    peak = [float(v) for v in re.findall(r"<td>\((-?\d+), (-?\d+)\)</td>", row)[-1]]
    assert np.hypot(*(np.asarray(peak) - expected_xy)) < 15.0


@pytest.mark.slow
def test_pipeline_lines_ship_csv_holds_the_judged_lines_ends_in_the_design_files_frame(inspected) -> None:
    """A mesh given in its own frame: the file's frame is the design frame, so the ends in
    lines-ship.csv, moved into the plate frame, are the report's start_plate_mm / end_plate_mm."""
    _, ins, out, _ = inspected
    text = (out / "lines-ship.csv").read_text().splitlines()
    assert (
        text[0].startswith("# frame: design file frame (ship), mm") and "design frame = file frame" in text[0]
    )
    rows = list(csv.DictReader(text[1:]))
    assert [r["line"] for r in rows] == [ln.name for ln in ins.report.lines]
    T = ins.T_plate_design
    for r, line in zip(rows, ins.report.lines, strict=True):
        for end, want in (("start", line.start_plate_mm), ("end", line.end_plate_mm)):
            p = np.array([float(r[f"{end}_{a}_mm"]) for a in "xyz"])
            np.testing.assert_allclose((T[:3, :3] @ p + T[:3, 3])[:2], want, atol=0.02)
