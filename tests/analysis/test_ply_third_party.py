"""The product's PLY clouds read by a reader nobody here wrote (plyfile): a QA inspector's tool
(CloudCompare, MeshLab, Open3D's tensor reader) meets the same header and the same columns."""

from __future__ import annotations

import numpy as np
import plyfile

from analysis.cloud_io import ScanCloud, read_cloud, write_cloud_ply


def _organised_cloud(n_profiles: int = 7, n_points: int = 11) -> ScanCloud:
    rng = np.random.default_rng(4)
    n = n_profiles * n_points
    return ScanCloud(
        xyz_mm=rng.uniform(-600.0, 600.0, (n, 3)),
        pass_id=np.repeat(np.arange(n_profiles) % 3, n_points).astype(np.int32),
        profile_index=np.repeat(np.arange(n_profiles), n_points).astype(np.int32),
        point_index=np.tile(np.arange(n_points), n_profiles).astype(np.int32),
        t_s=np.repeat(np.arange(n_profiles) * 0.005, n_points),
    )


def test_plyfile_reads_every_column_of_a_scan_cloud_with_its_values(tmp_path):
    cloud = _organised_cloud()
    path = write_cloud_ply(cloud, tmp_path / "scan.ply")
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names == ["x", "y", "z", "pass", "profile", "point", "t_s"]
    got = np.column_stack([vertex["x"], vertex["y"], vertex["z"]])
    np.testing.assert_allclose(got, cloud.xyz_mm.astype(np.float32))
    np.testing.assert_array_equal(vertex["pass"], cloud.pass_id)
    np.testing.assert_array_equal(vertex["profile"], cloud.profile_index)
    np.testing.assert_array_equal(vertex["point"], cloud.point_index)
    np.testing.assert_array_equal(vertex["t_s"], cloud.t_s)


def test_plyfile_reads_the_registered_clouds_deviation_field_nan_included(tmp_path):
    pts = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 1.5], [0.0, 10.0, 2.0]])
    deviation = np.array([0.25, np.nan, -0.125], dtype=np.float32)
    path = write_cloud_ply(ScanCloud(pts), tmp_path / "cloud.ply", extra={"scalar_deviation": deviation})
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    assert [p.name for p in vertex.properties] == ["x", "y", "z", "scalar_deviation"]
    np.testing.assert_array_equal(vertex["scalar_deviation"], deviation)
    # and our own reader agrees with it on the points
    np.testing.assert_allclose(read_cloud(path).xyz_mm, pts.astype(np.float32))


def test_open3d_tensor_reader_takes_the_deviation_as_a_point_attribute(tmp_path):
    import open3d as o3d

    pts = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 1.5]])
    deviation = np.array([0.25, -0.5], dtype=np.float32)
    path = write_cloud_ply(ScanCloud(pts), tmp_path / "cloud.ply", extra={"scalar_deviation": deviation})
    pc = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(pc.point["scalar_deviation"].numpy().ravel(), deviation)
    np.testing.assert_allclose(pc.point["positions"].numpy(), pts)
