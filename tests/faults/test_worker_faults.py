"""Worker fault: the only analysis worker ``kill -9``'d mid-analysis, its analysis child with it.

Expected outcome: the daemon sees the worker's liveliness token go, takes the job back (a retry, not
a lost job) and keeps it queued; a restarted worker gets it and the job completes, exactly once. No
process of the killed worker survives. The daemon's state stays consistent (idle while it waits,
the job ``waiting_for_worker`` / ``analysing``, never failed) and the raw files hold every profile.
(Two workers with one killed is covered at the dispatcher level in tests/zenoh.)
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
    children_of,
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


def test_worker_killed_mid_analysis_the_restarted_worker_completes_the_job_once(tmp_path):
    cell = FaultCell(tmp_path, fault_cell_config(tmp_path))
    try:
        # the first worker holds its analysis (the product's, a minute late): the real one now ends
        # well under a second after the last pass, before a test could see the job "analysing"
        cell.start(worker=False)
        cell.procs.start("worker", "worker", "--analysis", "tests.support.zworker_fns:product_analysis_held")
        first = cell.proc("worker")

        async def go() -> dict:
            seen: dict = {}
            async with cell.client() as c:
                session, keys, follower = c.session, c.keys, c.follower
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
                acc = await call(session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted)
                job_id = seen["job_id"] = acc.job_id
                # the scan is over and the worker analyses the streamed cloud (it holds the job from
                # the scan's start; tests/faults/test_stream_worker_kill.py kills it mid-stream)
                await wait_until(
                    lambda: (
                        (
                            [e for e in cell.log_events("worker", "job_started") if e.get("job_id") == job_id]
                            and cell.job_record(job_id)["state"] == "analysing"
                        )
                        or cell.job_record(job_id)["state"] in FINAL
                    ),
                    240.0,
                    what="worker started the job",
                )
                assert cell.job_record(job_id)["state"] not in FINAL, cell.job_record(job_id)["history"]
                seen["killed"] = kill9_tree(first.pid)
                seen["analysis_children"] = [p for p in seen["killed"] if p != first.pid]
                st = await wait_status(follower, lambda s: not s.workers, 30.0)
                await asyncio.sleep(1.0)  # stays: time passing with no worker, in which nothing may start
                st = follower.latest
                seen["while_no_worker"] = (st.state.value, st.job.state.value if st.job else None)
                # restart the worker: it takes the queued job
                cell.procs.start("worker2", "worker")
                state, message, _ = await wait_for_job(follower, job_id, 240.0)
                seen["final"] = (state, message)
            seen["sensor"] = await sensor_overruns(cell)
            return seen

        seen = asyncio.run(go())
        job_id = seen["job_id"]
        assert seen["final"][0] in ("done", "failed"), seen
        assert first.wait(10) == -9
        assert seen["analysis_children"], "the worker had an analysis child to kill"
        assert not any(pid_alive(p) for p in seen["killed"]), "no process of the killed worker survives"
        # issue 24: with no worker present the job waits for one, as docs/operations.md says (it said
        # analysing); the cell's message names the job's end once it is done
        assert seen["while_no_worker"] == ("idle", "waiting_for_worker"), seen
        retries = [e for e in cell.log_events("run", "job_retry") if e.get("job_id") == job_id]
        assert len(retries) == 1 and "disappeared" in retries[0]["reason"], retries
        reported = [e for e in cell.log_events("run", "job_reported") if e.get("job_id") == job_id]
        assert len(reported) == 1 and reported[0]["worker_id"].endswith(str(cell.proc("worker2").pid)), (
            reported
        )
        hist = job_history(cell, job_id)
        assert hist.count("done") + hist.count("failed") == 1 and hist[-1] in ("done", "failed"), hist
        raw = raw_check(cell, job_id)
        assert raw.profiles == cell.job_record(job_id)["info"]["profiles"] > 300
        assert raw.unique_frames and not raw.problems
        assert children_of(cell.proc("worker2").pid), "the restarted worker has its analysis child"
    finally:
        # the killed worker is already reaped; stop the rest
        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if p.poll() is None]
        codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes
    expect_analysed(*seen["final"], seen["sensor"])
