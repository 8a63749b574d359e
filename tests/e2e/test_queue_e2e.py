"""The bounded trigger queue through real processes (sim, daemon, worker; Zenoh on loopback).

One cell (``[daemon] queue_max = 2`` from the environment) walks the queue's life: a trigger while
busy is queued with its position, a full queue refuses with a reason and creates nothing, a queued
job is cancelled by ``abort {"job_id"}``, the next queued job starts by itself when the robot is
free, and a daemon stopped with a job still queued cancels it: after the restart nothing moves
until a fresh trigger.
"""

from __future__ import annotations

import asyncio
import json
import signal

import pytest

from cellctl.api import ApiCallError, ControlReply, Keys, TriggerAccepted, call
from cellctl.api.session import close_session
from cellctl.commands.demo_cmd import DEMO_DESIGN
from cellctl.commands.scan_cmd import StatusFollower
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, wait_status

pytestmark = pytest.mark.slow


def _req(cell: Cell, plate_id: str) -> str:
    pl = cell.cfg.sim.placement
    return json.dumps({"plate_id": plate_id, "design": DEMO_DESIGN,
                       "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}})  # fmt: skip


def _scanning(job_id: str, min_fraction: float):
    return lambda s: (
        s.job is not None and s.job.job_id == job_id and s.job.state.value == "scanning"
        and s.job.fraction >= min_fraction
    )  # fmt: skip


def test_queued_triggers_wait_in_order_are_cancellable_and_never_survive_a_restart(tmp_path):
    cell = Cell(tmp_path, tiny_cell_config(tmp_path))
    cell.procs.env["CELL_DAEMON__QUEUE_MAX"] = "2"  # the [daemon] section through the environment
    keys = Keys(cell.cfg.key_prefix)
    try:
        cell.start()

        async def walk_the_queue():
            session = await open_client(cell.cfg)
            follower = StatusFollower(session, keys)
            out = {}
            try:
                await wait_status(follower, lambda s: s.state.value == "idle" and s.workers)
                a = await call(session, keys.trigger, _req(cell, "plate-a"), TriggerAccepted)
                b = await call(session, keys.trigger, _req(cell, "plate-b"), TriggerAccepted)
                c = await call(session, keys.trigger, _req(cell, "plate-c"), TriggerAccepted)
                with pytest.raises(ApiCallError) as full:
                    await call(session, keys.trigger, _req(cell, "plate-d"), TriggerAccepted)
                out.update(a=a, b=b, c=c, full=full.value.error)
                out["jobs_after_full"] = sorted(p.name for p in cell.jobs_dir.iterdir())
                st = await wait_status(follower, lambda s: s.queued == 2)
                out["queue"] = [(q.job_id, q.position) for q in st.queue]
                out["cancel_c"] = await call(
                    session, keys.control("abort"), json.dumps({"job_id": c.job_id}), ControlReply
                )
                st = await wait_status(follower, lambda s: s.queued == 1)
                out["queue_after_cancel"] = [(q.job_id, q.position) for q in st.queue]
                with pytest.raises(ApiCallError) as unknown:
                    await call(session, keys.control("abort"), json.dumps({"job_id": c.job_id}), ControlReply)
                out["cancel_again"] = unknown.value.error
                # the robot is freed by aborting A: B, queued, starts by itself and scans
                await wait_status(follower, _scanning(a.job_id, 0.05), timeout_s=120.0)
                await call(session, keys.control("abort"), json.dumps({"job_id": a.job_id}), ControlReply)
                # (past the approach: the executor ignores a pause while it moves to the start)
                await wait_status(follower, _scanning(b.job_id, 0.02), timeout_s=120.0)
                out["a_end"] = follower.jobs[a.job_id].state.value
                # B held (paused on its path) so that it is surely busy when E comes
                await call(session, keys.control("pause"), json.dumps({"job_id": b.job_id}), ControlReply)
                e = await call(session, keys.trigger, _req(cell, "plate-e"), TriggerAccepted)
                out["e"] = e
                await wait_status(
                    follower,
                    lambda s: s.state.value == "paused" and [q.job_id for q in s.queue] == [e.job_id],
                )
                return out
            finally:
                follower.close()
                await asyncio.to_thread(close_session, session)

        out = asyncio.run(walk_the_queue())
        a, b, c, e = out["a"], out["b"], out["c"], out["e"]
        assert (a.state, b.state, c.state) == ("started", "queued", "queued")
        assert (b.queue_position, c.queue_position) == (1, 2)
        assert out["full"].code == "queue_full" and "queue_max = 2" in out["full"].message
        assert out["jobs_after_full"] == sorted([a.job_id, b.job_id, c.job_id])  # the refusal made nothing
        assert out["queue"] == [(b.job_id, 1), (c.job_id, 2)]
        assert (out["cancel_c"].job_id, out["cancel_c"].job_state) == (c.job_id, "cancelled")
        assert out["queue_after_cancel"] == [(b.job_id, 1)]
        assert out["cancel_again"].code == "no_job" and out["cancel_again"].field == "job_id"
        assert out["a_end"] == "aborted"
        assert (e.state, e.queue_position) == ("queued", 1)
        rec_c = cell.job_record(c.job_id)
        assert [h["state"] for h in rec_c["history"]] == ["queued", "cancelled"]
        assert not (cell.jobs_dir / c.job_id / "raw").exists()  # a cancelled job never moved the robot
        hist_b = [h["state"] for h in cell.job_record(b.job_id)["history"]]
        assert hist_b[0] == "queued" and "planning" in hist_b and "scanning" in hist_b

        # SIGTERM with B paused and E queued: B interrupted, E cancelled; the restart starts nothing
        daemon = cell.proc("run")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(60) == 0
        assert cell.job_record(b.job_id)["state"] == "interrupted"
        rec_e = cell.job_record(e.job_id)
        assert rec_e["state"] == "cancelled" and "trigger it again" in rec_e["history"][-1]["message"]
        cell.procs.procs = [(n, p) for n, p in cell.procs.procs if n != "run"]
        cell.start(sim=False, worker=False)

        async def after_restart():
            session = await open_client(cell.cfg)
            follower = StatusFollower(session, keys)
            try:
                seen = [await wait_status(follower, lambda s: s.state.value == "idle")]
                while len(seen) < 4:  # a few periodic publications: nothing starts on its own
                    await follower.next(5.0)
                    seen.append(follower.latest)
                return seen
            finally:
                follower.close()
                await asyncio.to_thread(close_session, session)

        seen = asyncio.run(after_restart())
        assert all(s.state.value == "idle" and s.job is None and s.queued == 0 for s in seen), seen
        assert len(list(cell.jobs_dir.iterdir())) == 4  # A, B, C, E: nothing new
    finally:
        codes = cell.stop()
    assert all(code == 0 for code in codes.values()), codes
