"""Controller faults: operator actions at the cabinet or pendant, and an RWS server that fails.

Injected into the simulated controller through ``<prefix>/sim/faults``; the daemon sees them only
through EGM and RWS, as it would on a real cell. Each case states its expected outcome and checks
that nothing acquired is lost and the job's history is consistent.
"""

from __future__ import annotations

import asyncio

import pytest

from tests.support.faultcell import ApiCallError, FaultCell, module_cell, run_job

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

RWS_TIMEOUT_S = 1.5


# a short RWS timeout, so "slow" (4 s) is over it while the simulator's normal answers are not
cell = module_cell("ctrlfaults", robot__rws_timeout_s=RWS_TIMEOUT_S)


def _stopped_mid_scan(run, cell: FaultCell, state: str = "failed") -> None:
    """What every controller stop mid-scan leaves: a stopped job with its raw data, nothing lost."""
    assert run.state == state, run.message
    if state == "failed":
        assert run.message.startswith("motion fault"), run.message
    assert run.info["execution"] == "faulted"
    assert 0 < run.check.raw_profiles == run.info["profiles"]
    assert run.info["max_tracking_error_mm"] <= cell.cfg.robot.tracking_error_max_mm


def _cell_state_after(cell: FaultCell) -> str:
    """The cell state once it settled after a job ended (the job's end is published first)."""

    async def go():
        async with cell.client() as c:
            st = await c.wait(lambda s: s.state.value not in ("scanning", "planning", "paused"), 120.0)
            return st.state.value

    return asyncio.run(go())


def test_motors_off_mid_pass_stops_the_job_and_the_next_trigger_switches_them_on_again(cell):
    """Motors switched off at the cabinet at 30 % of the scan. Expected: the controller reports motors
    off over EGM, the executor stops (fault, hold), the job fails with "motion fault: controller
    stopped EGM (motors off ...)", the cell is ``faulted``; raw data intact. The next job (next case)
    switches the motors on through RWS by itself."""
    run = asyncio.run(run_job(cell, [(0.3, {"controller": {"action": "motors_off"}})]))
    _stopped_mid_scan(run, cell)
    assert "motors OFF" in run.message, run.message
    assert _cell_state_after(cell) == "faulted"
    assert run.replies[0].controller["ctrl_state"] == "motoroff"


def test_rapid_stopped_from_the_pendant_stops_the_job_and_the_next_trigger_restarts_it(cell):
    """RAPID stopped from the pendant at 30 %: the EGM session drops out of RUNNING. Expected: the job
    fails with a motion fault naming RAPID / EGM state, the cell is ``faulted``, raw data intact; a
    new trigger is accepted (the daemon resets the program pointer and starts it again)."""
    run = asyncio.run(run_job(cell, [(0.3, {"controller": {"action": "stop_rapid"}})]))
    _stopped_mid_scan(run, cell)
    assert run.replies[0].controller["rapid_state"] == "stopped"
    assert _cell_state_after(cell) == "faulted"


def test_guard_stop_mid_pass_stops_the_job_and_leaves_the_cell_faulted(cell):
    """The safety guard opens at 30 % (auto stop). Expected: motion fault, job failed, cell
    ``faulted`` (not e-stopped), raw data intact; once the guard closes the cell takes triggers."""
    try:
        run = asyncio.run(run_job(cell, [(0.3, {"controller": {"action": "guard_stop"}})], clear_after=False))
        _stopped_mid_scan(run, cell)
        assert run.replies[0].controller["ctrl_state"] == "guardstop"
        assert _cell_state_after(cell) == "faulted"
    finally:
        cell.fault_sync(clear=True, controller={"action": "reset_guard_stop"})


def test_emergency_stop_mid_pass_holds_the_cell_until_the_controller_and_the_operator_reset_it(cell):
    """E-stop pressed at 30 %. Expected: the job is ``interrupted`` ("emergency stop during the scan; raw
    data kept"), nothing acquired lost; the cell is
    ``emergency_stopped``; a trigger is refused (not_allowed) and so is control/reset while the
    controller is still e-stopped; after the e-stop is released and reset on the controller,
    control/reset brings the cell to ``idle``."""

    async def after(job_id: str):
        async with cell.client() as c:
            st = await c.wait(lambda s: s.state.value == "emergency_stopped", 120.0)
            with pytest.raises(ApiCallError) as trig:
                await c.trigger()
            with pytest.raises(ApiCallError) as early_reset:
                await c.control("reset")
            await cell.fault(controller={"action": "reset_emergency_stop"})
            reply = await c.control("reset")
            idle = await c.wait(lambda s: s.state.value == "idle", 120.0)
            return st, trig.value, early_reset.value, reply, idle

    try:
        run = asyncio.run(
            run_job(cell, [(0.3, {"controller": {"action": "emergency_stop"}})], clear_after=False)
        )
        _stopped_mid_scan(run, cell, state="interrupted")
        assert "emergency stop" in run.message and "raw data kept" in run.message, run.message
        assert run.replies[0].controller["ctrl_state"] == "emergencystop"
        st, trig, early_reset, reply, idle = asyncio.run(after(run.job_id))
    finally:
        asyncio.run(_release_emergency_stop(cell))
    assert st.state.value == "emergency_stopped"
    assert trig.error.code == "not_allowed" and "emergency" in trig.error.message
    assert early_reset.error.code == "not_allowed"
    assert reply.state == "idle" and idle.state.value == "idle"


async def _release_emergency_stop(cell: FaultCell) -> None:
    """Whatever a failed case left: release the e-stop on the controller, reset the cell."""
    state = await cell.fault(clear=True)
    if state.controller["ctrl_state"] == "emergencystop":
        await cell.fault(controller={"action": "reset_emergency_stop"})
    async with cell.client() as c:
        st = await c.wait(lambda s: True, 120.0)
        if st.state.value in ("emergency_stopped", "faulted"):
            await c.control("reset")


@pytest.mark.parametrize(
    ("name", "rws"),
    [
        ("unavailable_503", {"error_status": 503}),
        ("connection_refused", {"serving": False}),
        ("slow_over_the_client_timeout", {"delay_s": 4.0}),
    ],
)
def test_rws_failing_before_motion_fails_the_job_with_a_clear_message_and_nothing_moves(cell, name, rws):
    """RWS answers 503, refuses connections, or answers slower than the client's timeout when a job
    starts. Expected: the job fails before any motion with a message naming RWS, no EGM session was
    started (the controller's session counter is unchanged), no raw profile exists, the daemon keeps
    running; once RWS is back a trigger is taken again."""

    async def go():
        before = await cell.fault(rws=rws)
        try:
            async with cell.client() as c:
                await c.wait_idle_or_faulted()
                job_id = await c.trigger()
                final = await c.wait_job_end(job_id)
        finally:
            after = await cell.fault(clear=True)
        return job_id, final, before, after

    job_id, final, before, after = asyncio.run(go())
    assert final.job.state.value == "failed", final.job.message
    assert "rws" in final.job.message.lower() or "controller" in final.job.message.lower(), final.job.message
    assert after.stats["egm"]["sessions"] == before.stats["egm"]["sessions"]  # nothing moved
    rec = cell.job_record(job_id)
    assert rec["state"] == "failed" and "scanning" not in [h["state"] for h in rec["history"]]
    assert (
        not (cell.jobs_dir / job_id / "raw" / "profiles.craw").exists() or rec["info"].get("profiles", 0) == 0
    )
    assert cell.proc("run").poll() is None
