"""The daemon's memory per point (issue 42 item 2, docs/operations.md "The daemon's memory, stage by
stage"): the whole scan's per-point arrays spilled to a file beside the raw files, the publication
written straight into its message, with the same published bytes as the cloud assembled in memory and
encoded the way it was before. A scaled-down long-plate stream (benchmarks/long_plate_memory.py's)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import cellctl.acquisition.assembly as assembly
from benchmarks.long_plate_memory import feed_stream
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan, publication_cloud
from cellctl.acquisition.spill import SpillArray, release
from cellctl.api.cloud_codec import CloudMeta, encode_cloud
from cellctl.jobstore.rawstore import RawWriter

EPOCH_NS = 10**12
#: numpy heap per raw point, acquiring a spilled scan (its per-profile arrays, the pending batches and
#: the raw writer's chunks; the per-point arrays are in the file): 4-5.5 on this stream (mostly fixed
#: costs: on the 6 m plate's stream 0.1), 28.7 with the scan's xyz_mm and valid in memory
ACQUIRE_HEAP_B_PER_POINT = 8.0
#: numpy heap per raw point while publishing at a fifth (raster) and a third (edge passes) of the
#: columns, in blocks of 100 rows: the message (6.8 here: 28 bytes a published point) and a block's
#: temporaries, 8.8; 13.7 when the cloud was built and then copied into its message
PUBLISH_HEAP_B_PER_POINT = 10.5


def _stream(tmp_path: Path, *, spill: bool, profiles: int = 1600, width: int = 200) -> Acquisition:
    settings = AcquisitionSettings(epoch_ns=EPOCH_NS)
    writer = RawWriter(tmp_path / ("spilled" if spill else "in-memory"), {"acquisition": settings.to_json()})
    # a reserve well under the scan: the spill file grows (the arrays in memory are copied) twice
    acq = Acquisition(settings, writer, expected_profiles=profiles // 3, spill_dir=None if spill else False)
    feed_stream(acq, n_profiles=profiles, n_passes=6, width=width, batch=20, epoch_ns=EPOCH_NS)
    acq.finish()
    writer.close()
    return acq


def _steps(scan) -> np.ndarray:
    return column_steps(scan.pass_id, 4, PublishSettings(pitch_mm=0.5, edge_pitch_mm=0.3))


def test_a_spilled_scan_publishes_the_bytes_the_scan_in_memory_did(tmp_path, monkeypatch):
    # small blocks and releases: every path of the spill (growth, release while writing and reading)
    monkeypatch.setattr(assembly, "_BLOCK_ROWS", 97)
    monkeypatch.setattr(assembly, "_RELEASE_BYTES", 64 << 10)
    spilled = _stream(tmp_path, spill=True).cloud()
    in_memory = _stream(tmp_path, spill=False).cloud()
    assert isinstance(spilled.xyz_mm.base.base, memoryview)  # a view of the spill file's mapping
    assert spilled.digest() == in_memory.digest()
    meta = CloudMeta(cell_id="c1")
    steps = _steps(in_memory)
    # before issue 42: the cloud's arrays built, then copied into the message by encode_cloud
    before = encode_cloud(
        publication_cloud(in_memory, job_id="J", plate_id="P", column_step=steps, meta=meta)
    )
    after, n = encode_scan(spilled, job_id="J", plate_id="P", column_step=steps, meta=meta)
    assert n > 50_000 and bytes(after) == bytes(before)
    np.testing.assert_array_equal(spilled.valid_per_profile(), in_memory.valid.sum(axis=1))


def test_the_daemon_heap_per_point_stays_under_its_bounds(tmp_path, monkeypatch):
    # blocks of rows as small against this scan as the 16 384 rows are against a 6 m plate's 340 000
    monkeypatch.setattr(assembly, "_BLOCK_ROWS", 100)
    tracemalloc.start()
    try:
        acq = _stream(tmp_path, spill=True)
        acquire_peak = tracemalloc.get_traced_memory()[1]
        scan = acq.cloud()
        raw_points = scan.n_valid
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        payload, _ = encode_scan(scan, job_id="J", plate_id="P", column_step=_steps(scan))
        publish_peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert raw_points > 300_000
    assert acquire_peak / raw_points < ACQUIRE_HEAP_B_PER_POINT, acquire_peak / raw_points
    assert publish_peak / raw_points < PUBLISH_HEAP_B_PER_POINT, publish_peak / raw_points
    assert len(payload) > 0


def test_a_spill_grows_without_a_copy_and_release_keeps_the_data(tmp_path):
    sp = SpillArray(tmp_path, (4, 3), np.float32, 10)
    sp.array[:10] = np.arange(120, dtype=np.float32).reshape(10, 4, 3)
    early = sp.array[:10]
    sp.reserve(100_000)  # the file extended and mapped again
    assert sp.capacity == 100_000 and list(tmp_path.iterdir()) == []  # unlinked from the start
    np.testing.assert_array_equal(sp.array[:10], early)
    sp.array[50_000:] = 7.0
    release(sp.array[:])  # out of memory, not out of the file
    assert float(sp.array[99_999, 3, 2]) == 7.0 and float(sp.array[9, 3, 2]) == 119.0
    release(np.zeros(5))  # an array in memory: nothing to do


def test_a_spill_that_cannot_grow_leaves_the_rows_in_memory(tmp_path, monkeypatch):
    def full(*_a, **_k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(SpillArray, "reserve", full)
    scan = _stream(tmp_path, spill=True, profiles=200, width=20).cloud()
    assert not isinstance(scan.xyz_mm.base, memoryview) and len(scan) == 200


@pytest.mark.parametrize("field", ["xyz_mm"])
def test_a_non_finite_published_point_is_refused(tmp_path, field):
    scan = _stream(tmp_path, spill=False, profiles=100, width=10).cloud()
    r, c = np.argwhere(scan.valid)[0]
    scan.xyz_mm[r, c, 0] = np.inf
    with pytest.raises(ValueError, match="non-finite coordinates"):
        encode_scan(scan, job_id="J", plate_id="P")
