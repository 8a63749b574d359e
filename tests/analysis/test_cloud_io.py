"""Reading and writing scan clouds, and the clear errors for files that cannot be used."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from analysis.cloud_io import CloudError, ScanCloud, read_cloud, write_cloud_npz, write_cloud_ply


def _organised(n: int = 500, seed: int = 0) -> ScanCloud:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-700, 700, (n, 3))
    return ScanCloud(pts, rng.integers(0, 20, n), rng.integers(0, 3000, n), rng.integers(0, 500, n))


def test_organised_ply_round_trips_points_and_organisation(tmp_path):
    cloud = _organised()
    back = read_cloud(write_cloud_ply(cloud, tmp_path / "scan.ply"))
    assert back.organised
    np.testing.assert_allclose(back.xyz_mm, cloud.xyz_mm.astype(np.float32), rtol=0, atol=0)
    for name in ("pass_id", "profile_index", "point_index"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name))


def test_ply_carries_times_and_extra_columns_after_the_organisation(tmp_path):
    cloud = _organised(50)
    timed = ScanCloud(
        cloud.xyz_mm, cloud.pass_id, cloud.profile_index, cloud.point_index, np.arange(50) * 0.005
    )
    dev = np.linspace(-1, 1, 50).astype(np.float32)
    path = write_cloud_ply(timed, tmp_path / "t.ply", extra={"deviation": dev})
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert header.index("int point") < header.index("double t_s") < header.index("float deviation")
    back = read_cloud(path)
    np.testing.assert_array_equal(back.t_s, timed.t_s)
    np.testing.assert_array_equal(back.point_index, cloud.point_index)


def test_npz_of_the_earlier_names_still_loads(tmp_path):
    pts = np.arange(12, dtype=np.float64).reshape(4, 3)
    np.savez(
        tmp_path / "old.npz", points_mm=pts, pass_id=[-1, 0, 0, 1], profile=[0, 1, 2, 3], point=[4, 4, 5, 5]
    )
    back = read_cloud(tmp_path / "old.npz")
    np.testing.assert_array_equal(back.xyz_mm, pts)
    assert back.pass_id.tolist() == [0, 0, 0, 1] and back.point_index.tolist() == [4, 4, 5, 5]


def test_ply_header_names_float_xyz_and_int_pass_profile_point(tmp_path):
    path = write_cloud_ply(_organised(10), tmp_path / "scan.ply")
    header = path.read_bytes().split(b"end_header")[0].decode()
    for prop in ("float x", "float y", "float z", "int pass", "int profile", "int point"):
        assert f"property {prop}\n" in header


def test_unorganised_double_ascii_ply_written_by_plyfile_reads_as_unorganised(tmp_path):
    from plyfile import PlyData, PlyElement

    pts = np.random.default_rng(1).normal(size=(50, 3))
    rec = np.array([tuple(p) for p in pts], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    PlyData([PlyElement.describe(rec, "vertex")], text=True).write(str(tmp_path / "a.ply"))
    back = read_cloud(tmp_path / "a.ply")
    assert not back.organised
    np.testing.assert_allclose(back.xyz_mm, pts, rtol=1e-6)


@settings(max_examples=25, deadline=None)
@given(pts=arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)), elements=st.floats(-1e4, 1e4)))
def test_npz_round_trips_any_finite_cloud_exactly(tmp_path_factory, pts):
    path = tmp_path_factory.mktemp("npz") / "c.npz"
    back = read_cloud(write_cloud_npz(ScanCloud(pts), path))
    np.testing.assert_array_equal(back.xyz_mm, pts)
    assert not back.organised


def test_organised_npz_keeps_organisation(tmp_path):
    cloud = _organised(30)
    back = read_cloud(write_cloud_npz(cloud, tmp_path / "c.npz"))
    np.testing.assert_array_equal(back.profile_index, cloud.profile_index)


def _pcd_header(n: int, data: str, fields="x y z", size="4 4 4", typ="F F F") -> bytes:
    return (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {typ}\nCOUNT {' '.join('1' * len(fields.split()))}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode()


def test_ascii_pcd_reads_xyz(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [4.5, 5.5, 6.5]])
    body = "\n".join(" ".join(str(v) for v in p) for p in pts).encode()
    (tmp_path / "a.pcd").write_bytes(_pcd_header(2, "ascii") + body + b"\n")
    np.testing.assert_allclose(read_cloud(tmp_path / "a.pcd").xyz_mm, pts)


def test_binary_pcd_with_an_extra_field_reads_xyz_and_drops_nan_points(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [7.0, 8.0, 9.0]], dtype=np.float32)
    body = b"".join(struct.pack("<fffI", *p, 0xFFFFFF) for p in pts)
    head = _pcd_header(3, "binary", fields="x y z rgb", size="4 4 4 4", typ="F F F U")
    (tmp_path / "b.pcd").write_bytes(head + body)
    np.testing.assert_allclose(read_cloud(tmp_path / "b.pcd").xyz_mm, pts[[0, 2]])


def test_compressed_pcd_is_refused_naming_the_data_kind(tmp_path):
    (tmp_path / "c.pcd").write_bytes(_pcd_header(1, "binary_compressed") + b"\x00" * 16)
    with pytest.raises(CloudError, match="binary_compressed"):
        read_cloud(tmp_path / "c.pcd")


def test_truncated_binary_pcd_is_reported(tmp_path):
    (tmp_path / "t.pcd").write_bytes(_pcd_header(10, "binary") + b"\x00" * 12)
    with pytest.raises(CloudError, match="truncated"):
        read_cloud(tmp_path / "t.pcd")


def test_xyz_text_with_spaces_and_comments_reads(tmp_path):
    (tmp_path / "a.xyz").write_text("# scan\n1 2 3\n4 5 6 0.5\n\n7 8 9 1\n")
    np.testing.assert_allclose(read_cloud(tmp_path / "a.xyz").xyz_mm, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_csv_with_header_reads_organisation(tmp_path):
    (tmp_path / "a.csv").write_text("x,y,z,pass,profile,point\n1,2,3,0,5,7\n4,5,6,1,6,8\n")
    c = read_cloud(tmp_path / "a.csv")
    assert c.organised
    np.testing.assert_array_equal(c.point_index, [7, 8])


def test_csv_with_columns_in_another_order_uses_the_names(tmp_path):
    (tmp_path / "a.csv").write_text("z;y;x\n3;2;1\n")
    np.testing.assert_allclose(read_cloud(tmp_path / "a.csv").xyz_mm, [[1, 2, 3]])


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.ply", b"", "empty file"),
        ("junk.ply", b"this is not a ply file", "not a PLY file"),
        (
            "cut.ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n",
            "unreadable PLY",
        ),
        (
            "nox.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n",
            "lacks properties",
        ),
        ("two.xyz", b"1 2\n3 4\n", "at least x y z"),
        ("words.csv", b"x,y,z\na,b,c\n", "not a table of numbers"),
        ("header_only.csv", b"x,y,z\n", "no points"),
        ("nan.xyz", b"1 2 3\nnan 1 1\n", "non-finite"),
        ("cloud.las", b"LASF", "unsupported cloud format"),
    ],
)
def test_unusable_files_raise_one_clear_cloud_error(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(CloudError, match=message) as info:
        read_cloud(tmp_path / name)
    assert name in str(info.value)


def test_missing_file_is_reported_by_name(tmp_path):
    with pytest.raises(CloudError, match="no such file"):
        read_cloud(tmp_path / "absent.ply")


def test_npz_without_points_lists_what_it_has(tmp_path):
    np.savez(tmp_path / "x.npz", foo=np.zeros(3))
    with pytest.raises(CloudError, match="foo"):
        read_cloud(tmp_path / "x.npz")


def test_empty_ply_vertex_element_is_an_empty_cloud_error(tmp_path):
    write_cloud_ply(ScanCloud(np.zeros((0, 3))), tmp_path / "e.ply")
    with pytest.raises(CloudError, match="no points"):
        read_cloud(tmp_path / "e.ply")


def test_scan_cloud_rejects_partial_organisation_and_bad_shapes():
    with pytest.raises(CloudError, match="together"):
        ScanCloud(np.zeros((2, 3)), np.zeros(2, int), None, None)
    with pytest.raises(CloudError, match=r"\(n, 3\)"):
        ScanCloud(np.zeros((2, 2)))
    with pytest.raises(CloudError, match="negative"):
        ScanCloud(np.zeros((1, 3)), np.array([-1]), np.array([0]), np.array([0]))
