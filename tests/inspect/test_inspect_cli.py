"""`cellctl inspect` as a user runs it: synthetic scans with known truth, and bad inputs."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.process  # the console script in a subprocess

SMALL_PLATE = ["--length-mm", "600", "--width-mm", "400", "--profile-step-mm", "2",
               "--point-pitch-mm", "0.4", "--points-per-profile", "125"]  # fmt: skip
SMALL_LAYOUT = (
    "[analysis]\ntransverse_count = 5\ntransverse_spacing_mm = 100.0\n"
    "longitudinal_count = 3\nlongitudinal_spacing_mm = 100.0\n"
)


def _run(exe: list[str], *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*exe, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory: pytest.TempPathFactory, cellctl_exe: list[str]) -> Path:
    d = tmp_path_factory.mktemp("scan")
    r = _run(
        cellctl_exe, "synth", "--plate", "sail", *SMALL_PLATE, "--seed", "1", "--out", str(d / "scan.ply")
    )
    assert r.returncode == 0, r.stderr
    (d / "cell.toml").write_text(SMALL_LAYOUT)
    return d


@pytest.mark.slow
def test_inspect_writes_results_and_exit_code_follows_the_verdict(
    small_scan: Path, cellctl_exe: list[str]
) -> None:
    out = small_scan / "out"
    r = _run(cellctl_exe, "inspect", str(small_scan / "scan.ply"), "--design", str(small_scan / "scan-design.ply"),
             "--out", str(out), "--config", str(small_scan / "cell.toml"), "--plate-id", "P-17")  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    assert r.returncode == (0 if report["verdict"] == "pass" else 1), r.stderr
    for name in ("report.json", "report.csv", "results.npz", "cloud.ply", "report.html", "report.pdf"):
        assert (out / name).stat().st_size > 0, name
    assert report["plate_id"] == "P-17"
    assert [line["name"] for line in report["lines"]] == [
        "T1",
        "T2",
        "T3",
        "T4",
        "T5",
        "L1",
        "L2",
        "L3",
        "D1",
        "D2",
    ]
    assert report["registration"]["penetration_points"] == 0
    # The printed table has one row per line and the verdict.
    assert all(line["name"] in r.stdout for line in report["lines"])
    assert f"verdict: {report['verdict'].upper()}" in r.stdout
    # The known forming error: the truth's dent is found where it is, as a plate below the template.
    truth = json.loads((small_scan / "scan-truth.json").read_text())
    assert truth["forming_error"]["bumps"], "the default forming error has dents/bumps"
    res = np.load(out / "results.npz")
    # non-penetrating: the design rests on the plate, on its raised edges too (the default forming
    # error's 1 mm springback; docs/metrology.md, "Edges"): nowhere is the plate more than 0.1 mm
    # above the template
    assert res["plate_deviation_mm"].min() > -0.1


def _inspect_error(exe: list[str], tmp: Path, cloud: Path, design: Path) -> str:
    r = _run(exe, "inspect", str(cloud), "--design", str(design), "--out", str(tmp / "o"))
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("cellctl inspect:")]
    assert len(lines) == 1, r.stderr
    return lines[0]


def test_missing_cloud_file(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    msg = _inspect_error(cellctl_exe, tmp_path, tmp_path / "nope.ply", small_scan / "scan-design.ply")
    assert "nope.ply" in msg


def test_empty_cloud_file(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    (tmp_path / "empty.xyz").write_text("")
    msg = _inspect_error(cellctl_exe, tmp_path, tmp_path / "empty.xyz", small_scan / "scan-design.ply")
    assert "empty.xyz" in msg


def test_unreadable_design(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    (tmp_path / "d.stl").write_bytes(b"\x00garbage")
    msg = _inspect_error(cellctl_exe, tmp_path, small_scan / "scan.ply", tmp_path / "d.stl")
    assert "d.stl" in msg


def test_cloud_with_no_plate(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    rng = np.random.default_rng(0)
    np.savetxt(tmp_path / "noise.xyz", rng.uniform(-500, 500, size=(20_000, 3)))
    msg = _inspect_error(cellctl_exe, tmp_path, tmp_path / "noise.xyz", small_scan / "scan-design.ply")
    assert "plate" in msg.lower()


@pytest.mark.slow
def test_design_of_another_size_is_refused(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    from analysis.design.mesh import save_mesh
    from analysis.design.plates import design_mesh, plate_spec

    big = save_mesh(
        design_mesh(plate_spec("sail", length_mm=1200, width_mm=800), pitch_mm=10), tmp_path / "big.ply"
    )
    msg = _inspect_error(cellctl_exe, tmp_path, small_scan / "scan.ply", big)
    assert "does not match the plate" in msg and "600 x 400" in msg


def test_bad_placement_is_refused(cellctl_exe: list[str], tmp_path: Path, small_scan: Path) -> None:
    r = _run(cellctl_exe, "inspect", str(small_scan / "scan.ply"), "--design", str(small_scan / "scan-design.ply"),
             "--out", str(tmp_path / "o"), "--placement", "1,2")  # fmt: skip
    assert r.returncode == 2 and "--placement '1,2': expected X,Y,ANGLE_DEG" in r.stderr
