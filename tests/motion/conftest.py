"""Shared plans and the loopback harness (EGM endpoint + controller simulator) for the motion tests.

The controller simulator runs as its own process (``python -m drivers.abb_egm.sim``) and is reached
only over its sockets: EGM through the endpoint (its feedback is the arm's true position, as the
controller reports it), RWS for the panel (motors off), its fault channel for wire faults.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.motion import ExecutionResult, ExecutorConfig, MotionExecutor
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.abb_egm.sim.controller import ABB_DEFAULT_PASSWORD
from drivers.runtime import precise_event_loop
from drivers.sim.fault_channel import send_fault_request
from tests.support.waits import wait_until as wait_for_event

REPO = Path(__file__).resolve().parents[2]

SAIL_PLACEMENT = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
#: a small plate and fast sweeps keep the executions short; the geometry is the real planner's
SMALL_SETTINGS = PlannerSettings(
    speed_mm_s=200.0, placement_uncertainty_mm=5.0, placement_uncertainty_deg=0.5
)
SMALL_PLACEMENT = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0)


@pytest.fixture(scope="session")
def sail_plan() -> ScanPlan:
    """The 1200 x 800 sail plate at the default placement with the cell.toml defaults."""
    return plan_scan(design_mesh(plate_spec("sail"), pitch_mm=10.0), SAIL_PLACEMENT, PlannerSettings())


@pytest.fixture(scope="session")
def small_plan() -> ScanPlan:
    """A 200 x 150 sail-shaped plate: a full plan (approach, raster, edges, retract) of a few seconds."""
    mesh = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    return plan_scan(mesh, SMALL_PLACEMENT, SMALL_SETTINGS)


@dataclass
class Controller:
    """The simulated controller process, seen only through its sockets."""

    proc: subprocess.Popen
    addresses: dict[str, Any]
    endpoint: EgmEndpoint

    async def faults(self, **egm: Any) -> dict[str, Any]:
        """Set EGM wire faults over the simulator's fault channel (``faults(stop_sending=True)``);
        returns its reply (the knobs in force and its counters)."""
        reply = await send_fault_request(self.addresses["fault"], {"egm": egm})
        assert reply["ok"], reply
        return reply

    async def motors_off(self) -> None:
        """Switch the motors off through RWS, as the pendant's or a cell PC's request would."""
        config = RwsClientConfig(
            base_url=self.addresses["rws_url"], password=ABB_DEFAULT_PASSWORD, timeout_s=30.0
        )
        async with RwsClient(config) as rws:
            await rws.motors_off()

    @property
    def q_deg(self) -> np.ndarray:
        """The joints the controller last reported over EGM (6,) deg."""
        return np.array(self.endpoint.latest.q_deg, dtype=np.float64)


@contextlib.asynccontextmanager
async def controller_process(
    endpoint: EgmEndpoint, port: int, q_start_deg: np.ndarray
) -> AsyncIterator[Controller]:
    """``python -m drivers.abb_egm.sim`` sending EGM to ``port``, its program running, its arm at
    ``q_start_deg``, with RWS and its fault channel on free ports; stopped by SIGTERM afterwards."""
    args = ["--egm-port", str(port), "--rws-port", "0", "--fault-port", "0", "--start", "--seed", "1",
            "--q-start-deg", *(repr(float(q)) for q in q_start_deg)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    with tempfile.TemporaryFile() as err:
        proc = await asyncio.to_thread(
            subprocess.Popen,
            [sys.executable, "-m", "drivers.abb_egm.sim", *args],
            cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
        )  # fmt: skip
        try:
            with contextlib.suppress(AttributeError, PermissionError, OSError):
                os.sched_setscheduler(proc.pid, os.SCHED_FIFO, os.sched_param(10))  # as realtime_priority
            line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 60.0)
            if not line:
                err.seek(0)
                raise RuntimeError(
                    f"controller simulator ended: {err.read()[-2000:].decode(errors='replace')}"
                )
            yield Controller(proc, json.loads(line), endpoint)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(asyncio.to_thread(proc.wait), 20.0)
            except TimeoutError:
                proc.kill()
                proc.wait()
            proc.stdout.close()


@contextlib.contextmanager
def realtime_priority(priority: int = 10):
    """Run the block under SCHED_FIFO when permitted, as a cell PC runs its EGM loop.

    The machine is shared with other jobs; without it, a descheduled executor makes the simulated
    arm drift on its last reference (which is what a real controller does when the sensor stalls).
    It mostly sleeps, so the priority costs the other jobs little. Restored afterwards; a no-op
    without the privilege. (The simulator's process gets the same where permitted.)
    """
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, PermissionError, OSError):
        yield False
        return
    try:
        yield True
    finally:
        os.sched_setscheduler(0, before[0], before[1])


def run_async(coro: Awaitable):
    """Run a coroutine on the simulator's precise event loop (microsecond timer wake-ups)."""
    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        return runner.run(coro)


@dataclass
class Execution:
    """What one execution over loopback produced."""

    result: ExecutionResult
    true_t_s: np.ndarray
    true_q_deg: np.ndarray
    feedback_t_s: np.ndarray

    def undisturbed(self, recovery_s: float = 0.6, gap_cycles: float = 3.0) -> np.ndarray:
        """(n,) bool over the true trajectory: False within ``recovery_s`` after a gap of more than
        ``gap_cycles`` EGM cycles in the feedback's arrival. Such a gap means the simulator or this
        process was not scheduled: the simulated arm then drifted on its last reference, which says
        nothing about the executor."""
        t = self.feedback_t_s
        gaps = np.flatnonzero(np.diff(t) > gap_cycles * 0.004032)
        ok = np.ones(self.true_t_s.shape, dtype=bool)
        for g in gaps:
            ok &= ~((self.true_t_s >= t[g]) & (self.true_t_s <= t[g + 1] + recovery_s))
        return ok


async def execute(
    plan: ScanPlan,
    settings: PlannerSettings,
    *,
    q_start_offset_deg: np.ndarray | None = None,
    config: ExecutorConfig | None = None,
    control: Callable[[MotionExecutor, Controller], Awaitable[None]] | None = None,
    timeout_s: float = 120.0,
) -> Execution:
    """Start an endpoint (ephemeral port) and the controller simulator's process sending to it,
    execute ``plan``, run ``control(executor, controller)`` alongside (pause, faults, ...), and return
    the result with the arm's true trajectory as the controller reported it over EGM."""
    endpoint = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0))
    _, port = await endpoint.start()
    q0 = plan.trajectory.q_deg[0] + (np.zeros(6) if q_start_offset_deg is None else q_start_offset_deg)
    try:
        async with controller_process(endpoint, port, q0) as controller:
            await endpoint.wait_for_feedback(30.0)
            await wait_until(lambda: endpoint.ok_to_command, 30.0, "the EGM session running")
            executor = MotionExecutor.for_plan(endpoint, plan, settings, config)
            side = asyncio.get_running_loop().create_task(control(executor, controller)) if control else None
            with realtime_priority():
                result = await asyncio.wait_for(executor.run(), timeout_s)
                if side is not None:
                    side.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await side
                # let the arm settle on the last reference: 0.3 s on the controller's clock (75 of
                # its feedback messages, which a starved simulator's slower cadence stretches); a
                # controller gone quiet (a stall under test) has nothing more to report
                n0 = endpoint.stats.received
                await wait_for_event(
                    lambda: endpoint.stats.received - n0 >= 75 or endpoint.quiet,
                    0.3,
                    "75 EGM feedback messages while the arm settles, or the controller quiet",
                )
            fb = endpoint.history.arrays()
    finally:
        await endpoint.close()
    t_s = fb.t_host_ns / 1e9
    return Execution(result, t_s, fb.q_deg[:, :6], t_s)


async def wait_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll until ``pred()`` holds (raises TimeoutError naming ``what``)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not pred():
        if loop.time() > end:
            raise TimeoutError(f"{what}: not within {timeout_s} s")
        await asyncio.sleep(0.01)


async def wait_for_state(executor: MotionExecutor, state: str, timeout_s: float = 30.0) -> None:
    """Poll until the executor reaches ``state`` (raises TimeoutError)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while executor.state.value != state:
        if loop.time() > end:
            raise TimeoutError(f"executor never reached {state!r} (is {executor.state.value!r})")
        await asyncio.sleep(0.01)


async def wait_for_segment(
    executor: MotionExecutor, label: str, fraction: float, timeout_s: float = 60.0
) -> None:
    """Poll until the executor is ``fraction`` of the way through the segment labelled ``label``."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    labels = executor.segment_labels
    k = labels.index(label)
    seg_mask = executor.trajectory.segment == k
    t0, t1 = executor.trajectory.t_s[seg_mask][[0, -1]]
    target = t0 + fraction * (t1 - t0)
    while executor.progress().t_traj_s < target:
        if loop.time() > end:
            raise TimeoutError(f"executor never reached {fraction:.0%} of {label!r}")
        await asyncio.sleep(0.005)
