"""Raw files: chunk framing, torn tails, CRC, no overwrite, bit-for-bit reassembly, kill -9."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.reassemble import reassemble
from cellctl.jobstore.rawstore import RawFormatError, RawReader, RawWriter
from tests.support.synthetic_scan import feed, make_run

_dtypes = st.sampled_from([np.float32, np.float64, np.int64, np.uint32, np.uint8, np.int16, np.bool_])


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(arrays=st.lists(hnp.arrays(_dtypes, hnp.array_shapes(min_dims=0, max_dims=3, max_side=7)), max_size=4))
def test_records_round_trip_every_array_exactly(tmp_path_factory, arrays):
    job = tmp_path_factory.mktemp("job")
    with RawWriter(job, {"x": 1}, fsync=False) as w:
        w.append("robot", 2, {f"a{i}": a for i, a in enumerate(arrays)})
        w.append("events", 4, {"t_ns": np.int64(5)})
    recs = RawReader(job).records()
    assert [r.seq for r in recs] == [0, 1]
    for i, a in enumerate(arrays):
        got = recs[0].arrays[f"a{i}"]
        assert got.dtype == a.dtype and got.shape == a.shape
        np.testing.assert_array_equal(got, a)


def _write_chunks(job, n_chunks=5):
    with RawWriter(job, {}, fsync=False) as w:
        for i in range(n_chunks):
            w.append("robot", 2, {"i": np.int64(i), "pad": np.arange(100.0)})
            w.flush()
    return job / "robot.craw"


def test_a_torn_last_chunk_is_dropped_and_everything_before_it_is_kept(tmp_path):
    path = _write_chunks(tmp_path)
    size = path.stat().st_size
    for cut in (size - 1, size - 500, size - 820):
        with open(path, "r+b") as f:
            f.truncate(cut)
        reader = RawReader(tmp_path)
        recs = reader.records()
        assert [int(r.arrays["i"]) for r in recs] == list(range(len(recs)))
        assert len(recs) in (3, 4)
        assert reader.report.torn_bytes["robot"] > 0
        size = cut


def test_a_flipped_byte_stops_the_reader_at_the_crc_check(tmp_path):
    path = _write_chunks(tmp_path)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    reader = RawReader(tmp_path)
    recs = reader.records()
    assert 0 < len(recs) < 5
    assert any("CRC" in p for p in reader.report.problems)


def test_writer_refuses_to_overwrite_existing_raw_files(tmp_path):
    _write_chunks(tmp_path)
    with pytest.raises(FileExistsError, match="never overwritten"):
        RawWriter(tmp_path, {})


def test_reader_names_a_directory_that_is_not_a_job(tmp_path):
    with pytest.raises(RawFormatError, match=r"job\.json"):
        RawReader(tmp_path)


def _settings(run, **kw):
    return AcquisitionSettings(epoch_ns=run.epoch_ns, latency_ms=0.8, **kw)


def test_reassembly_rebuilds_the_live_cloud_bit_for_bit(tmp_path):
    run = make_run(3.0)
    s = _settings(run)
    with RawWriter(tmp_path / "job", {"acquisition": s.to_json()}, fsync=False) as w:
        live = Acquisition(s, w)
        live.begin_pass(0, run.epoch_ns + 500_000_000)
        live.end_pass(run.epoch_ns + 2_000_000_000)
        feed(live, run)
    res = reassemble(tmp_path / "job", final=False)
    assert len(res.cloud) == len(live.cloud()) > 500
    assert res.cloud.digest() == live.cloud().digest()
    assert res.fits_recorded == res.fits_matching > 0
    assert set(np.unique(res.cloud.pass_id)) == {-1, 0}
    # the final cloud (whole-scan clock fits) is deterministic in the files too
    a, b = reassemble(tmp_path / "job"), reassemble(tmp_path / "job")
    assert a.final and a.cloud.digest() == b.cloud.digest() != res.cloud.digest()
    assert len(a.cloud) == len(res.cloud)


_CHILD = r"""
import sys, time
from pathlib import Path
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.jobstore.rawstore import RawWriter
from tests.support.synthetic_scan import make_run
run = make_run(4.0)
s = AcquisitionSettings(epoch_ns=run.epoch_ns, latency_ms=0.8)
w = RawWriter(Path(sys.argv[1]), {"acquisition": s.to_json()}, flush_interval_s=0.05)
acq = Acquisition(s, w)
profiles = 0
flushed = 0
profiles_at_seq = {}
for kind, payload in run.events:
    seq = w.next_seq
    if kind == "robot":
        acq.feed_robot(*payload)
    else:
        acq.feed_profiles(payload)
        profiles += len(payload)
    profiles_at_seq[seq] = profiles
    durable = max((p for q, p in profiles_at_seq.items() if q <= w.durable_seq), default=0)
    if durable > flushed:  # these profiles are fsync'ed: they must survive the kill
        flushed = durable
        print(f"flushed {flushed}", flush=True)
    time.sleep(0.002)  # stays: pacing the writer the test kills mid-stream
print("done", flush=True)
"""


@pytest.mark.slow
def test_kill_9_mid_scan_loses_at_most_the_unflushed_chunk(tmp_path, repo_root):
    job = tmp_path / "job"
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(job)],
        cwd=repo_root,
        env={**os.environ, "PYTHONPATH": str(repo_root)},
        stdout=subprocess.PIPE,
        text=True,
    )
    flushed = 0
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line and not line.startswith("done"), "child finished before it was killed"
            flushed = int(line.split()[1])
            if flushed >= 300:
                break
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=10)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    res = reassemble(job, final=False)
    n = len(res.cloud)
    # everything flushed before the kill is there; at most one flush interval more may be
    assert n >= flushed
    assert n <= flushed + 200 * 0.05 * 4 + 10
    # and it is the same scan the uninterrupted pipeline assembles, profile for profile
    full = Acquisition(AcquisitionSettings(epoch_ns=res.settings.epoch_ns, latency_ms=0.8))
    feed(full, make_run(4.0))
    ref = full.cloud()
    k = n - 20  # the last few were assembled at replay's end without robot samples after them
    np.testing.assert_array_equal(res.cloud.xyz_mm[:k], ref.xyz_mm[:k])
    np.testing.assert_array_equal(res.cloud.t_ns[:k], ref.t_ns[:k])


def test_a_garbage_file_header_loses_neither_that_streams_chunks_nor_the_other_streams(tmp_path):
    """Issue 24: one raw file whose header was overwritten made the whole job unreadable."""
    w = RawWriter(tmp_path, {"job_id": "J"}, fsync=False, chunk_bytes=1)
    for i in range(5):
        w.append("robot", 2, {"t_host_ns": np.array([i], dtype=np.int64)})
        w.append("profiles", 1, {"frame": np.array([i], dtype=np.int64)})
    w.close()
    with open(tmp_path / "robot.craw", "r+b") as f:
        f.write(b"\xde\xad\xbe\xef" * 4)  # the file header (and nothing past it) destroyed
    reader = RawReader(tmp_path)
    recs = reader.records()
    by_stream = {s: [r for r in recs if r.stream == s] for s in ("robot", "profiles")}
    assert len(by_stream["profiles"]) == 5
    assert [int(r.arrays["t_host_ns"][0]) for r in by_stream["robot"]] == [0, 1, 2, 3, 4]
    assert any("robot.craw: bad file header" in p and "resumed" in p for p in reader.report.problems)
