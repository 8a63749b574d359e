"""PLY and LAS written block by block (a 6 m plate's 170 M points): the same bytes as written whole."""

from __future__ import annotations

import numpy as np
import pytest

import cellctl.acquisition.assembly as asm
from analysis.cloud_export import read_las
from analysis.cloud_io import read_cloud, write_cloud_ply
from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.cloud_files import write_las, write_ply


def _scan(n: int = 53, w: int = 17) -> AssembledScan:
    rng = np.random.default_rng(9)
    xyz = rng.uniform([-3000, -1000, 200], [3000, 1000, 450], (n, w, 3)).astype(np.float32)
    valid = rng.random((n, w)) > 0.25
    valid[7] = False  # a profile without a point
    xyz[~valid] = np.nan
    return AssembledScan(
        profile_index=np.arange(n, dtype=np.int64),
        frame_index=np.arange(n, dtype=np.uint64),
        pass_id=np.repeat(np.arange(-1, n // 10 + 1, dtype=np.int32), 10)[:n],
        t_ns=10**12 + np.arange(n, dtype=np.int64) * 5_000_000,
        xyz_mm=xyz,
        valid=valid,
        sensor_pos_mm=np.zeros((n, 3), np.float32),
    )


@pytest.fixture(params=[4, 10_000])
def block_rows(request, monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(asm, "_BLOCK_ROWS", request.param)
    return request.param


def test_ply_streamed_is_the_ply_written_whole(tmp_path, block_rows: int) -> None:
    scan = _scan()
    got = write_ply(scan, tmp_path / "blocks.ply").read_bytes()
    ref = write_cloud_ply(
        scan.scan_cloud(), tmp_path / "whole.ply", comment="cellctl scan cloud: robot base frame, mm"
    )
    assert got == ref.read_bytes()
    back = read_cloud(tmp_path / "blocks.ply")
    assert len(back) == scan.n_valid


def test_las_streamed_reads_back_every_point(tmp_path, block_rows: int) -> None:
    scan = _scan()
    path = write_las(scan, tmp_path / "c.las")
    back = read_las(path)
    pts = scan.cloud_arrays()
    assert len(back["xyz_mm"]) == scan.n_valid
    np.testing.assert_allclose(back["xyz_mm"], pts["xyz_mm"].astype(np.float64), atol=0.0006)
    np.testing.assert_array_equal(back["pass_id"], pts["pass_id"])
    np.testing.assert_array_equal(back["profile_index"], pts["profile_index"])
    np.testing.assert_array_equal(back["point_index"], pts["point_index"])
    np.testing.assert_allclose(back["t_s"], pts["t_s"])


def test_las_is_the_same_whatever_the_blocks(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    scan = _scan()
    a = write_las(scan, tmp_path / "a.las").read_bytes()
    monkeypatch.setattr(asm, "_BLOCK_ROWS", 3)
    b = write_las(scan, tmp_path / "b.las").read_bytes()
    # the header (extent, counts) and every record byte for byte; not the VLRs between them, whose
    # extra-bytes descriptors carry laspy's unset (and unflagged) min/max bytes
    start = int.from_bytes(a[96:100], "little")  # offset to point data
    assert len(a) == len(b) and a[:375] == b[:375] and a[start:] == b[start:]


def test_the_transit_apart_numbers_the_passes_from_one(block_rows: int) -> None:
    """The scan's cloud files the transit with its first pass under pass 0; the locate run's keeps
    them apart (passes from 1, the transit alone under 0), so its first pass is read as a pass."""
    scan = _scan()
    whole, apart = scan.scan_cloud(), scan.scan_cloud(transit_apart=True)
    row_pass = np.repeat(scan.pass_id[:, None], scan.valid.shape[1], axis=1)[scan.valid]
    np.testing.assert_array_equal(apart.pass_id, row_pass + 1)
    np.testing.assert_array_equal(whole.pass_id, np.maximum(row_pass, 0))
    np.testing.assert_array_equal(whole.xyz_mm, apart.xyz_mm)
