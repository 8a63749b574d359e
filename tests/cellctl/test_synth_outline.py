"""`cellctl synth` with a non-rectangular outline (issue 18 item 3), called in-process.

The written design (mesh, and the IGES / STEP of --cad) is read back and its corners found from its
own outline; their angles must be the ones asked for on the command line. The CLI runs
in-process; only reading the CAD files back starts a (forked) process.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from analysis.design.cad import read_design
from analysis.design.mesh import load_mesh
from analysis.design.outline import design_corners_from_mesh
from cellctl.cli import main

# a small, coarse scan: the test is about the outline, not the scan
QUICK = ["--length-mm", "600", "--width-mm", "400", "--point-pitch-mm", "1", "--points-per-profile", "50",
         "--profile-step-mm", "4", "--seed", "3"]  # fmt: skip
L_MM, W_MM = 600.0, 400.0


def _synth(*args: str) -> int:
    return main(["--log-format", "json", "--log-level", "WARNING", "synth", *QUICK, *args])


def _corner_angles_deg(corners: np.ndarray) -> np.ndarray:
    """Interior angle in plan at each of the four corners (in their order)."""
    c = np.asarray(corners)[:, :2]
    out = []
    for k in range(4):
        a, b = c[(k - 1) % 4] - c[k], c[(k + 1) % 4] - c[k]
        out.append(np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))))
    return np.array(out)


def _expected_angles_deg(corner0_deg: float, top_mm: float) -> np.ndarray:
    """Corners 0-3 of a trapezoid: edge 0 along +x (L_MM), edge 2 parallel W_MM away, top_mm long."""
    dx = W_MM / np.tan(np.radians(corner0_deg)) + top_mm - L_MM  # x run of edge 1 (corner 1 -> 2)
    corner1 = 180.0 - np.degrees(np.arctan2(W_MM, dx))
    return np.array([corner0_deg, corner1, 180.0 - corner1, 180.0 - corner0_deg])


def _matches_cyclically(measured: np.ndarray, expected: np.ndarray, tol_deg: float) -> bool:
    # the project's corner order picks corner 0 by its own convention; the angles' cycle is what counts
    return any(np.abs(np.roll(measured, s) - expected).max() <= tol_deg for s in range(4))


@pytest.mark.process  # reading the IGES / STEP back forks the CAD reader
@pytest.mark.slow
def test_parallelogram_from_the_command_line_with_cad(tmp_path: Path) -> None:
    out = tmp_path / "para.ply"
    assert _synth("--corner-angle-deg", "72", "--cad", "--out", str(out)) == 0
    expected = _expected_angles_deg(72.0, L_MM)
    np.testing.assert_allclose(expected, [72, 108, 72, 108])
    corners = design_corners_from_mesh(load_mesh(tmp_path / "para-design.ply"))
    assert _matches_cyclically(_corner_angles_deg(corners), expected, 0.5), _corner_angles_deg(corners)
    cad = read_design(tmp_path / "para-design.step")
    assert _matches_cyclically(_corner_angles_deg(cad.corners_mm), expected, 0.5)
    # not the rectangle: the sides are sheared by W / tan(72 deg) = 130 mm
    assert np.ptp(corners[:, 0]) == pytest.approx(L_MM + W_MM / np.tan(np.radians(72.0)), abs=2.0)


@pytest.mark.process  # reading the IGES / STEP back forks the CAD reader
@pytest.mark.slow
def test_bowed_trapezoid_from_the_command_line_with_cad(tmp_path: Path) -> None:
    out = tmp_path / "trap.ply"
    rc = _synth("--corner-angle-deg", "80", "--top-length-mm", "480", "--bow-mm", "8,0,-6,4", "--cad",
                "--out", str(out))  # fmt: skip
    assert rc == 0
    expected = _expected_angles_deg(80.0, 480.0)
    assert abs(expected[1] - 100.0) > 10.0  # a real trapezoid: corner 1 is not corner 0's supplement
    corners = design_corners_from_mesh(load_mesh(tmp_path / "trap-design.ply"))
    assert _matches_cyclically(_corner_angles_deg(corners), expected, 0.5), _corner_angles_deg(corners)
    cad = read_design(tmp_path / "trap-design.igs")
    assert _matches_cyclically(_corner_angles_deg(cad.corners_mm), expected, 0.5)
    # edge 0 is bowed 8 mm outward (-y): the outline's lowest point lies 8 mm beyond the corners'
    assert cad.boundary_mm[:, 1].min() == pytest.approx(corners[:, 1].min() - 8.0, abs=0.3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--corner-angle-deg", "125"], "--corner-angle-deg 125: outside 60-120 degrees"),
        (["--corner-angle-deg", "nan"], "--corner-angle-deg nan: outside 60-120 degrees"),
        (["--top-length-mm", "0"], "--top-length-mm 0: must be a positive length"),
        (["--top-length-mm", "100"], "--top-length-mm 100: the corner at corner 1 would be"),
        (["--bow-mm", "13,0,0,0"], "--bow-mm: edge 0's bow 13 mm exceeds 2 % of its 600.0 mm length"),
        (["--bow-mm", "1,2,3"], "--bow-mm: four comma-separated bows in mm (edges 0-3) expected"),
    ],
)
def test_out_of_range_outline_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    out = tmp_path / "bad.ply"
    assert _synth(*args, "--cad", "--out", str(out)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"cellctl synth: {message}"), err
    assert "\n" not in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # refused before anything is written


def test_help_documents_the_outline_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["synth", "--help"]) == 0
    text = capsys.readouterr().out
    for option in ("--corner-angle-deg", "--top-length-mm", "--bow-mm", "60-120", "2%"):
        assert option in text
