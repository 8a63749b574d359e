"""Inspecting against IGES and STEP designs: the same figures as against the fine mesh, a known dent
found, a design in ship coordinates read in its own frame; the command line end to end."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.settings import InspectionSettings
from analysis.design.cad import read_cad
from analysis.design.cad_write import write_design
from analysis.design.plates import FormingError, GaussianBump, design_mesh, plate_spec
from analysis.pipeline import inspect_cloud
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout
from tests.support.surfaces import ship_pose

SETTINGS = InspectionSettings(layout=DetectionLayout(5, 100.0, 3, 100.0, True))
DENT_MM = 1.5


@pytest.fixture(scope="module")
def dented(tmp_path_factory: pytest.TempPathFactory):
    # a dent on transverse line 3 (x = 0) and longitudinal line 2 (y = 0)
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    error = FormingError(bumps=(GaussianBump(x_mm=0.0, y_mm=0.0, amplitude_mm=-DENT_MM, sigma_mm=40.0),))
    scan = synthesize_scan(spec, error, settings=ScanSettings.coarse(), seed=5)
    d = tmp_path_factory.mktemp("cad")
    files = {
        "iges": write_design(spec, d / "plate.igs"),
        "step_m": write_design(spec, d / "plate.step", units="m"),
        "step_ship": write_design(spec, d / "ship.step", units="m", T_file_design=ship_pose()),
    }
    return spec, scan, files


@pytest.mark.slow
def test_iges_and_step_designs_give_the_mesh_figures_and_find_the_dent(dented) -> None:
    spec, scan, files = dented
    ref = inspect_cloud(scan.cloud, design_mesh(spec, pitch_mm=2.0), SETTINGS).report
    ref_lines = {line.name: line for line in ref.lines}
    assert ref.design.kind == "mesh" and ref.design.templates == "mesh"
    for name, path in files.items():
        report = inspect_cloud(scan.cloud, read_cad(path), SETTINGS).report
        assert report.design.kind == "cad" and report.design.templates == "exact surface"
        assert report.registration.penetration_points == 0
        lines = {line.name: line for line in report.lines}
        assert lines.keys() == ref_lines.keys(), name
        for k, line in lines.items():
            for fig in ("zmax_mm", "sz_avg_mm"):
                got, want = getattr(line, fig), getattr(ref_lines[k], fig)
                assert abs(got - want) < 0.01, (name, k, fig, got, want)
            np.testing.assert_allclose(line.start_plate_mm, ref_lines[k].start_plate_mm, atol=0.5)
        for k in ("T3", "L2"):
            assert abs(lines[k].zmax_mm - DENT_MM) < 0.1, (name, k, lines[k].zmax_mm)


@pytest.mark.slow
def test_cli_synth_cad_design_check_inspect_and_plan(
    tmp_path: Path, cellctl_exe: list[str], repo_root
) -> None:
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*cellctl_exe, *args], capture_output=True, text=True, cwd=tmp_path, timeout=600
        )

    small = ["--length-mm", "600", "--width-mm", "400", "--profile-step-mm", "2", "--point-pitch-mm", "0.4",
             "--points-per-profile", "125"]  # fmt: skip
    r = run("synth", "--plate", "sail", *small, "--seed", "2", "--cad", "--out", "scan.ply")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "scan-design.igs").is_file() and (tmp_path / "scan-design.step").is_file()

    (tmp_path / "cell.toml").write_text(
        "[analysis]\ntransverse_count = 5\ntransverse_spacing_mm = 100.0\n"
        "longitudinal_count = 3\nlongitudinal_spacing_mm = 100.0\n"
    )
    r = run("design", "check", "scan-design.step", "--thickness", "15", "--json", "--preview", "p.png")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["format"] == "STEP" and s["file_units"] == "mm" and s["faces"] == 1
    np.testing.assert_allclose(s["size_mm"], [600, 400], atol=0.01)
    assert len(s["lines"]) == 10 and s["lines"][0]["name"] == "T1" and "other_side" in s
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    r = run("inspect", "scan.ply", "--design", "scan-design.igs", "--out", "out", "--quiet")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert r.returncode == (0 if report["verdict"] == "pass" else 1), r.stderr
    assert report["design"]["format"] == "IGES" and len(report["lines"]) == 10

    data = (tmp_path / "scan-design.igs").read_bytes()
    (tmp_path / "cut.igs").write_bytes(data[: len(data) // 2])
    for args in (
        ("design", "check", "cut.igs"),
        ("inspect", "scan.ply", "--design", "cut.igs", "--out", "o2"),
    ):
        r = run(*args)
        assert r.returncode == 2
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and "cut.igs" in err[0] and "truncated" in err[0], r.stderr

    r = run("--log-level", "WARNING", "plan", "--design", "scan-design.step", "--placement", "1600,100,3",
            "--config", str(repo_root / "cell.toml"), "--no-coverage")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "scan time:" in r.stdout
