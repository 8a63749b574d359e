"""Zenoh fault: the link between the daemon and the analysis worker cut and restored.

The worker's client session reaches the daemon's listener through a loopback TCP forwarder of our own
(tcp_forwarder.py), so the cut is a real one: every connection reset, new ones refused.

Expected outcome: while the link is down the daemon goes on scanning (progress keeps rising) and then
idles with the job waiting for a worker; liveliness shows the worker gone. When the link returns the
worker's client session reconnects by itself, its token is back, and the job's analysis completes,
exactly once (one report stored, one ``done``), also when the link is cut a second time just after
the cloud went to the worker (that attempt is taken back and retried). Nothing acquired is lost: the
raw files hold every profile the daemon counted, none twice.
"""

from __future__ import annotations

import asyncio
import json
import time

import pytest

from cellctl.api import TriggerAccepted, call
from cellctl.commands.demo_cmd import Processes
from tests.support.cellfaults import (
    FINAL,
    FaultCell,
    expect_analysed,
    fault_cell_config,
    job_history,
    raw_check,
    sensor_overruns,
    stop_cell,
    wait_status,
    wait_until,
    worker_config_via,
)
from tests.support.tcp_forwarder import TcpForwarder

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.timeout(600)]


def _daemon_port(cell: FaultCell) -> int:
    return int(cell.cfg.zenoh.listen[0].rsplit(":", 1)[1])


def test_link_cut_during_scan_and_analysis_the_job_is_analysed_once_after_the_link_returns(tmp_path):
    cell = FaultCell(tmp_path, fault_cell_config(tmp_path))
    workers: Processes | None = None
    fwd = TcpForwarder(("127.0.0.1", _daemon_port(cell)))
    try:
        cell.start(worker=False)
        fwd.start()
        workers = Processes(tmp_path / "logs", worker_config_via(cell, fwd.endpoint), cell.procs.env)
        worker = workers.start("worker", "worker")

        async def go() -> dict:
            seen: dict = {}
            async with cell.client() as c:
                session, keys, follower = c.session, c.keys, c.follower
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
                acc = await call(session, keys.trigger, json.dumps(cell.trigger_request()), TriggerAccepted)
                job_id = seen["job_id"] = acc.job_id
                await wait_status(
                    follower,
                    lambda s: s.job is not None and s.job.state.value == "scanning" and s.job.fraction > 0.1,
                )

                # --- cut 1, during the scan (the streamed job went to the worker when the scan started)
                def assigned() -> int:
                    return len(
                        [e for e in cell.log_events("run", "job_assigned") if e.get("job_id") == job_id]
                    )

                n_assigned = assigned()
                fwd.cut()
                st = await wait_status(follower, lambda s: not s.workers, 30.0)
                seen["worker_gone_state"] = st.state.value
                f0 = st.job.fraction
                st = await wait_status(
                    follower,
                    lambda s: (
                        s.job is not None and (s.job.fraction > f0 + 0.1 or s.job.state.value != "scanning")
                    ),
                )
                seen["progress_while_cut"] = (f0, st.job.fraction, st.job.state.value)
                st = await wait_status(
                    follower, lambda s: s.job is not None and s.job.state.value in ("waiting_for_worker", "analysing")
                    and s.state.value == "idle", 120.0,
                )  # fmt: skip
                await asyncio.sleep(2.0)  # stays: time passing in which no job may go out
                st = follower.latest
                seen["while_cut"] = (st.state.value, st.job.state.value, list(st.workers))
                assert assigned() == n_assigned, "no worker is reachable"

                # --- restore: the client session reconnects, the token returns, the job goes out
                fwd.restore()
                t_restore = time.monotonic()
                await wait_status(follower, lambda s: bool(s.workers), 60.0)
                seen["reconnect_s"] = time.monotonic() - t_restore
                await wait_until(lambda: assigned() > n_assigned, 30.0, what="job assigned")

                # --- cut 2, just after the cloud went to the worker: that attempt is lost
                await asyncio.sleep(0.3)  # stays: the cloud in flight to the worker (no event marks it)
                fwd.cut()
                await wait_status(follower, lambda s: not s.workers, 30.0)
                await asyncio.sleep(3.0)  # stays: the fault, the link cut for 3 s
                fwd.restore()

                # the job's end from its record: the attempt after the first cut may have finished
                # (a small plate's analysis takes well under a second) before this wait begins, and
                # an end seen before wait_for_job is called is, to it, not this job's end
                await wait_until(
                    lambda: cell.job_record(job_id)["state"] in FINAL, 240.0, what="the job's end"
                )
                rec = cell.job_record(job_id)
                seen["final"] = (rec["state"], rec["history"][-1]["message"])
                seen["worker_alive_at_end"] = worker.poll() is None
            seen["sensor"] = await sensor_overruns(cell)
            return seen

        seen = asyncio.run(go())
        job_id = seen["job_id"]
        assert seen["final"][0] in ("done", "failed"), seen
        # liveliness followed the link, and the daemon went on with its work while it was down
        assert seen["worker_gone_state"] in ("scanning", "paused")
        f0, f1, _ = seen["progress_while_cut"]
        assert f1 > f0
        assert seen["while_cut"] == ("idle", "waiting_for_worker", []) or seen["while_cut"][:2] == (
            "idle",
            "analysing",
        ), seen["while_cut"]
        assert seen["worker_alive_at_end"], "the worker process survived both cuts"
        # exactly once: one report accepted by the dispatcher, one `done` in the job's history
        reported = [e for e in cell.log_events("run", "job_reported") if e.get("job_id") == job_id]
        assert len(reported) == 1, reported
        hist = job_history(cell, job_id)
        assert hist.count("done") + hist.count("failed") == 1, hist
        if seen["final"][0] == "done":
            assert json.loads((cell.jobs_dir / job_id / "report.json").read_text())["job_id"] == job_id
        # the second cut cost a retry, not the job
        retries = [e for e in cell.log_events("run", "job_retry") if e.get("job_id") == job_id]
        assert retries and any("disappeared" in e.get("reason", "") for e in retries), retries
        # nothing acquired is lost
        rec = cell.job_record(job_id)
        raw = raw_check(cell, job_id)
        assert raw.profiles == rec["info"]["profiles"] > 1000
        assert raw.unique_frames and not raw.problems, raw.problems
        assert fwd.stats.cuts == 2 and fwd.stats.accepted >= 3
    finally:
        if workers is not None:
            workers.stop_all(grace_s=60.0)
        fwd.close()
        codes = stop_cell(cell)
    assert all(c == 0 for c in codes.values()), codes
    expect_analysed(*seen["final"], seen["sensor"])
