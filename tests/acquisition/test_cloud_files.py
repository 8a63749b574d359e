"""PLY and LAS 1.4 writers: fields, types and values survive a read back."""

from __future__ import annotations

import struct

import numpy as np
import plyfile
import pytest

from analysis.cloud_io import read_cloud
from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.cloud_files import LAS_SCALE_MM, CloudFileError, read_las, write_las, write_ply


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


def test_las_is_version_1_4_format_6_with_extra_bytes_and_micrometre_coordinates(cloud, tmp_path):
    path = write_las(cloud, tmp_path / "c.las")
    data = path.read_bytes()
    assert data[:4] == b"LASF" and data[24:26] == b"\x01\x04"
    header_size, offset, n_vlr, fmt, reclen = struct.unpack_from("<HIIBH", data, 94)
    assert (header_size, n_vlr, fmt, reclen) == (375, 1, 6, 36)
    assert data[375 + 2 : 375 + 11] == b"LASF_Spec" and struct.unpack_from("<H", data, 375 + 18)[0] == 4
    (n,) = struct.unpack_from("<Q", data, 247)
    assert n == cloud.n_valid and len(data) == offset + 36 * n
    back = read_las(path)
    pts = cloud.points()
    assert np.max(np.abs(back["xyz_mm"] - pts["xyz_mm"].astype(np.float64))) <= LAS_SCALE_MM / 2 + 1e-4
    np.testing.assert_array_equal(back["pass_id"], np.maximum(pts["pass_id"], 0))
    np.testing.assert_array_equal(back["profile_index"], pts["profile_index"])
    np.testing.assert_array_equal(back["point_index"], pts["point_index"])
    np.testing.assert_allclose(back["t_s"], (pts["t_ns"] - cloud.t_ns.min()) * 1e-9)


def test_las_bounds_in_the_header_enclose_the_points(cloud, tmp_path):
    data = write_las(cloud, tmp_path / "c.las").read_bytes()
    mx, mn_x, my, mn_y, mz, mn_z = struct.unpack_from("<6d", data, 179)
    xyz = cloud.points()["xyz_mm"]
    assert mn_x <= xyz[:, 0].min() and mx >= xyz[:, 0].max()
    assert mn_y <= xyz[:, 1].min() and my >= xyz[:, 1].max()
    assert mn_z <= xyz[:, 2].min() and mz >= xyz[:, 2].max()


def test_reading_a_file_that_is_not_las_names_the_file(tmp_path):
    p = tmp_path / "x.las"
    p.write_bytes(b"PLY\n" + bytes(400))
    with pytest.raises(CloudFileError, match=r"x\.las"):
        read_las(p)
