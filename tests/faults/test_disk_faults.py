"""Disk faults: the data directory too small, read-only, or filling up mid-scan.

Simulated honestly on a real file system: a small tmpfs mounted on the data directory (resized and
remounted read-only between cases), and a file-size limit (RLIMIT_FSIZE) set on the running daemon
for the mid-scan case, so its raw writes fail with EFBIG like a full disk's would with ENOSPC.
Mounting needs root (CI runs as root); without it the cases are skipped, saying so.

Expected outcomes:

* too little free space for the planned scan's raw data + ``[daemon] min_free_mb``: the job fails in
  pre-flight, naming ``daemon.min_free_mb`` and the sizes, before any motion (the arm does not move,
  no raw file is opened);
* read-only data directory: the trigger is refused (``not_allowed``, field ``cell.data_dir``), no job
  record is made, the daemon stays idle and serving;
* writes failing mid-scan: the scan stops smoothly along its path, the EGM program is ended, the job
  is ``failed`` saying the raw data could not be written, the cell ``faulted`` (a stated state a new
  trigger leaves); the daemon survives, everything written before is readable, and the arm holds.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import resource
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cellctl.api import ApiCallError, TriggerAccepted, call
from cellctl.daemon.preflight import (
    PreflightError,
    check_data_dir,
    expected_profiles,
    probe_writable,
    raw_bytes_estimate,
    spill_bytes_estimate,
)
from tests.support.cellfaults import (
    FINAL,
    FaultCell,
    fault_cell_config,
    raw_check,
    rws_client,
    stop_cell,
    wait_status,
    wait_until,
)
from tests.support.faultcell import wait_record


def _mount(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["mount", *args], capture_output=True, text=True, timeout=30)


@contextlib.contextmanager
def tmpfs(directory: Path, size: str):
    """A tmpfs of ``size`` on ``directory`` for the block; skipped (with the reason) when mounting is not
    permitted here."""
    directory.mkdir(parents=True, exist_ok=True)
    r = _mount("-t", "tmpfs", "-o", f"size={size},mode=0700", "tmpfs", str(directory))
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield directory
    finally:
        if subprocess.run(["umount", str(directory)], capture_output=True, timeout=30).returncode != 0:
            subprocess.run(["umount", "-l", str(directory)], capture_output=True, timeout=30)


def _remount(directory: Path, opts: str) -> None:
    r = _mount("-o", f"remount,{opts}", str(directory))
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------ the pre-flight itself


def test_raw_estimate_covers_what_a_scan_stores():
    # measured: 3.87 kB per 500-point profile (one profile per record, x row included)
    est = raw_bytes_estimate(30.0, rate_hz=200.0, points_per_profile=500, settle_s=1.0, safety=1.0)
    assert est.profiles == 6201
    assert est.bytes / est.profiles >= 3870
    with pytest.raises(ValueError, match="rate_hz"):
        raw_bytes_estimate(30.0, rate_hz=0.0, points_per_profile=500)


def test_spill_estimate_covers_the_scan_arrays_and_the_chunks_a_6_m_plate_spills():
    # issue 42: 340 000 profiles planned (1776 s at 200 Hz), 13 B a raw point of xyz_mm + valid reserved
    # in the spill file at the start, 28 B a published point (every 5th) of streamed chunks
    profiles = expected_profiles(1776.0, rate_hz=200.0, settle_s=1.0)
    assert profiles == round(1787.0 * 200.0 * 1.1)
    spill = spill_bytes_estimate(profiles, points_per_profile=500, publish_step=5)
    assert spill >= profiles * 500 * 13 + 0.93e9  # the spill file's reserve and the 6 m plate's chunks
    assert spill < 4.0e9


@pytest.mark.process  # mounts tmpfs with mount(8)
def test_preflight_names_the_field_and_sizes_for_a_small_full_or_read_only_data_directory(tmp_path):
    d = tmp_path / "data"
    with tmpfs(d, "8m"):
        est = raw_bytes_estimate(30.0, rate_hz=200.0, points_per_profile=500)
        with pytest.raises(PreflightError) as small:
            check_data_dir(d, est.bytes, min_free_mb=0.0)
        assert small.value.field == "daemon.min_free_mb"
        assert "MB free" in small.value.message and str(d) in small.value.message
        ok = check_data_dir(d, 1_000_000, min_free_mb=1.0)
        assert ok.free_bytes > ok.need_bytes and not any(d.iterdir()), "the probe file is removed"

        # a full file system: the probe's write fails and says so
        with open(d / "filler", "wb") as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * (1 << 20))
        with pytest.raises(PreflightError) as full:
            probe_writable(d)
        assert full.value.field == "cell.data_dir" and "is full" in full.value.message
        (d / "filler").unlink()

        _remount(d, "ro")
        with pytest.raises(PreflightError) as ro:
            probe_writable(d / "jobs")
        assert ro.value.field == "cell.data_dir" and "read-only" in ro.value.message
        _remount(d, "rw")
        probe_writable(d / "jobs")


# ------------------------------------------------------------------------------ the cell, end to end


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.timeout(600)
def test_data_dir_too_small_or_read_only_faults_before_motion_and_full_mid_scan_stops_smoothly(tmp_path):
    cfg_path = fault_cell_config(tmp_path)
    cell = FaultCell(tmp_path, cfg_path)
    data = Path(cell.cfg.cell.data_dir)
    assert cell.cfg.daemon.min_free_mb >= 100, "the case relies on the default margin"
    with tmpfs(data, "64m"):
        try:
            cell.start()

            async def before_motion() -> dict:
                seen: dict = {}
                rws = rws_client(cell)
                try:
                    async with cell.client() as c:
                        session, keys, follower = c.session, c.keys, c.follower
                        await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 180.0)
                        q0 = await rws.get_joint_position()
                        # 1. 64 MB free, the scan's estimate + 200 MB needed: pre-flight fails the job
                        acc = await call(
                            session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted
                        )
                        await wait_until(
                            lambda: cell.job_record(acc.job_id)["state"] in FINAL, 60.0, what="job ends"
                        )
                        seen["small"] = (acc.job_id, cell.job_record(acc.job_id))
                        await wait_status(follower, lambda s: s.state.value == "idle", 30.0)
                        seen["moved_deg"] = float(np.max(np.abs(await rws.get_joint_position() - q0)))
                        # 2. read-only: the trigger is refused, nothing is written, the daemon serves on
                        _remount(data, "ro")
                        try:
                            with pytest.raises(ApiCallError) as ro:
                                await call(
                                    session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted
                                )
                            seen["ro"] = ro.value.error
                            st = await wait_status(follower, lambda s: True)
                            seen["ro_state"] = st.state.value
                            seen["jobs_after_ro"] = sorted(p.name for p in cell.jobs_dir.iterdir())
                        finally:
                            _remount(data, "rw,size=2g")
                        # 3. room again, but the daemon's files may not grow past 2 MB: raw writes
                        #    fail with EFBIG a few seconds into the scan
                        resource.prlimit(
                            cell.proc("run").pid, resource.RLIMIT_FSIZE, (2 << 20, resource.RLIM_INFINITY)
                        )
                        acc = await call(
                            session,
                            keys.trigger,
                            json.dumps(cell.trigger_request(plate_id="fills-up")),
                            TriggerAccepted,
                        )
                        seen["full_job"] = acc.job_id
                        await wait_until(
                            lambda: cell.job_record(acc.job_id)["state"] in FINAL, 180.0, period_s=0.5,
                            what="job ends",
                        )  # fmt: skip
                        st = await wait_status(follower, lambda s: s.state.value != "scanning", 30.0)
                        seen["full_state"] = (st.state.value, st.message)
                        q1 = await rws.get_joint_position()
                        await asyncio.sleep(1.5)  # stays: time passing in which the arm must hold
                        seen["hold_after_full_deg"] = float(
                            np.max(np.abs(await rws.get_joint_position() - q1))
                        )
                finally:
                    await rws.close()
                return seen

            seen = asyncio.run(before_motion())
            job_id, rec = seen["small"]
            assert rec["state"] == "failed", rec["history"]
            msg = rec["history"][-1]["message"]
            assert "pre-flight" in msg and "daemon.min_free_mb" in msg and "nothing moved" in msg, msg
            assert "scanning" not in [h["state"] for h in rec["history"]]
            assert not (cell.jobs_dir / job_id / "raw").exists(), "no raw file opened before the check"
            assert seen["moved_deg"] < 0.01
            assert (seen["ro"].code, seen["ro"].field) == ("not_allowed", "cell.data_dir")
            assert "read-only" in seen["ro"].message
            assert seen["ro_state"] == "idle" and seen["jobs_after_ro"] == [job_id]

            full = seen["full_job"]
            rec = cell.job_record(full)
            assert rec["state"] == "failed", rec["history"]
            msg = rec["history"][-1]["message"]
            assert "raw data could not be written" in msg and "File too large" in msg, msg
            assert "scanning" in [h["state"] for h in rec["history"]]
            assert seen["full_state"][0] == "faulted", seen["full_state"]
            assert cell.proc("run").poll() is None, "the daemon survives a full disk"
            assert seen["hold_after_full_deg"] < 0.01
            raw = raw_check(cell, full)
            assert raw.profiles > 100 and raw.unique_frames
            assert os.path.getsize(cell.jobs_dir / full / "raw" / "profiles.craw") <= 2 << 20
            # the cell takes triggers again (it is faulted, not stuck); lift the limit first
            resource.prlimit(cell.proc("run").pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY,) * 2)
        finally:
            codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes


def _fill(directory: Path) -> Path:
    """Write ``directory/filler`` until the file system is full (ENOSPC); returns the file."""
    path = directory / "filler"
    chunk = b"\0" * (1 << 20)
    with contextlib.suppress(OSError), open(path, "wb") as f:
        while True:
            f.write(chunk)
            f.flush()
    return path


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.timeout(600)
def test_a_disk_that_fills_mid_scan_leaves_an_operator_a_way_out_without_a_restart(tmp_path):
    """Issue 24, finding 1 (and 2): the data directory fills up during a scan, so that also the job
    record cannot be written. The job must end ``failed`` in memory and in the publication (the cell
    ``faulted``, abort has nothing to abort, reset clears it), no half-written record is left, the
    record reaches the disk once there is room again, and the next scan runs to its report (the
    sensor and the controller brought back to a known state)."""
    cfg_path = fault_cell_config(tmp_path, daemon__min_free_mb=1)
    cell = FaultCell(tmp_path, cfg_path)
    data = Path(cell.cfg.cell.data_dir)
    with tmpfs(data, "150m"):
        try:
            cell.start()

            async def scenario() -> dict:
                seen: dict = {}
                async with cell.client() as c:
                    await c.wait_idle()
                    job = await c.trigger(plate_id="fills-up")
                    await c.wait_scanning(job, min_fraction=0.05)
                    filler = await asyncio.to_thread(_fill, data)
                    st = await c.wait(
                        lambda s: s.state.value != "scanning" and s.job is not None and s.job.job_id == job
                        and s.job.state.value == "failed", 120.0,
                    )  # fmt: skip
                    st = await c.wait(lambda s: s.state.value == "faulted", 30.0)
                    seen["failed_state"] = st.state.value
                    seen["message"] = st.job.message if st.job else ""
                    seen["tmp_left"] = sorted(p.name for p in (cell.jobs_dir / job).glob("*.tmp"))
                    seen["on_disk_while_full"] = cell.job_record(job)["state"]
                    with pytest.raises(ApiCallError) as nothing:
                        await c.control("abort")
                    seen["abort"] = nothing.value.error.code
                    reply = await c.control("reset")
                    seen["reset"] = reply.state
                    filler.unlink()
                    rec = await wait_record(cell, job, lambda r: r["state"] == "failed", 30.0)
                    seen["record"] = rec
                    again = await c.trigger(plate_id="room-again")
                    st = await c.wait_job_end(again, 480.0)
                    seen["again"] = st.job.state.value
                return seen

            seen = asyncio.run(scenario())
            assert seen["failed_state"] == "faulted"
            assert "raw data could not be written" in seen["message"], seen["message"]
            assert seen["tmp_left"] == [], "a half-written job.json.tmp was left"
            assert seen["on_disk_while_full"] in ("scanning", "failed")
            assert seen["abort"] == "no_job"
            assert seen["reset"] == "idle"
            assert seen["record"]["history"][-1]["message"].startswith("raw data could not be written")
            assert seen["again"] == "done", seen
            assert cell.proc("run").poll() is None
            assert cell.log_events("run", "job_record_write_failed")
            assert cell.log_events("run", "job_record_written")
        finally:
            codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes
