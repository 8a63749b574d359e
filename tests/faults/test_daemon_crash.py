"""Daemon fault: ``kill -9`` of `cellctl run` mid-scan, then a restart.

Expected outcome:

* the robot holds: without the daemon nothing commands the arm; the controller's EGM communication
  timeout ends the EGM session (event 41822 in its event log) and the joints stay where they were;
* the raw files are intact: every stream reads to its last complete chunk (what the daemon had
  counted, less at most the raw store's documented kill -9 bound of one flush interval); a torn tail (a write cut
  short, made here by appending half of the last chunk again) is detected, reported and dropped,
  never a crash, and it costs no record that was complete;
* after the restart the job is reported ``interrupted`` (it died in ``scanning``), the daemon says
  so in its state message, and ``control/reanalyse`` rebuilds the cloud from the raw files and the
  worker's report completes the job. (The kill comes at 60 % of the scan: a cloud of part of the
  plate is re-analysed too; it failed plainly with "the design does not match the plate", observed,
  and is now reported for what was scanned, verdict ``incomplete`` or ``fail``: issue 43.)
"""

from __future__ import annotations

import asyncio
import json
import os
import time

import numpy as np
import pytest

from cellctl.api import TriggerAccepted, call
from cellctl.api.session import async_get
from cellctl.commands.scan_cmd import wait_for_job
from cellctl.jobstore.rawstore import CHUNK, RawReader
from tests.support.cellfaults import (
    FINAL,
    FaultCell,
    fault_cell_config,
    job_history,
    kill9_tree,
    raw_check,
    rws_client,
    stop_cell,
    wait_status,
)
from tests.support.skiplog import record_fallback

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.timeout(600)]

EGM_COMM_TIMEOUT_EVENT = 41822  # the controller's "EGM communication timeout" event code


def _tear_last_chunk(path) -> int:
    """Append the first half of the file's last complete chunk again: a write cut short. Returns bytes added."""
    data = path.read_bytes()
    pos, last = None, None
    # walk the chunks from the header on (file header: magic 8, version 4, name_len 4, name)
    name_len = int.from_bytes(data[12:16], "little")
    pos = 16 + name_len
    while pos + CHUNK.size <= len(data):
        _, plen, _, _ = CHUNK.unpack_from(data, pos)
        if pos + CHUNK.size + plen > len(data):
            break
        last = (pos, CHUNK.size + plen)
        pos += CHUNK.size + plen
    assert last is not None, f"{path} has no complete chunk"
    torn = data[last[0] : last[0] + last[1] // 2]
    with open(path, "ab") as f:
        f.write(torn)
    return len(torn)


def test_daemon_kill9_mid_scan_robot_holds_raw_data_intact_and_restart_reanalyses(tmp_path):
    cell = FaultCell(tmp_path, fault_cell_config(tmp_path))
    try:
        cell.start()

        async def scan_then_kill() -> dict:
            seen: dict = {}
            async with cell.client() as c:
                session, keys, follower = c.session, c.keys, c.follower
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
                seen["scans_lost_to_load"] = []
                for _ in range(2):  # one scan again at most: .ci/run allows one fallback per module
                    before = (await cell.fault()).stats["egm"]
                    acc = await call(
                        session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted
                    )
                    seen["job_id"] = job_id = acc.job_id
                    st = await wait_status(
                        follower,
                        lambda s, job_id=job_id: s.job is not None and s.job.job_id == job_id and (
                            (s.job.state.value == "scanning" and s.job.fraction > 0.6) or s.job.state.value in FINAL
                        ),
                        180.0,
                    )  # fmt: skip
                    if st.job.state.value == "scanning":
                        break
                    # A loaded machine can starve the simulated controller past the executor's
                    # silence limit (a motion fault, observed at load 13): only then, scan again
                    # (limits unchanged), and count it as a fallback (.ci/run's fallback count).
                    after = (await cell.fault()).stats["egm"]
                    overruns, cycles = (
                        after["overruns"] - before["overruns"],
                        after["cycles"] - before["cycles"],
                    )
                    assert overruns > 0.01 * max(cycles, 1), (
                        f"the scan ended {st.job.state.value} before the kill, with the controller "
                        f"keeping time ({overruns} of {cycles} cycles late): {st.job.message}"
                    )
                    seen["scans_lost_to_load"].append(st.job.message)
                    record_fallback(
                        f"fallback: simulators starved (controller overruns {overruns} of {cycles} cycles): "
                        f"scan {st.job.state.value} before the kill ({st.job.message}), scanned again"
                    )
                assert st.job.state.value == "scanning", seen
                seen["profiles_seen"] = st.job.profiles
            seen["killed"] = kill9_tree(cell.proc("run").pid)
            t_kill = time.monotonic()
            rws = rws_client(cell)
            try:
                # the controller ends EGM on its own after its communication timeout, then holds
                deadline = t_kill + 30.0
                while time.monotonic() < deadline:
                    log = await rws.read_event_log()
                    if any(e.code == EGM_COMM_TIMEOUT_EVENT for e in log):
                        break
                    await asyncio.sleep(0.25)
                seen["comm_timeout_after_s"] = time.monotonic() - t_kill
                seen["elog_codes"] = [e.code for e in log[:10]]
                q0 = await rws.get_joint_position()
                await asyncio.sleep(2.0)  # stays: time passing in which the arm must hold
                q1 = await rws.get_joint_position()
                seen["hold_deg"] = float(np.max(np.abs(q1 - q0)))
                seen["exec_state"] = str(await rws.get_execution_state())
            finally:
                await rws.close()
            return seen

        seen = asyncio.run(scan_then_kill())
        job_id = seen["job_id"]
        assert cell.proc("run").wait(10) == -9
        assert EGM_COMM_TIMEOUT_EVENT in seen["elog_codes"], seen
        assert seen["hold_deg"] < 0.01, f"the arm moved {seen['hold_deg']} deg without the daemon"

        # raw files: intact to the last complete chunk; a torn tail is dropped, not fatal
        raw_dir = cell.jobs_dir / job_id / "raw"
        before = raw_check(cell, job_id)
        # kill -9 may cost what was still buffered: the raw store's documented bound is the last
        # flush interval (0.2 s) plus the chunks queued for the disk, about 40 to 50 profiles at 200 Hz
        lost_bound = int(cell.cfg.laser.rate_hz * 0.25)
        assert before.profiles >= seen["profiles_seen"] - lost_bound, (before.profiles, seen["profiles_seen"])
        assert seen["profiles_seen"] > 100
        assert before.unique_frames
        added = _tear_last_chunk(raw_dir / "profiles.craw")
        after = raw_check(cell, job_id)
        assert after.torn_bytes["profiles"] == added > 0
        assert any("torn chunk" in p for p in after.problems), after.problems
        assert after.profiles == before.profiles and after.records_used == before.records_used
        assert RawReader(raw_dir).meta["job_id"] == job_id

        # restart: the job is interrupted, re-analysis from the raw files completes it
        assert cell.job_record(job_id)["state"] == "scanning"  # what the killed daemon left
        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if n != "run"]
        cell.procs.start("run2", "run")

        async def reanalyse() -> dict:
            seen2: dict = {}
            async with cell.client() as c:
                session, keys, follower = c.session, c.keys, c.follower
                st = await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
                seen2["message"] = st.message
                # published with the first state after the restart: a client still waiting on the job
                # (`cellctl scan --wait` across the crash) learns that it was interrupted
                seen2["published"] = {j.job_id: j.state.value for j in st.jobs()}.get(job_id)
                rec = cell.job_record(job_id)
                seen2["recovered"] = (rec["state"], rec["info"].get("interrupted_in"))
                replies = await async_get(
                    session, f"{keys.prefix}/control/reanalyse", payload=json.dumps({"job_id": job_id}),
                    timeout_s=20.0,
                )  # fmt: skip
                assert replies and replies[0].ok is not None, replies and replies[0].err.payload.to_bytes()
                seen2["final"] = await wait_for_job(follower, job_id, 300.0)
                # issue 24, finding 2: the killed daemon left the sensor streaming and the EGM program
                # ended by the controller; a fresh scan must bring both back to a known state
                acc = await call(session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted)
                seen2["next_scan"] = await wait_for_job(follower, acc.job_id, 480.0)
                st = await wait_status(follower, lambda s: s.state.value == "idle", 30.0)
                seen2["idle_message"] = (acc.job_id, st.message)
            return seen2

        seen2 = asyncio.run(reanalyse())
        assert seen2["recovered"] == ("interrupted", "scanning"), seen2
        assert "1 interrupted job" in seen2["message"], seen2["message"]
        state, message, report = seen2["final"]
        # the scan cut short by the kill is analysed from its raw files with the placement it was planned
        # from (as tests/e2e/test_shutdown_recovery.py's): a report of what it covered, never a pass
        assert state == "done", message
        hist = job_history(cell, job_id)
        assert hist.count("interrupted") == 1 and hist[-1] == state, hist
        assert report is not None and report.job_id == job_id
        stored = json.loads((cell.jobs_dir / job_id / "report.json").read_text())
        assert stored["job_id"] == job_id
        # what it covered, never a pass; the truth's verdict (the default forming error passes) if whole
        expected = ("incomplete", "fail") if stored["coverage"].get("partial") else ("pass",)
        assert stored["verdict"] in expected, (stored["verdict"], stored["coverage"])
        assert os.path.getsize(raw_dir / "profiles.craw") > 0
        assert seen2["published"] == "interrupted", seen2
        next_id, idle_message = seen2["idle_message"]
        assert idle_message == f"job {next_id} done", idle_message  # not "scanned; analysing" any more
        next_state, next_message, _ = seen2["next_scan"]
        assert next_state == "done", next_message
        assert "needs the sensor stopped" not in next_message
    finally:
        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if p.poll() is None]
        codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes
