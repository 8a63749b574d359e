"""Emergency stop end to end: real processes, the e-stop pressed on the simulated controller through
its fault-control channel (Zenoh on loopback, never in-process).

Expected: the daemon goes ``emergency_stopped``; the scanning job ends ``interrupted`` with its raw
data intact (every profile received is on disk, none twice) and is re-analysed to a report; the
queued job is cancelled; triggers and ``control/reset`` are refused with a reason while the
controller is still e-stopped; once the controller is released and reset, ``control/reset`` brings
the cell back to ``idle`` without moving anything, and a fresh trigger scans again.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "faults"))

from faultcell import FaultCell, check_job_data

from cellctl.acquisition.reassemble import reassemble
from cellctl.api import ApiCallError, ControlReply, TriggerAccepted, call
from cellctl.commands.scan_cmd import wait_for_job

pytestmark = pytest.mark.slow


def test_emergency_stop_mid_scan_holds_the_cell_until_reset_and_keeps_the_raw_data(tmp_path):
    cell = FaultCell.create(tmp_path)
    try:

        async def go():
            out = {}
            async with cell.client() as c:
                await c.wait_idle()
                a = await c.trigger(plate_id="estop-a")
                b = await call(c.session, c.keys.trigger, json.dumps(cell.trigger_request(plate_id="estop-b")),
                               TriggerAccepted)  # fmt: skip
                out["b"] = b
                await c.wait_scanning(a, min_fraction=0.5)  # enough of the plate to analyse
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
        rec = cell.job_record(a)
        assert rec["state"] in ("interrupted", "done")  # done after the re-analysis
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
        # re-analysed from the raw files to a report
        assert out["reanalyse"].job_state == "waiting_for_worker"
        state, message, report = out["a_report"]
        assert state == "done", message
        assert report is not None and report["job_id"] == a
        assert cell.job_record(a)["state"] == "done"
        # scanning again after the reset
        assert out["d_abort"].job_state in ("scanning", "paused")
    finally:
        codes = cell.stop()
    assert all(code == 0 for code in codes.values()), codes
