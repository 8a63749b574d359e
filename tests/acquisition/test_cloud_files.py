"""PLY, LAS 1.4 (laspy) and E57 (pye57) writers of an assembled scan: fields, types and values survive a read back."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest

from analysis.cloud_export import LAS_SCALE_MM, read_e57, read_las
from analysis.cloud_io import CloudError, read_cloud
from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.cloud_files import write_e57, write_las, write_ply


@pytest.fixture
def cloud():
    rng = np.random.default_rng(5)
    n, w = 40, 30
    xyz = rng.uniform([1000, -500, 200], [2200, 500, 450], (n, w, 3)).astype(np.float32)
    valid = rng.random((n, w)) > 0.2
    xyz[~valid] = np.nan
    return AssembledScan(
        profile_index=np.arange(n, dtype=np.int64),
        frame_index=np.arange(n, dtype=np.uint64) + 100,
        pass_id=np.repeat(np.array([-1, 0, 1, 2], dtype=np.int32), 10),
        t_ns=10**12 + np.arange(n, dtype=np.int64) * 5_000_000,
        xyz_mm=xyz,
        valid=valid,
        sensor_pos_mm=np.zeros((n, 3), np.float32),
    )


def test_ply_holds_float32_xyz_pass_profile_and_point_of_every_valid_point(cloud, tmp_path):
    path = write_ply(cloud, tmp_path / "c.ply")
    v = plyfile.PlyData.read(str(path))["vertex"].data
    pts = cloud.points()
    assert len(v) == cloud.n_valid
    assert v.dtype["x"] == np.float32
    np.testing.assert_array_equal(np.column_stack([v["x"], v["y"], v["z"]]), pts["xyz_mm"])
    np.testing.assert_array_equal(v["pass"], np.maximum(pts["pass_id"], 0))  # transit filed under pass 0
    np.testing.assert_array_equal(v["profile"], pts["profile_index"])
    np.testing.assert_array_equal(v["point"], pts["point_index"])
    assert v["t_s"].min() == 0.0 and v["t_s"].max() == pytest.approx(0.195)


def test_the_acquisition_ply_reads_back_as_the_analysis_cloud_with_transit_in_pass_zero(cloud, tmp_path):
    back = read_cloud(write_ply(cloud, tmp_path / "c.ply"))
    pts = cloud.points()
    assert back.organised and len(back) == cloud.n_valid
    np.testing.assert_array_equal(back.xyz_mm, pts["xyz_mm"].astype(np.float64))
    np.testing.assert_array_equal(back.pass_id, np.maximum(pts["pass_id"], 0))
    np.testing.assert_array_equal(back.profile_index, pts["profile_index"])
    np.testing.assert_allclose(back.t_s, (pts["t_ns"] - cloud.t_ns.min()) * 1e-9)


def test_an_acquisition_ply_of_the_earlier_layout_still_loads(tmp_path):
    """Before one vocabulary: transit as pass -1, point as ushort, times as ``time_s``."""
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pass", "<i4"), ("profile", "<i4"),
                             ("point", "<u2"), ("time_s", "<f8")])  # fmt: skip
    rec["pass"], rec["profile"], rec["point"], rec["time_s"] = (
        [-1, 0, 1],
        [0, 1, 2],
        [5, 6, 7],
        [0.0, 0.1, 0.2],
    )
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nproperty int pass\nproperty int profile\nproperty ushort point\n"
            "property double time_s\nend_header\n")  # fmt: skip
    (tmp_path / "old.ply").write_bytes(head.encode() + rec.tobytes())
    back = read_cloud(tmp_path / "old.ply")
    assert back.pass_id.tolist() == [0, 0, 1] and back.point_index.tolist() == [5, 6, 7]
    np.testing.assert_allclose(back.t_s, [0.0, 0.1, 0.2])


def test_las_through_laspy_holds_every_field_and_names_the_robot_base_frame(cloud, tmp_path):
    import laspy

    path = write_las(cloud, tmp_path / "c.las")
    las = laspy.read(path)  # laspy itself: version, format, the extra dimensions by name
    assert (las.header.version.major, las.header.version.minor, las.header.point_format.id) == (1, 4, 6)
    assert list(las.point_format.extra_dimension_names) == ["pass", "profile", "point"]
    assert "robot base frame" in las.header.system_identifier
    back = read_las(path, require=["pass_id", "profile_index", "point_index", "t_s"])
    pts = cloud.points()
    assert np.max(np.abs(back["xyz_mm"] - pts["xyz_mm"].astype(np.float64))) <= LAS_SCALE_MM / 2 + 1e-4
    np.testing.assert_array_equal(back["pass_id"], np.maximum(pts["pass_id"], 0))
    np.testing.assert_array_equal(back["profile_index"], pts["profile_index"])
    np.testing.assert_array_equal(back["point_index"], pts["point_index"])
    np.testing.assert_allclose(back["t_s"], (pts["t_ns"] - cloud.t_ns.min()) * 1e-9)
    assert "cellctl robot base frame, mm" in str(back["frame"])
    xyz = pts["xyz_mm"]  # the header's bounds enclose the points
    assert np.all(las.header.mins <= xyz.min(axis=0) + 1e-3) and np.all(
        las.header.maxs >= xyz.max(axis=0) - 1e-3
    )


def test_e57_through_pye57_holds_the_points_profile_point_and_time(cloud, tmp_path):
    import pye57

    path = write_e57(cloud, tmp_path / "c.e57")
    raw = pye57.E57(str(path)).read_scan(0, ignore_missing_fields=True, row_column=True)
    pts = cloud.points()
    got = np.column_stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]])
    np.testing.assert_allclose(got, pts["xyz_mm"], atol=1e-3)
    np.testing.assert_array_equal(raw["rowIndex"], pts["profile_index"])
    np.testing.assert_array_equal(raw["columnIndex"], pts["point_index"])
    back = read_e57(path, require=["t_s"])
    np.testing.assert_allclose(back["t_s"], (pts["t_ns"] - cloud.t_ns.min()) * 1e-9)
    np.testing.assert_array_equal(back["pose"], np.eye(4))


def test_reading_a_file_that_is_not_las_names_the_file(tmp_path):
    p = tmp_path / "x.las"
    p.write_bytes(b"PLY\n" + bytes(400))
    with pytest.raises(CloudError, match=r"x\.las"):
        read_las(p)
