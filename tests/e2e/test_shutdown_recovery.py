"""Pause and resume over Zenoh; SIGTERM during a scan: smooth stop, exit 0, raw data complete, job
interrupted; after a restart the job is re-analysed from its raw files."""

from __future__ import annotations

import asyncio
import json
import signal

import pytest

from cellctl.acquisition.reassemble import reassemble
from cellctl.api import ControlReply, Keys, TriggerAccepted, call
from cellctl.api.session import async_get, close_session
from cellctl.commands.demo_cmd import DEMO_DESIGN
from cellctl.commands.scan_cmd import StatusFollower, wait_for_job
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, wait_status

pytestmark = pytest.mark.slow


def test_pause_resume_then_sigterm_mid_scan_interrupts_the_job_and_a_restart_reanalyses_it(tmp_path):
    cell = Cell(tmp_path, tiny_cell_config(tmp_path))
    keys = Keys(cell.cfg.key_prefix)
    pl = cell.cfg.sim.placement
    req = {"plate_id": "cut-short", "design": DEMO_DESIGN,
           "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}}  # fmt: skip
    try:
        cell.start(worker=False)

        async def scan_then_term():
            session = await open_client(cell.cfg)
            follower = StatusFollower(session, keys)
            try:
                await wait_status(follower, lambda s: s.state.value == "idle")
                acc = await call(session, keys.trigger, json.dumps(req), TriggerAccepted)
                await wait_status(
                    follower,
                    lambda s: s.job is not None and s.job.state.value == "scanning" and s.job.fraction > 0.2,
                )
                # pause and resume over Zenoh: the arm stops on the path and goes on from there
                paused = await call(session, keys.control("pause"), b"", ControlReply)
                assert paused.job_id == acc.job_id
                st = await wait_status(follower, lambda s: s.state.value == "paused", timeout_s=20.0)
                held = st.job.fraction
                await asyncio.sleep(1.0)  # stays: time passing in which a paused job must not move
                assert follower.latest.state.value == "paused"
                assert abs(follower.latest.job.fraction - held) < 0.01
                await call(session, keys.control("resume"), b"", ControlReply)
                await wait_status(follower, lambda s: s.state.value == "scanning", timeout_s=20.0)
                await wait_status(
                    follower,
                    lambda s: s.job is not None and s.job.state.value == "scanning" and s.job.fraction > 0.5,
                )
                return acc.job_id
            finally:
                follower.close()
                await asyncio.to_thread(close_session, session)

        job_id = asyncio.run(scan_then_term())
        daemon = cell.proc("run")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(60) == 0
        rec = cell.job_record(job_id)
        assert rec["state"] == "interrupted", rec["history"]
        assert rec["info"]["execution"] == "aborted"  # stopped along the path, not a fault stop
        raw = cell.jobs_dir / job_id / "raw"
        res = reassemble(raw, final=False)
        # every profile the daemon received is in the raw files
        assert len(res.cloud) == rec["info"]["profiles"] > 300
        assert res.cloud.n_valid > 100_000  # half a scan of the plate

        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if n != "run"]
        cell.start(sim=False)

        async def reanalyse():
            session = await open_client(cell.cfg)
            follower = StatusFollower(session, keys)
            try:
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers)
                replies = await async_get(
                    session,
                    f"{keys.prefix}/control/reanalyse",
                    payload=json.dumps({"job_id": job_id}),
                    timeout_s=10.0,
                )
                assert replies and replies[0].ok is not None, replies and replies[0].err.payload.to_bytes()
                return await wait_for_job(follower, job_id, 240.0)
            finally:
                follower.close()
                await asyncio.to_thread(close_session, session)

        state, message, report = asyncio.run(reanalyse())
        assert state == "done", message
        assert report is not None and report.job_id == job_id
        rec = cell.job_record(job_id)
        assert [h["state"] for h in rec["history"]].count("interrupted") == 1
        assert json.loads((cell.jobs_dir / job_id / "report.json").read_text())["job_id"] == job_id
    finally:
        codes = cell.stop()
    assert all(c == 0 for c in codes.values()), codes
