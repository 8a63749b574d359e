"""The motion process (issue 41): the EGM endpoint and the executor in a real-time process of their own,
driven by the daemon's :class:`~cellctl.motion.link.MotionLink` over its typed channel, against the
controller simulator's process over loopback UDP.

What these tests hold: a plan runs there with every reply computed for the cycle it answers; pause,
resume and abort cross the channel; a daemon that blocks for 2 s costs no stale cycle (on the
in-process design a blocked loop held every reference); a starved motion process does count stale
cycles; a motion process that dies fails its execution with the reason and a new one serves again;
a daemon that goes away makes the motion process stop the arm and exit.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest

from cellctl.motion import EnvelopeLimits, ExecState, ExecutorConfig
from cellctl.motion.channel import RealtimeSpec
from cellctl.motion.link import MotionLink, MotionSettings, RemoteExecution, envelope_spec
from cellctl.planning import ScanPlan
from drivers.abb_egm.endpoint import EgmEndpointConfig
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.abb_egm.sim.controller import ABB_DEFAULT_PASSWORD
from tests.motion.conftest import (
    controller_process,
    run_async,
    wait_for_segment,
    wait_for_state,
    wait_until,
)
from tests.support.plans import SMALL_SETTINGS
from tests.support.ports import free_port

pytestmark = pytest.mark.slow

#: stale replies allowed on a shared VM: its vCPUs can be taken away by the host for several ms
#: (steal time) whatever this process's priority, a few replies each time (6 of 3817 seen at load 1);
#: the designs these tests tell apart differ by hundreds (a 2 s block of the old design's loop is 500
#: cycles of a ~3800-cycle plan)
STALE_SHARE = 0.005


def stale_allowance(cycles: int) -> float:
    return max(4.0, STALE_SHARE * cycles)


#: the controller's event for an EGM session ended by its communication timeout (RAPID EGM docs)
EVENT_EGM_COMM_TIMEOUT = 41822


def _settings(port: int) -> MotionSettings:
    cfg = ExecutorConfig.from_settings(SMALL_SETTINGS)
    limits = EnvelopeLimits.from_settings(SMALL_SETTINGS, cycle_s=cfg.cycle_s)
    return MotionSettings(
        EgmEndpointConfig(host="127.0.0.1", port=port, reply_spin_us=150.0),
        envelope_spec(limits),
        RealtimeSpec(priority=20),
        log_format="json",
    )


@contextlib.asynccontextmanager
async def motion_cell(plan: ScanPlan) -> AsyncIterator[tuple[MotionLink, object]]:
    """A motion process on a free port and the controller simulator sending to it, its arm at the
    plan's start; both stopped afterwards."""
    port = free_port()
    link = MotionLink(_settings(port))
    await link.start()
    try:
        async with controller_process(None, port, plan.trajectory.q_deg[0]) as ctl:
            await link.wait_for_feedback(30.0)
            deadline = time.monotonic() + 30.0
            while not (got := link.latest()) or not got.ok_to_command:
                assert time.monotonic() < deadline, "the EGM session never became commandable"
                await asyncio.sleep(0.01)
            yield link, ctl
    finally:
        await link.close()


def _execution(link: MotionLink, plan: ScanPlan, tmp_path) -> RemoteExecution:
    return link.execution(
        plan.trajectory,
        ExecutorConfig.from_settings(SMALL_SETTINGS),
        segment_labels=[s.label for s in plan.segments],
        segment_kinds=[s.kind for s in plan.segments],
        work_dir=tmp_path,
    )


def _assert_tracks_plan(rec, plan: ScanPlan, atol_deg: float = 1e-6) -> None:
    """The record's references are the plan's states at their playback times (never another
    cycle's): every reference at its own t_traj, and consecutive cycles one EGM cycle apart."""
    q, _qd, _qdd, _seg = plan.trajectory.sample_many(rec.t_traj_s)
    running = rec.t_traj_s > 0
    np.testing.assert_allclose(rec.q_ref_deg[running], q[running], atol=atol_deg)
    assert np.all(np.diff(rec.cycle) >= 1)


def test_a_plan_runs_in_the_motion_process_with_every_reply_for_its_own_cycle(small_plan, tmp_path):
    async def main():
        async with motion_cell(small_plan) as (link, _ctl):
            ex = _execution(link, small_plan, tmp_path)
            result = await ex.run()
            return link, ex, result

    _link, ex, result = run_async(main())
    assert result.state == ExecState.FINISHED, result.fault
    c = ex.counters
    assert c.cycles == result.cycles > 0.9 * small_plan.trajectory.duration_s / 0.004032
    assert c.egm_stale_cycles <= stale_allowance(c.cycles), c
    assert c.egm_reply_p50_us is not None and c.egm_reply_p50_us < 1000.0, c
    assert 0.0 < c.max_tracking_error_mm < 1.0, c
    rec = ex.record()
    assert rec is not None and rec.cycles == result.cycles
    _assert_tracks_plan(rec, small_plan)
    # the plan and the record stay beside the raw data
    assert (tmp_path / "motion-plan.npz").is_file() and (tmp_path / "motion-record.npz").is_file()


def test_pause_resume_and_abort_cross_the_channel_and_stop_smoothly(small_plan, tmp_path):
    seen = {}

    async def main():
        async with motion_cell(small_plan) as (link, _ctl):
            ex = _execution(link, small_plan, tmp_path)
            run = asyncio.get_running_loop().create_task(ex.run())
            await wait_for_segment(ex, "scan 1", 0.4)
            ex.pause()
            await wait_for_state(ex, "paused")
            tau = ex.progress().t_traj_s
            await asyncio.sleep(0.3)
            seen["held"] = ex.progress().t_traj_s - tau
            ex.resume()
            await wait_for_state(ex, "running")
            await wait_for_segment(ex, "scan 2", 0.5)
            ex.abort()
            return await run, ex

    result, ex = run_async(main())
    assert result.state == ExecState.ABORTED, result.fault
    assert seen["held"] == 0.0  # paused: the playback time stood still
    rec = ex.record()
    # the abort ended at rest, and the commanded speed never stepped more than the joint
    # acceleration limits allow in a cycle
    assert np.max(np.abs(rec.qd_ref_deg_s[-1])) < 1e-3
    dqd = np.abs(np.diff(rec.qd_ref_deg_s, axis=0)) / 0.004032
    assert np.all(dqd.max(axis=0) <= 1.05 * np.asarray(SMALL_SETTINGS.joint_accel_max_deg_s2))
    assert [e.state for e in ex.events].count("paused") >= 1


def test_a_daemon_blocked_for_two_seconds_costs_no_stale_cycle(small_plan, tmp_path):
    async def main():
        async with motion_cell(small_plan) as (link, _ctl):
            ex = _execution(link, small_plan, tmp_path)
            run = asyncio.get_running_loop().create_task(ex.run())
            await wait_for_segment(ex, "scan 1", 0.2)
            before = ex.progress().t_traj_s
            time.sleep(2.0)  # noqa: ASYNC251 - the daemon's interpreter held: no loop, no Python here
            after = ex.progress().t_traj_s
            return await run, ex, after - before

    result, ex, advanced = run_async(main())
    assert result.state == ExecState.FINISHED, result.fault
    # the plan went on while the daemon stood: ~2 s of playback
    assert advanced >= 1.9
    assert ex.counters.egm_stale_cycles <= stale_allowance(ex.counters.cycles), ex.counters
    _assert_tracks_plan(ex.record(), small_plan)


def test_a_starved_motion_process_counts_its_stale_cycles(small_plan, tmp_path):
    async def main():
        async with motion_cell(small_plan) as (link, _ctl):
            ex = _execution(link, small_plan, tmp_path)
            run = asyncio.get_running_loop().create_task(ex.run())
            await wait_for_segment(ex, "scan 1", 0.3)
            stale0 = ex.counters.egm_stale_cycles
            for _ in range(3):  # the motion process not scheduled for 40 ms, three times
                os.kill(link.pid, signal.SIGSTOP)
                time.sleep(0.04)  # noqa: ASYNC251 - a stop this precise, not a wait
                os.kill(link.pid, signal.SIGCONT)
                await asyncio.sleep(0.3)
            return await run, ex, stale0

    result, ex, stale0 = run_async(main())
    assert result.state == ExecState.FINISHED, result.fault
    # each stop left ~10 controller packets waiting more than a cycle: their replies were stale
    assert ex.counters.egm_stale_cycles - stale0 >= 3 * 5, ex.counters
    # and the record says when each left and how late, so a stale cycle can be set against what
    # else the machine did then: every one of the execution's, each later than a cycle or not its own
    with np.load(tmp_path / "motion-record.npz") as z:
        stale_ns, t_host_s = z["stale_ns"], z["t_host_s"]
    assert stale_ns.shape == (ex.counters.egm_stale_cycles, 2)
    assert np.all(stale_ns[:, 0] >= t_host_s[0] * 1e9) and np.all(np.diff(stale_ns[:, 0]) >= 0)
    # the three stops' replies among them, each sent more than a cycle after its packet arrived
    assert np.count_nonzero(stale_ns[:, 1] > 4_032_000) >= 3 * 5


def test_a_killed_motion_process_fails_the_execution_and_a_new_one_serves(small_plan, tmp_path):
    deaths = []

    async def main():
        async with motion_cell(small_plan) as (link, ctl):
            link.on_death = deaths.append
            ex = _execution(link, small_plan, tmp_path)
            run = asyncio.get_running_loop().create_task(ex.run())
            await wait_for_segment(ex, "scan 1", 0.5)
            pid = link.pid
            os.kill(pid, signal.SIGKILL)
            result = await asyncio.wait_for(run, 10.0)
            alive_after_kill = link.alive
            # the controller, unanswered, ends its EGM session after its communication timeout (1 s),
            # and says so in its event log (41822), read over RWS as a cell PC would
            codes: list[int] = []
            config = RwsClientConfig(base_url=ctl.addresses["rws_url"], password=ABB_DEFAULT_PASSWORD)
            async with RwsClient(config) as rws:
                deadline = time.monotonic() + 10.0
                while EVENT_EGM_COMM_TIMEOUT not in codes and time.monotonic() < deadline:
                    await asyncio.sleep(0.2)
                    codes = [e.code for e in await rws.read_event_log()]
            await link.restart()
            return result, alive_after_kill, link.alive, link.pid != pid, codes

    result, alive_after_kill, alive_again, new_pid, codes = run_async(main())
    assert result.state == ExecState.FAULTED
    assert "SIGKILL" in (result.fault or ""), result.fault
    assert not alive_after_kill
    assert deaths and "SIGKILL" in deaths[0]
    assert EVENT_EGM_COMM_TIMEOUT in codes
    assert alive_again and new_pid


def test_a_daemon_that_goes_away_makes_the_motion_process_stop_the_arm_and_exit(small_plan, tmp_path):
    async def main():
        async with motion_cell(small_plan) as (link, _ctl):
            ex = _execution(link, small_plan, tmp_path)
            run = asyncio.get_running_loop().create_task(ex.run())
            await wait_for_segment(ex, "scan 1", 0.5)
            proc = link._proc
            ring = link.history
            # the daemon's end of the channel closes, as when the daemon dies
            link._sock.shutdown(2)
            code = await asyncio.wait_for(proc.wait(), 30.0)
            fb = ring.arrays()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(run, 5.0)
            return code, fb

    code, fb = run_async(main())
    assert code == 0
    # it aborted along the path, smoothly, to rest ...
    with np.load(tmp_path / "motion-record.npz") as rec:
        qd = rec["qd_ref_deg_s"]
    assert np.max(np.abs(qd[-1])) < 1e-3
    dqd = np.abs(np.diff(qd, axis=0)) / 0.004032
    assert np.all(dqd.max(axis=0) <= 1.05 * np.asarray(SMALL_SETTINGS.joint_accel_max_deg_s2))
    # ... and the arm stood before the process left the controller unanswered
    tail = fb.q_deg[-25:]
    assert np.max(np.ptp(tail, axis=0)) < 0.01


def _tracking_where_the_controller_kept_time(rec, after_cycles: int = 75):
    """The record's tracking checks (mm, NaN where none) with the checks in the ``after_cycles`` (the
    0.3 s tracking window) after each jump of the controller's clock left out."""
    track = np.asarray(rec.track_mm, dtype=np.float64).copy()
    for g in np.nonzero(np.diff(rec.cycle) > 1)[0]:
        track[g + 1 : g + 1 + after_cycles] = np.nan
    return track


def _pause_windows(rec, before_s: float = 2.0, after_s: float = 3.0, cycle_s: float = 0.004032):
    """Row ranges around each hold of the playback longer than 1 s (a pause): from ``before_s`` before
    the hold to ``after_s`` after the playback moved again."""
    still = np.diff(rec.t_traj_s) == 0.0
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    n_before, n_after = int(before_s / cycle_s), int(after_s / cycle_s)
    return [
        (max(0, a - n_before), min(len(rec.t_traj_s), b + n_after))
        for a, b in zip(starts, ends, strict=True)
        if (b - a) * cycle_s > 1.0 and rec.t_traj_s[a] > 0.0
    ]


@pytest.mark.long
@pytest.mark.timeout(2400)
def test_ten_long_pauses_over_a_scan_on_a_busy_pc_track_as_well_as_no_pause(sail_plan, tmp_path):
    """Issue 41's re-probe: a 32-35 s pause faulted 2 of 5 resumed demo scans with a 23.8 mm tracking
    error on the in-process executor. Here: the PC kept busy (two busy loops), one run without a
    pause, then ten pauses of 30 s (60 s for the last) spread over the sail's plan (1200 x 800 mm,
    about 3 minutes), each resumed: about 12 minutes."""
    pauses_s = [30.0] * 9 + [60.0]

    async def run(pause: bool, work):
        async with motion_cell(sail_plan) as (link, _ctl):
            ex = _execution(link, sail_plan, work)
            task = asyncio.get_running_loop().create_task(ex.run())
            if pause:
                T = sail_plan.trajectory.duration_s
                for k, hold_s in enumerate(pauses_s):
                    # between 10 % and 85 % of the plan, on passes and links alike
                    target = T * (0.1 + 0.75 * k / (len(pauses_s) - 1))
                    await wait_until(
                        lambda t=target: ex.progress().t_traj_s >= t, 60.0, f"playback {target:.1f} s"
                    )
                    ex.pause()
                    await wait_for_state(ex, "paused")
                    await asyncio.sleep(hold_s)
                    ex.resume()
                    # running again (or, resumed in the retract, at its end before the ramp is up)
                    await wait_until(lambda: ex.state.value in ("running", "finished"), 30.0, "resumed")
            return await task, ex

    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        plain, ex0 = run_async(run(False, tmp_path / "plain"))
        paused, ex1 = run_async(run(True, tmp_path / "paused"))
    finally:
        for b in busy:
            b.kill()
            b.wait()
    assert plain.state == ExecState.FINISHED, plain.fault
    assert paused.state == ExecState.FINISHED, paused.fault
    assert [e.state for e in ex1.events].count("paused") >= len(pauses_s)
    # The tracking error is compared where the simulated controller kept its clock. When its own
    # process is held (a VM stall: its clock jumps 4-8 cycles), its arm integrates the gap on the last
    # reference, and every peak of the first two runs (0.64 mm at t_traj 0.57 s, before any pause;
    # 4.67 mm in the run before) followed such a jump by 9-29 cycles. A real controller's clock does
    # not stop; the figures with those windows are in the message.
    rec0, rec1 = ex0.record(), ex1.record()
    track0, track1 = (
        _tracking_where_the_controller_kept_time(rec0),
        _tracking_where_the_controller_kept_time(rec1),
    )
    base = float(np.nanmax(track0))
    bound = max(1.5 * base, base + 0.3)
    held = _pause_windows(rec1)
    assert len(held) >= len(pauses_s), held
    near = np.concatenate([track1[a:b] for a, b in held])
    figures = dict(base_mm=base, paused_mm=float(np.nanmax(track1)), around_pauses_mm=float(np.nanmax(near)),
                   with_stalls_mm=(ex0.counters.max_tracking_error_mm, ex1.counters.max_tracking_error_mm))  # fmt: skip
    assert float(np.nanmax(near)) <= bound, figures
    assert float(np.nanmax(track1)) <= bound, figures
    # and with the controller's stalls in: far from a fault
    assert ex1.counters.max_tracking_error_mm < 0.5 * ExecutorConfig().tracking_error_max_mm, figures
    # over ~13 minutes on a PC kept busy, a shared VM's host takes its CPUs away now and then (the
    # first run, beside four other engineers' test runs: 712 stale of 170 610, 0.42 %); the old
    # design lost 5-13 % of the cycles on an idle one
    assert ex1.counters.egm_stale_cycles <= 0.01 * ex1.counters.cycles, ex1.counters
