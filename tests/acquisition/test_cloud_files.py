"""PLY and LAS 1.4 writers: fields, types and values survive a read back."""

from __future__ import annotations

import struct

import numpy as np
import plyfile
import pytest

from cellctl.acquisition.assembly import ScanCloud
from cellctl.acquisition.cloud_files import LAS_SCALE_MM, CloudFileError, read_las, write_las, write_ply


@pytest.fixture
def cloud():
    rng = np.random.default_rng(5)
    n, w = 40, 30
    xyz = rng.uniform([1000, -500, 200], [2200, 500, 450], (n, w, 3)).astype(np.float32)
    valid = rng.random((n, w)) > 0.2
    xyz[~valid] = np.nan
    return ScanCloud(
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
    np.testing.assert_array_equal(v["pass"], pts["pass_id"])
    np.testing.assert_array_equal(v["profile"], pts["profile_index"])
    np.testing.assert_array_equal(v["point"], pts["point_index"])
    assert v["time_s"].max() == pytest.approx(0.195)


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
    np.testing.assert_array_equal(back["pass_id"], pts["pass_id"])
    np.testing.assert_array_equal(back["profile"], pts["profile_index"])
    np.testing.assert_array_equal(back["point"], pts["point_index"])


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
