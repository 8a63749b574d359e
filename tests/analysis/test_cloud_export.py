"""Cloud files for the metrology tools (analysis.cloud_export, analysis.export): LAS through
laspy, E57 through pye57, PLY with CloudCompare's scalar fields; each read back with its fields by
the library the tools are built on (and CloudCompare's own command line for PLY), the design file's
(ship) frame checked against a known transform, bad files refused by name."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import tracemalloc
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pye57
import pytest

from analysis import cloud_export
from analysis.cloud_export import (
    CloudFrame,
    apply_rigid_blocks,
    read_e57,
    read_las,
    write_e57,
    write_las,
    write_ply_blocks,
)
from analysis.cloud_io import CloudError
from analysis.contracts.results import read_report
from analysis.export import T_file_design, export_results, read_results_cloud, write_lines_ship
from tests.support.results_fixture import write_synthetic_results

FRAME = CloudFrame("test frame", "a frame of this test")


def _rotation_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: design file -> design frame, as report.json's design.T_design_file: a hull plate 42 m aft of
#: midship, 6 m off the centre line, 3.5 m up, turned 30 degrees about z (and the file's z turned over)
T_DESIGN_FILE = np.eye(4)
T_DESIGN_FILE[:3, :3] = _rotation_z(30.0) @ np.diag([1.0, -1.0, -1.0])
T_DESIGN_FILE[:3, 3] = T_DESIGN_FILE[:3, :3] @ -np.array([42_000.0, 6_000.0, 3_500.0])


def _cloud(n: int = 3000) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    dev = rng.normal(0.0, 0.8, n).astype(np.float32)
    dev[::9] = np.nan  # off the design
    return {
        "xyz_mm": rng.uniform([-800, -400, -5], [800, 400, 40], (n, 3)).astype(np.float32),
        "pass_id": (np.arange(n) // 500).astype(np.int32),
        "profile_index": (np.arange(n) // 30).astype(np.int32),
        "point_index": (np.arange(n) % 30).astype(np.int32),
        "t_s": np.arange(n) * 2e-4,
        "deviation_mm": dev,
    }


def _blocks(cloud: dict[str, np.ndarray], cut: int = 1100):
    return lambda: (
        {k: v[lo : lo + cut] for k, v in cloud.items()} for lo in range(0, len(cloud["xyz_mm"]), cut)
    )


def test_las_round_trip_holds_every_field_and_names_the_frame(tmp_path: Path) -> None:
    cloud = _cloud()
    path = write_las(tmp_path / "c.las", _blocks(cloud), FRAME)
    las = laspy.read(path)  # laspy's own view: the extra dimensions by name, the frame in the VLRs
    assert list(las.point_format.extra_dimension_names) == ["pass", "profile", "point", "deviation"]
    assert las.point_format.dimension_by_name("deviation").dtype == np.float32
    assert any(v.record_id == 2112 and 'UNIT["millimetre",0.001]' in v.string for v in las.vlrs)
    np.testing.assert_array_equal(np.asarray(las["deviation"]), cloud["deviation_mm"])
    back = read_las(path, require=["deviation_mm", "pass_id", "profile_index", "point_index", "t_s"])
    np.testing.assert_allclose(back["xyz_mm"], cloud["xyz_mm"], atol=0.0005 + 1e-4)
    for k in ("pass_id", "profile_index", "point_index", "t_s"):
        np.testing.assert_array_equal(back[k], cloud[k])
    np.testing.assert_array_equal(back["deviation_mm"], cloud["deviation_mm"])
    assert str(back["frame"]) == "test frame, mm; a frame of this test"


def test_e57_round_trip_puts_the_deviation_in_the_intensity_and_the_frame_in_the_pose(tmp_path: Path) -> None:
    cloud = _cloud()
    T = np.linalg.inv(T_DESIGN_FILE)  # the scan's own frame (design) -> the file's (ship)
    path = write_e57(tmp_path / "c.e57", _blocks(cloud), FRAME, pose=T, name="P-7")
    ship = cloud["xyz_mm"].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    # pye57's own reader (pose applied, as CloudCompare and other E57 readers do)
    f = pye57.E57(str(path))
    raw = f.read_scan(0, intensity=True, ignore_missing_fields=True, transform=True)
    np.testing.assert_allclose(
        np.column_stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]]), ship, atol=2e-3
    )
    np.testing.assert_array_equal(raw["intensity"], cloud["deviation_mm"])  # mm, unscaled; NaN off the design
    header = f.get_header(0)
    assert header["intensityLimits"]["intensityMinimum"].value() == pytest.approx(
        np.nanmin(cloud["deviation_mm"])
    )
    f.close()
    back = read_e57(path, require=["deviation_mm", "profile_index", "point_index", "t_s"])
    np.testing.assert_allclose(back["xyz_mm"], ship, atol=2e-3)
    np.testing.assert_allclose(back["pose"], T, atol=1e-9)
    np.testing.assert_array_equal(back["deviation_mm"], cloud["deviation_mm"])
    np.testing.assert_array_equal(back["profile_index"], cloud["profile_index"])
    np.testing.assert_array_equal(back["point_index"], cloud["point_index"])
    assert str(back["frame"]).startswith("test frame, mm") and "intensity = deviation in mm" in str(
        back["frame"]
    )


def test_ply_fields_are_cloudcompare_scalar_fields_and_the_header_names_the_frame(tmp_path: Path) -> None:
    cloud = _cloud()
    path = write_ply_blocks(tmp_path / "c.ply", _blocks(cloud), FRAME)
    ply = plyfile.PlyData.read(str(path))
    v = ply["vertex"].data
    assert v.dtype.names == (
        "x",
        "y",
        "z",
        "scalar_pass",
        "scalar_profile",
        "scalar_point",
        "scalar_t_s",
        "scalar_deviation",
    )
    assert v.dtype["scalar_deviation"] == np.float32 and v.dtype["x"] == np.float32
    assert "frame: test frame, mm; a frame of this test" in ply.comments
    np.testing.assert_array_equal(v["scalar_deviation"], cloud["deviation_mm"])
    np.testing.assert_array_equal(np.column_stack([v["x"], v["y"], v["z"]]), cloud["xyz_mm"])


@pytest.fixture
def results(tmp_path: Path) -> Path:
    """A small results directory whose design came from a file in ship coordinates (T_DESIGN_FILE)."""
    out = tmp_path / "results"
    write_synthetic_results(out, n_points=2000)
    doc = json.loads((out / "report.json").read_text())
    doc["design"] = {**doc.get("design", {}), "kind": "cad", "format": "STEP", "file_units": "m",
                     "T_design_file": T_DESIGN_FILE.tolist()}  # fmt: skip
    doc["inputs"]["design"] = "designs/hull-P7.stp"
    (out / "report.json").write_text(json.dumps(doc))
    return out


def test_export_writes_each_format_in_the_design_and_the_ship_frame(results: Path) -> None:
    written = export_results(results)
    assert sorted(written) == ["cloud-ship.e57", "cloud-ship.las", "cloud-ship.ply", "cloud.e57", "cloud.las"]
    xyz, dev = read_results_cloud(results / "cloud.ply")
    T = np.linalg.inv(T_DESIGN_FILE)
    np.testing.assert_allclose(T_file_design(read_report(results)), T, atol=1e-9)
    ship = xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    # the ship frame: the design points moved by the inverse of T_design_file, the deviation with them
    ply = plyfile.PlyData.read(str(written["cloud-ship.ply"]))
    v = ply["vertex"].data
    assert v.dtype["x"] == np.float64  # 42 m from midship: float32 would round to 4 um
    np.testing.assert_allclose(np.column_stack([v["x"], v["y"], v["z"]]), ship, atol=1e-6)
    np.testing.assert_array_equal(v["scalar_deviation"], dev)
    assert any(
        "design file frame (ship)" in c and "hull-P7.stp (file units m), in mm" in c for c in ply.comments
    )
    las = read_las(written["cloud-ship.las"], require=["deviation_mm"])
    np.testing.assert_allclose(las["xyz_mm"], ship, atol=0.0006)
    np.testing.assert_array_equal(las["deviation_mm"], dev)
    assert "design file frame (ship)" in str(las["frame"])
    e57 = read_e57(written["cloud-ship.e57"], require=["deviation_mm"])
    np.testing.assert_allclose(e57["xyz_mm"], ship, atol=1e-3)
    np.testing.assert_array_equal(e57["deviation_mm"], dev)
    design = read_las(written["cloud.las"], require=["deviation_mm"])
    np.testing.assert_allclose(design["xyz_mm"], xyz, atol=0.0006)
    assert "cellctl design frame" in str(design["frame"])


def test_lines_ship_csv_holds_the_line_ends_in_the_design_files_frame(results: Path) -> None:
    report = read_report(results)
    rng = np.random.default_rng(2)
    ends = rng.uniform(-500, 500, (len(report.lines), 2, 3))
    path = write_lines_ship(results / "lines-ship.csv", report, ends)
    text = path.read_text().splitlines()
    assert text[0].startswith("# frame: design file frame (ship), mm; coordinates of hull-P7.stp")
    rows = list(csv.DictReader(text[1:]))
    assert [r["line"] for r in rows] == [ln.name for ln in report.lines]
    T = np.linalg.inv(T_DESIGN_FILE)
    want = ends.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    got = np.array(
        [[float(r[f"{e}_{a}_mm"]) for e in ("start", "end") for a in "xyz"] for r in rows]
    ).reshape(-1, 3)
    np.testing.assert_allclose(got, want, atol=5e-4)


def test_the_export_holds_no_copy_of_the_cloud(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A memory-mapped cloud.ply of 400 k points (16 B each) exported to every file, 16 k points a
    block (a real export: 256 k of a plate's tens of millions): the export's own allocations stay
    below one float32 copy of the points (12 B a point)."""
    monkeypatch.setattr(cloud_export, "BLOCK_POINTS", 1 << 14)
    n = 400_000
    out = tmp_path / "results"
    write_synthetic_results(out, n_points=500)
    rng = np.random.default_rng(1)
    cloud = {
        "xyz_mm": rng.uniform(-3000, 3000, (n, 3)).astype(np.float32),
        "deviation_mm": rng.normal(0, 1, n).astype(np.float32),
    }
    write_ply_blocks(out / "cloud.ply", _blocks(cloud, 1 << 17), FRAME)
    del cloud
    tracemalloc.start()
    try:
        export_results(out, tmp_path / "x")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 12 * n, f"peak {peak / 1e6:.1f} MB for {n} points"
    assert len(read_las(tmp_path / "x" / "cloud-ship.las")["xyz_mm"]) == n


def test_bad_files_are_refused_with_the_file_and_what_is_wrong(tmp_path: Path) -> None:
    cloud = _cloud()
    las = write_las(tmp_path / "c.las", _blocks(cloud), FRAME)
    data = las.read_bytes()
    (tmp_path / "cut.las").write_bytes(data[: len(data) - 500])
    with pytest.raises(CloudError, match=r"cut\.las: .*(truncated|not a readable)"):
        read_las(tmp_path / "cut.las")
    bare = write_las(tmp_path / "bare.las", _blocks({"xyz_mm": cloud["xyz_mm"]}), FRAME)
    with pytest.raises(CloudError, match=r"bare\.las: no deviation_mm in the file"):
        read_las(bare, require=["deviation_mm"])
    e57 = write_e57(tmp_path / "c.e57", _blocks(cloud), FRAME).read_bytes()
    (tmp_path / "cut.e57").write_bytes(e57[: len(e57) // 2])
    with pytest.raises(CloudError, match=r"cut\.e57: not a readable E57 file"):
        read_e57(tmp_path / "cut.e57")
    bare_e57 = write_e57(tmp_path / "bare.e57", _blocks({"xyz_mm": cloud["xyz_mm"]}), FRAME)
    with pytest.raises(CloudError, match=r"bare\.e57: no deviation_mm"):
        read_e57(bare_e57, require=["deviation_mm"])
    plain = write_ply_blocks(tmp_path / "plain.ply", _blocks({"xyz_mm": cloud["xyz_mm"]}), FRAME)
    with pytest.raises(
        CloudError, match=r"plain\.ply: not a results cloud: needs x, y, z and scalar_deviation"
    ):
        read_results_cloud(plain)
    with pytest.raises(CloudError, match="an E57 pose must be a rotation"):
        write_e57(tmp_path / "m.e57", _blocks(cloud), FRAME, pose=np.diag([1.0, 1.0, -1.0, 1.0]))
    assert not (tmp_path / "m.e57").exists() and not (tmp_path / ".m.e57.tmp").exists()


def test_moving_blocks_cuts_a_whole_cloud_into_slices() -> None:
    cloud = _cloud(1000)
    T = np.linalg.inv(T_DESIGN_FILE)
    parts = list(apply_rigid_blocks(lambda: iter([cloud]), T, block_points=300)())
    assert [len(p["xyz_mm"]) for p in parts] == [300, 300, 300, 100]
    np.testing.assert_allclose(
        np.vstack([p["xyz_mm"] for p in parts]), cloud["xyz_mm"] @ T[:3, :3].T + T[:3, 3]
    )


CLOUDCOMPARE = shutil.which("CloudCompare")


@pytest.mark.process
@pytest.mark.skipif(
    CLOUDCOMPARE is None, reason="CloudCompare not installed (scripts/setup.sh installs Debian's)"
)
def test_cloudcompare_reads_the_ply_exports_scalar_fields(results: Path, tmp_path: Path) -> None:
    """CloudCompare's command line (headless, Qt offscreen) opens cloud.ply and cloud-ship.ply and
    saves them as ASCII with a header: the deviation comes back as its scalar field ``deviation``.
    (Debian's CloudCompare 2.11 has no LAS or E57 plugin: those are checked through laspy and pye57.)"""
    written = export_results(results, formats=("ply",), frames=("ship",))
    _, dev = read_results_cloud(results / "cloud.ply")
    T = np.linalg.inv(T_DESIGN_FILE)
    for src in (results / "cloud.ply", written["cloud-ship.ply"]):
        asc = tmp_path / f"{src.stem}.asc"
        run = subprocess.run(
            [CLOUDCOMPARE, "-SILENT", "-O", str(src), "-C_EXPORT_FMT", "ASC", "-ADD_HEADER", "-PREC", "6",
             "-SAVE_CLOUDS", "FILE", str(asc)],
            env={**os.environ, "QT_QPA_PLATFORM": "offscreen"}, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert run.returncode == 0 and asc.exists(), run.stdout + run.stderr
        lines = asc.read_text().splitlines()
        assert lines[0].lstrip("/").split() == ["X", "Y", "Z", "deviation"]
        got = np.loadtxt(lines[1:])
        np.testing.assert_allclose(got[:, 3], dev, atol=1e-6)  # NaN where NaN
        if src.stem == "cloud-ship":  # CloudCompare holds points in float32: ~4 um at 42 m
            xyz, _ = read_results_cloud(results / "cloud.ply")
            np.testing.assert_allclose(got[:, :3], xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3], atol=0.02)


def test_a_las_file_of_the_earlier_hand_written_writer_still_reads_its_pass(tmp_path: Path) -> None:
    """Before laspy, `cellctl reassemble` wrote the pass + 1 in point_source_id (0 for transit) and
    only profile and point as extra bytes; such a file reads with its passes."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.generating_software = "cellctl acquisition"
    header.add_extra_dims(
        [laspy.ExtraBytesParams("profile", np.uint32), laspy.ExtraBytesParams("point", np.uint16)]
    )
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]).T
    las.point_source_id = np.array([0, 1, 3], dtype=np.uint16)
    las.profile = np.array([0, 1, 2], dtype=np.uint32)
    las.write(tmp_path / "old.las")
    back = read_las(tmp_path / "old.las", require=["pass_id", "profile_index"])
    assert back["pass_id"].tolist() == [0, 0, 2] and back["profile_index"].tolist() == [0, 1, 2]


def test_a_design_file_frame_that_is_mirrored_gets_its_e57_points_moved_instead_of_a_pose(
    results: Path,
) -> None:
    doc = json.loads((results / "report.json").read_text())
    mirrored = np.diag([1.0, -1.0, 1.0, 1.0])  # a file with a left-handed frame: no E57 pose reaches it
    mirrored[:3, 3] = [-42_000.0, 0.0, 0.0]
    doc["design"]["T_design_file"] = mirrored.tolist()
    (results / "report.json").write_text(json.dumps(doc))
    written = export_results(results, formats=("e57",), frames=("ship",))
    xyz, dev = read_results_cloud(results / "cloud.ply")
    T = np.linalg.inv(mirrored)
    back = read_e57(written["cloud-ship.e57"], require=["deviation_mm"])
    np.testing.assert_array_equal(back["pose"], np.eye(4))
    np.testing.assert_allclose(back["xyz_mm"], xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3], atol=5e-3)
    np.testing.assert_array_equal(back["deviation_mm"], dev)
