"""A parallelogram plate in ship coordinates is inspected like a rectangular one (issue 18's done-when).

The designs (a 70-degree parallelogram, a trapezoid with a bowed edge) are given in ship coordinates
(stood up 75 degrees, 13 m above the keel); the scans are synthetic plates of that outline lying on
the bed. The figures are held to the rectangular case's tolerances (tests/inspect/test_pipeline.py:
a perfect plate reads below 0.05 mm on every line, a 1.5 mm dent is found within 0.1 mm), the
corners to the boundary's (tests/analysis/test_boundary.py), and the lines follow the plate's own
edges: they are where the design's own corners put them, in the plate frame.
"""

from __future__ import annotations

import json
import subprocess
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.settings import InspectionSettings
from analysis.design.plates import (
    NO_FORMING_ERROR,
    FormingError,
    GaussianBump,
    design_corners,
    design_mesh,
    plate_spec,
)
from analysis.pipeline import inspect_cloud, plate_frame
from analysis.synth import ScanSettings, synthesize_scan, write_synth
from analysis.templates import DetectionLayout, detection_lines
from tests.support.surfaces import ship_pose

LAYOUT = DetectionLayout(5, 100.0, 3, 100.0, True)
SETTINGS = InspectionSettings(layout=LAYOUT)
DENT_MM = 1.5
OUTLINES = {
    "parallelogram_70": {"corner_angle_deg": 70.0},
    "trapezoid_bowed": {"corner_angle_deg": 80.0, "top_length_mm": 520.0, "bow_mm": (0.0, 0.0, 8.0, 0.0)},
}


def _spec(outline: str):
    return plate_spec("sail", length_mm=600, width_mm=400, **OUTLINES[outline])


def _dent_on_t3_and_l2(spec) -> FormingError:
    """A dent where transverse line 3 crosses longitudinal line 2 (design frame)."""
    lines = {f"{ln.family[0].upper()}{ln.index}": ln for ln in detection_lines(design_corners(spec), LAYOUT)}
    t3, l2 = lines["T3"], lines["L2"]
    # t3.start + a d_t = l2.start + b d_l, in plan
    A = np.column_stack([t3.direction[:2], -l2.direction[:2]])
    a, _ = np.linalg.solve(A, (l2.start_mm - t3.start_mm)[:2])
    x, y = (t3.start_mm + a * t3.direction)[:2]
    return FormingError(
        bumps=(GaussianBump(x_mm=float(x), y_mm=float(y), amplitude_mm=-DENT_MM, sigma_mm=40.0),)
    )


@cache
def _inspected(outline: str, dented: bool):
    spec = _spec(outline)
    error = _dent_on_t3_and_l2(spec) if dented else NO_FORMING_ERROR
    scan = synthesize_scan(spec, error, settings=ScanSettings.coarse(), seed=5 if dented else 4)
    design_ship = design_mesh(spec, pitch_mm=2.0).transformed(ship_pose())
    return spec, scan, inspect_cloud(scan.cloud, design_ship, SETTINGS)


@pytest.mark.slow
@pytest.mark.parametrize("outline", sorted(OUTLINES))
def test_a_perfect_plate_of_any_outline_reads_below_0_05_mm_against_its_ship_design(outline: str) -> None:
    _, scan, ins = _inspected(outline, False)
    report = ins.report
    zmax = {line.name: line.zmax_mm for line in report.lines}
    assert len(zmax) == 10 and max(zmax.values()) < 0.05, zmax
    assert report.registration.penetration_points == 0
    assert report.verdict == "pass"
    # the mesh design was moved out of ship coordinates into its own frame, and the report says how
    T = np.asarray(report.design.T_design_file)
    assert report.design.kind == "mesh" and np.linalg.norm(T[:3, 3]) > 10000.0
    # corners within the rectangle's boundary tolerance (the half turn of a parallelogram allowed)
    measured = np.asarray(report.corners_mm)
    truth = scan.corners_bed_mm()
    d = min((np.roll(measured, k, axis=0) - truth for k in (0, 2)), key=lambda e: np.abs(e).max())
    assert np.abs(d[:, :2]).max() < 1.5 and np.abs(d[:, 2]).max() < 0.5, d


@pytest.mark.slow
@pytest.mark.parametrize("outline", sorted(OUTLINES))
def test_a_known_dent_is_found_on_the_lines_through_it_whatever_the_outline(outline: str) -> None:
    _, _, ins = _inspected(outline, True)
    lines = {line.name: line for line in ins.report.lines}
    for name in ("T3", "L2"):
        assert abs(lines[name].zmax_mm - DENT_MM) < 0.1, (name, lines[name].zmax_mm)
    assert ins.report.registration.penetration_points == 0


@pytest.mark.slow
@pytest.mark.parametrize("outline", sorted(OUTLINES))
def test_detection_lines_follow_the_plates_own_edges_in_its_frame(outline: str) -> None:
    spec, _, ins = _inspected(outline, False)
    c = design_corners(spec)
    expected = detection_lines(c, LAYOUT)  # laid out from the design's own corners
    T = plate_frame(c)
    by_name = {line.name: line for line in ins.report.lines}
    for ln in expected:
        name = f"{ln.family[0].upper()}{ln.index}"
        ends = np.vstack([ln.start_mm, ln.end_mm]) @ T[:3, :3].T + T[:3, 3]
        got = np.array([by_name[name].start_plate_mm, by_name[name].end_plate_mm])
        np.testing.assert_allclose(got, ends[:, :2], atol=1.5, err_msg=name)
    plate_c = c @ T[:3, :3].T + T[:3, 3]
    # transverse lines run from the length edge 0-1 to the opposite edge 3-2, parallel to the width
    # edges where those are parallel (a parallelogram), longitudinal ones parallel to the length edges
    for name in ("T1", "T3", "T5"):
        s, e = np.array(by_name[name].start_plate_mm), np.array(by_name[name].end_plate_mm)
        assert abs(s[1]) < 1.5 and abs(e[1] - plate_c[3, 1]) < 1.5, (name, s, e)
        if outline.startswith("parallelogram"):
            side = plate_c[3, :2] - plate_c[0, :2]
            cross = (e - s)[0] * side[1] - (e - s)[1] * side[0]
            assert abs(np.degrees(np.arcsin(cross / np.linalg.norm(e - s) / np.linalg.norm(side)))) < 0.3
    for name in ("L1", "L2", "L3"):
        s, e = np.array(by_name[name].start_plate_mm), np.array(by_name[name].end_plate_mm)
        assert abs(np.degrees(np.arctan2(e[1] - s[1], e[0] - s[0]))) < 0.5, (name, s, e)


@pytest.mark.slow
@pytest.mark.process
def test_cli_inspects_a_parallelogram_against_a_step_design_in_ship_coordinates(
    tmp_path: Path, cellctl_exe: list[str]
) -> None:
    from analysis.design.cad import read_cad
    from analysis.design.cad_write import write_design

    spec = _spec("parallelogram_70")
    scan = synthesize_scan(spec, _dent_on_t3_and_l2(spec), settings=ScanSettings.coarse(), seed=5)
    cloud, _, _ = write_synth(scan, tmp_path / "scan.ply")
    step = write_design(spec, tmp_path / "ship.step", units="m", T_file_design=ship_pose())
    # in process first: the exact STEP surface gives the ship mesh's figures within 0.01 mm
    cad_lines = {ln.name: ln for ln in inspect_cloud(scan.cloud, read_cad(step), SETTINGS).report.lines}
    mesh_ins = inspect_cloud(scan.cloud, design_mesh(spec, pitch_mm=2.0).transformed(ship_pose()), SETTINGS)
    for line in mesh_ins.report.lines:
        for fig in ("zmax_mm", "sz_avg_mm"):
            assert abs(getattr(cad_lines[line.name], fig) - getattr(line, fig)) < 0.01, (line.name, fig)
    (tmp_path / "cell.toml").write_text(
        "[analysis]\ntransverse_count = 5\ntransverse_spacing_mm = 100.0\n"
        "longitudinal_count = 3\nlongitudinal_spacing_mm = 100.0\n"
    )
    r = subprocess.run(
        [*cellctl_exe, "inspect", str(cloud), "--design", str(step), "--out", "out", "--quiet"],
        capture_output=True, text=True, cwd=tmp_path, timeout=600,
    )  # fmt: skip
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert r.returncode == (0 if report["verdict"] == "pass" else 1), r.stderr
    assert report["design"]["format"] == "STEP" and report["design"]["file_units"] == "m"
    lines = {line["name"]: line for line in report["lines"]}
    assert len(lines) == 10
    for name in ("T3", "L2"):
        assert abs(lines[name]["zmax_mm"] - DENT_MM) < 0.1, (name, lines[name]["zmax_mm"])
