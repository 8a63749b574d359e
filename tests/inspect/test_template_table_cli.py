"""The yard's template table through the command line: `inspect` and `design check --template-table`."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.process  # the console script in a subprocess

SMALL_PLATE = ["--length-mm", "600", "--width-mm", "400", "--profile-step-mm", "2",
               "--point-pitch-mm", "0.4", "--points-per-profile", "125"]  # fmt: skip
TABLE = "name,edge,distance_mm,angle_deg\nFR101,0-3,120,90\nFR102,1-2,150,90\nLK-7,0-1,180,90\nSKEW-2,0-3,250,75\n"
NAMES = ["FR101", "FR102", "LK-7", "SKEW-2"]


def _run(exe: list[str], *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*exe, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory: pytest.TempPathFactory, cellctl_exe: list[str]) -> Path:
    d = tmp_path_factory.mktemp("table")
    r = _run(cellctl_exe, "synth", "--plate", "sail", *SMALL_PLATE, "--seed", "3", "--out", "scan.ply", cwd=d)
    assert r.returncode == 0, r.stderr
    (d / "cell.toml").write_text(
        "[analysis]\ntransverse_count = 3\ntransverse_spacing_mm = 150.0\n"
        "longitudinal_count = 0\nlongitudinal_spacing_mm = 100.0\ndiagonals = false\n"
    )
    (d / "table.csv").write_text(TABLE)
    return d


@pytest.mark.slow
def test_the_tables_lines_appear_in_the_report_under_their_names(
    scan_dir: Path, cellctl_exe: list[str]
) -> None:
    r = _run(cellctl_exe, "inspect", "scan.ply", "--design", "scan-design.ply", "--out", "out",
             "--template-table", "table.csv", cwd=scan_dir)  # fmt: skip
    report = json.loads((scan_dir / "out" / "report.json").read_text())
    assert r.returncode == (0 if report["verdict"] == "pass" else 1), r.stderr
    lines = {ln["name"]: ln for ln in report["lines"]}
    assert list(lines) == ["T1", "T2", "T3", *NAMES]  # the equal spacing, then the table
    assert lines["FR101"]["family"] == "transverse" and lines["FR101"]["position_mm"] == pytest.approx(120)
    assert lines["FR101"]["start_plate_mm"] == pytest.approx([120, 0], abs=1.0)
    assert lines["FR102"]["start_plate_mm"][0] == pytest.approx(450, abs=1.0)  # 150 mm from the far edge
    assert lines["LK-7"]["family"] == "longitudinal" and lines["LK-7"]["start_plate_mm"][1] == pytest.approx(
        180, abs=1.0
    )
    # FR102 lies where T3 does (450 mm): the same section, the same figures
    for key in ("zmax_mm", "sz_avg_mm", "ci", "length_mm"):
        assert lines["FR102"][key] == pytest.approx(lines["T3"][key], abs=1e-3), key
    html = (scan_dir / "out" / "report.html").read_text()
    for name in NAMES:
        assert f'data-line="{name}"' in html
        assert name in r.stdout  # the printed table


@pytest.mark.slow
def test_design_check_lists_the_tables_lines(scan_dir: Path, cellctl_exe: list[str]) -> None:
    r = _run(cellctl_exe, "design", "check", "scan-design.ply", "--template-table", "table.csv", "--json",
             "--no-preview", cwd=scan_dir)  # fmt: skip
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert [ln["name"] for ln in s["lines"]] == ["T1", "T2", "T3", *NAMES]
    r = _run(cellctl_exe, "design", "check", "scan-design.ply", "--template-table", "table.csv", "--no-preview",
             cwd=scan_dir)  # fmt: skip
    assert r.returncode == 0 and "SKEW-2" in r.stdout


@pytest.mark.parametrize(
    ("table", "reason"),
    [
        ("name,distance_mm\nA,100\n", "missing column 'edge'"),
        ("name,edge,distance_mm\nA,bow,100\n", "line 2: unknown edge 'bow'"),
        ("name,edge,distance_mm\nA,0-1,401\n", "template A: 401 mm from edge 0-1 lies outside the plate"),
        ("name,edge,distance_mm\nA,0-3,1o0\n", "line 2: distance '1o0' is not a number"),
    ],
)
def test_a_bad_table_is_refused_with_its_reason(
    scan_dir: Path, cellctl_exe: list[str], table: str, reason: str
) -> None:
    (scan_dir / "bad.csv").write_text(table)
    for cmd, args in (
        ("design check", ("design", "check", "scan-design.ply", "--no-preview")),
        ("inspect", ("inspect", "scan.ply", "--design", "scan-design.ply", "--out", "bad-out")),
    ):
        r = _run(cellctl_exe, *args, "--template-table", "bad.csv", cwd=scan_dir)
        assert r.returncode == 2, r.stdout + r.stderr
        assert "Traceback" not in r.stderr
        err = [ln for ln in r.stderr.splitlines() if ln.startswith(f"cellctl {cmd}:")]
        assert len(err) == 1 and reason in err[0], r.stderr


def test_inspect_refuses_moulded_side_down_without_a_thickness(
    scan_dir: Path, cellctl_exe: list[str]
) -> None:
    r = _run(cellctl_exe, "inspect", "scan.ply", "--design", "scan-design.ply", "--out", "side-out",
             "--design-side", "moulded_down", cwd=scan_dir)  # fmt: skip
    assert r.returncode == 2 and "Traceback" not in r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("cellctl inspect:")]
    assert len(err) == 1 and "needs its thickness" in err[0], r.stderr


@pytest.mark.slow
def test_the_compared_fit_names_the_lines_as_the_table_does() -> None:
    from analysis.contracts.settings import InspectionSettings
    from analysis.design.plates import plate_spec
    from analysis.design.template_table import parse_template_table
    from analysis.pipeline import inspect_cloud
    from analysis.synth import ScanSettings, synthesize_scan
    from analysis.templates import DetectionLayout

    spec = plate_spec("sail", length_mm=600, width_mm=400)
    scan = synthesize_scan(spec, settings=ScanSettings.coarse(), seed=3)
    layout = DetectionLayout(2, 200.0, 0, 100.0, False, templates=parse_template_table(TABLE))
    settings = InspectionSettings(layout=layout, template_fit_compare=True)
    report = inspect_cloud(scan.cloud, scan.design_mesh(2.0), settings).report
    main = [ln.name for ln in report.lines]
    other = [ln.name for ln in report.template_fit_compare.lines]
    assert main == ["T1", "T2", *NAMES]
    assert set(other) <= set(main) and set(NAMES) & set(other), other  # not T*/L* for the table's lines
    assert not {"T3", "T4", "L1"} & set(other), other
