"""Worker fault: the worker analysing a streamed cloud ``kill -9``'d mid-stream, while the plate is
still being scanned (issue 22: a worker that dies mid-stream costs a retry from the stored passes,
never a job).

Expected outcome: the scan goes on undisturbed; the daemon sees the worker's token go and takes the
streamed job back (one retry); a restarted worker gets it and every chunk from the first
(``seq`` 0, replayed from what the daemon kept), then the rest as the scan produces them; the job
completes once, from the stream (no fall-back to the whole cloud), with every profile on disk.
"""

from __future__ import annotations

import asyncio
import json

import pytest

from cellctl.api import TriggerAccepted, call
from cellctl.commands.scan_cmd import wait_for_job
from tests.support.cellfaults import (
    FINAL,
    FaultCell,
    expect_analysed,
    fault_cell_config,
    job_history,
    kill9_tree,
    pid_alive,
    raw_check,
    sensor_overruns,
    stop_cell,
    wait_status,
    wait_until,
)

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.timeout(600)]


def test_worker_killed_mid_stream_the_restarted_worker_gets_every_pass_and_completes_the_job(tmp_path):
    cell = FaultCell(tmp_path, fault_cell_config(tmp_path))
    seen: dict = {}
    try:
        cell.start()
        first = cell.proc("worker")

        async def go() -> None:
            async with cell.client() as c:
                session, keys, follower = c.session, c.keys, c.follower
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
                acc = await call(session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted)
                job_id = seen["job_id"] = acc.job_id

                def chunks_out() -> list[dict]:
                    return [e for e in cell.log_events("run", "stream_chunk") if e.get("job_id") == job_id]

                # the worker holds the streamed job and the first pass went out: kill it mid-stream
                await wait_until(
                    lambda: (
                        (chunks_out() and [e for e in cell.log_events("worker", "job_started")
                                           if e.get("job_id") == job_id])
                        or cell.job_record(job_id)["state"] in FINAL
                    ),
                    240.0,
                    what="the first pass streamed to the worker",
                )  # fmt: skip
                seen["state_at_kill"] = cell.job_record(job_id)["state"]
                seen["chunks_before_kill"] = len(chunks_out())
                seen["killed"] = kill9_tree(first.pid)
                await wait_status(follower, lambda s: not s.workers, 30.0)
                cell.procs.start("worker2", "worker")
                state, message, _ = await wait_for_job(follower, job_id, 300.0)
                seen["final"] = (state, message)
                seen["chunks"] = len(chunks_out())
            seen["sensor"] = await sensor_overruns(cell)

        asyncio.run(go())
        job_id = seen["job_id"]
        assert seen["state_at_kill"] == "scanning", seen  # killed while the plate was being scanned
        assert 1 <= seen["chunks_before_kill"] < seen["chunks"], seen
        assert first.wait(10) == -9
        assert not any(pid_alive(p) for p in seen["killed"]), "no process of the killed worker survives"
        retries = [e for e in cell.log_events("run", "job_retry") if e.get("job_id") == job_id]
        assert len(retries) == 1 and "disappeared" in retries[0]["reason"], retries
        # the restarted worker got the whole stream, from seq 0, in its attempt
        sent = [e for e in cell.log_events("run", "stream_sent") if e.get("job_id") == job_id]
        assert len(sent) == 1 and sent[0]["attempt"] == 2 and sent[0]["chunks"] == seen["chunks"], sent
        assert sent[0]["worker_id"].endswith(str(cell.proc("worker2").pid)), sent
        assert not cell.log_events("worker2", "stream_incomplete")
        reported = [e for e in cell.log_events("run", "job_reported") if e.get("job_id") == job_id]
        assert len(reported) == 1 and reported[0]["attempt"] == 2, reported
        hist = job_history(cell, job_id)
        assert hist.count("done") + hist.count("failed") == 1 and hist[-1] in ("done", "failed"), hist
        rec = cell.job_record(job_id)
        if seen["final"][0] == "done":
            timings = rec["info"]["analysis_timings_s"]
            assert timings["stream_chunks"] == seen["chunks"] and timings["stream_fallback"] == 0, timings
        raw = raw_check(cell, job_id)
        assert raw.profiles == rec["info"]["profiles"] > 300
        assert raw.unique_frames and not raw.problems
    finally:
        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if p.poll() is None]
        codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes
    expect_analysed(*seen["final"], seen["sensor"])
