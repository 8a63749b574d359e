"""Emergency stop end to end: real processes, the e-stop pressed on the simulated controller through
its fault-control channel (Zenoh on loopback, never in-process).

Expected: the daemon goes ``emergency_stopped``; the scanning job ends ``interrupted`` with its raw
data intact (every profile received is on disk, none twice) and is re-analysed (a report: the
truth's verdict when the half scan covered the plate, else ``incomplete`` for what it covered); the
queued job is cancelled; triggers and ``control/reset`` are refused with a reason while the
controller is still e-stopped; once the controller is released and reset, ``control/reset`` brings
the cell back to ``idle`` without moving anything, and a fresh trigger scans again.
"""

from __future__ import annotations

import asyncio
import json

import pytest

from cellctl.acquisition.reassemble import reassemble
from cellctl.api import ApiCallError, ControlReply, TriggerAccepted, call
from cellctl.commands.scan_cmd import wait_for_job
from tests.support.faultcell import FaultCell, check_job_data
from tests.support.skiplog import record_fallback

pytestmark = pytest.mark.slow


async def _scan_to(cell: FaultCell, c, fraction: float, attempts: int = 2) -> str:
    """Trigger a scan and wait until it has done ``fraction``; returns its job id.

    On this shared 2-core machine a starved simulated controller can fault a scan by itself (late on
    more than 1 % of its cycles, silent past the executor's limit); that is not what is under test
    here, so such a scan is reset and triggered again, once (``attempts``), recorded as a fallback
    with the overrun counts that prove it (.ci/run counts it). A scan that ended early with the
    controller keeping time fails the case.
    """
    for attempt in range(attempts):
        before = (await cell.fault()).stats["egm"]
        job_id = await c.trigger(plate_id=f"estop-a{attempt}")

        def there(s, job_id=job_id):
            jp = c.follower.jobs.get(job_id)
            return jp is not None and (
                jp.state.value in ("done", "failed", "aborted", "interrupted")
                or (jp.state.value == "scanning" and jp.fraction >= fraction)
            )

        await c.wait(there, timeout_s=240.0)
        job = c.follower.jobs[job_id]
        if job.state.value == "scanning":
            return job_id
        after = (await cell.fault()).stats["egm"]
        overruns, cycles = after["overruns"] - before["overruns"], after["cycles"] - before["cycles"]
        assert overruns > 0.01 * max(cycles, 1), (
            f"the scan ended {job.state.value} before the e-stop with the controller keeping time "
            f"({overruns} of {cycles} cycles late): {job.message}"
        )
        if attempt == attempts - 1:
            break
        record_fallback(
            f"fallback: simulators starved (controller overruns {overruns} of {cycles} cycles): scan "
            f"{job.state.value} before the e-stop ({job.message}), triggered again"
        )
        await c.control("reset")
        await c.wait(lambda s: s.state.value == "idle", timeout_s=30.0)
    pytest.fail(f"no scan reached {fraction:.0%} in {attempts} attempts, the controller starved each time")


def test_emergency_stop_mid_scan_holds_the_cell_until_reset_and_keeps_the_raw_data(tmp_path):
    # no HTML rendering: not under test here, and a shutdown waits for a render in progress
    cell = FaultCell.create(tmp_path, daemon__write_html_report=False)
    try:

        async def go():
            out = {}
            async with cell.client() as c:
                await c.wait_idle()
                a = await _scan_to(cell, c, 0.5)  # enough of the plate to analyse
                b = await call(c.session, c.keys.trigger, json.dumps(cell.trigger_request(plate_id="estop-b")),
                               TriggerAccepted)  # fmt: skip
                out["b"] = b
                await cell.fault(controller={"action": "emergency_stop"})
                st = await c.wait(lambda s: s.state.value == "emergency_stopped", timeout_s=60.0)
                out["estop_status"] = st
                out["a_end"] = await c.wait(
                    lambda s: a in c.follower.jobs and c.follower.jobs[a].state.value == "interrupted"
                )
                jobs_before = sorted(p.name for p in cell.jobs_dir.iterdir())
                with pytest.raises(ApiCallError) as refused:
                    await c.trigger(plate_id="estop-c")
                out["trigger_refused"] = refused.value.error
                with pytest.raises(ApiCallError) as early:
                    await c.control("reset")
                out["reset_refused"] = early.value.error
                out["jobs_unchanged"] = sorted(p.name for p in cell.jobs_dir.iterdir()) == jobs_before
                out["still_stopped"] = c.follower.latest.state.value
                # the operator releases and resets the e-stop on the controller, then resets the cell
                await cell.fault(controller={"action": "reset_emergency_stop"})
                out["reset"] = await c.control("reset")
                idle = await c.wait(lambda s: s.state.value == "idle", timeout_s=10.0)
                out["idle"] = idle
                out["nothing_new"] = sorted(p.name for p in cell.jobs_dir.iterdir()) == jobs_before
                out["check"] = check_job_data(cell, a)  # before the re-analysis adds states
                # re-analysable: the raw data of the stopped scan goes to the worker
                out["reanalyse"] = await c.control("reanalyse", a)
                out["a_report"] = await wait_for_job(c.follower, a, 240.0)
                # and the cell scans again on a fresh trigger
                d = await c.trigger(plate_id="estop-d")
                await c.wait_scanning(d, min_fraction=0.05)
                out["d_abort"] = await call(
                    c.session, c.keys.control("abort"), json.dumps({"job_id": d}), ControlReply
                )
                out["a"] = a
            return out

        out = asyncio.run(go())
        a, b = out["a"], out["b"]
        assert b.state == "queued"
        assert out["estop_status"].message.startswith("emergency stop during job")
        # the stopped job: interrupted (not failed), raw data intact and readable
        rec = cell.job_record(a)  # (its final state comes from the re-analysis, below)
        states = [h["state"] for h in rec["history"]]
        assert states[states.index("scanning") + 1] == "interrupted", states
        assert rec["info"]["stopped_by"] == "emergency_stop"
        check = out["check"]
        assert check.raw_profiles == rec["info"]["profiles"] > 100
        res = reassemble(cell.jobs_dir / a / "raw", final=False)
        assert len(res.cloud) == check.raw_profiles
        # the queued job never started
        rec_b = cell.job_record(b.job_id)
        assert [h["state"] for h in rec_b["history"]] == ["queued", "cancelled"]
        assert "emergency_stopped" in rec_b["history"][-1]["message"]
        # refusals while the controller is still e-stopped, and nothing created or moved meanwhile
        assert (
            out["trigger_refused"].code == "not_allowed" and "control/reset" in out["trigger_refused"].message
        )
        assert out["reset_refused"].code == "not_allowed" and "emergencystop" in out["reset_refused"].message
        assert out["jobs_unchanged"] and out["still_stopped"] == "emergency_stopped"
        # reset: idle, nothing started by itself
        assert (out["reset"].action, out["reset"].state) == ("reset", "idle")
        assert out["idle"].job is None or out["idle"].job.job_id == a
        assert out["nothing_new"]
        # re-analysed: the raw files rebuilt into a cloud that a worker analysed, always a report. A
        # scan stopped half way may have covered the plate (the passes over it done, observed: coverage
        # 1.0): then the verdict is the truth's (the default forming error passes); or part of it:
        # analysed with the placement it was planned from, reported for what it covered, never a pass
        assert out["reanalyse"].job_state == "waiting_for_worker"
        state, message, report = out["a_report"]
        rec = cell.job_record(a)
        assert rec["info"]["points"] > 10_000 and (cell.jobs_dir / a / "cloud.bin").stat().st_size > 0
        assert state == "done", message
        assert report is not None and report.job_id == a
        stored = json.loads((cell.jobs_dir / a / "report.json").read_text())
        expected = ("incomplete", "fail") if stored["coverage"].get("partial") else ("pass",)
        assert stored["verdict"] in expected, (stored["verdict"], stored["coverage"])
        assert rec["state"] == state
        # scanning again after the reset
        assert out["d_abort"].job_state in ("scanning", "paused")
    finally:
        codes = cell.stop()
    assert all(code == 0 for code in codes.values()), codes
