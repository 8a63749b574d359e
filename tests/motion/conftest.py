"""Shared plans and the loopback harness (EGM endpoint + controller simulator) for the motion tests."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np
import pytest

from analysis.placement import Placement
from analysis.plates import design_mesh, plate_spec
from cellctl.motion import ExecutionResult, ExecutorConfig, MotionExecutor
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig
from drivers.runtime import precise_event_loop

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


@contextlib.contextmanager
def realtime_priority(priority: int = 10):
    """Run the block under SCHED_FIFO when permitted, as a cell PC runs its EGM loop.

    The executor and the simulator share this process and the machine is shared with other jobs;
    without it, a descheduled process makes the simulated arm drift on its last reference (which is
    what a real controller does when the sensor stalls). Both mostly sleep, so the priority costs
    the other jobs little. Restored afterwards; a no-op without the privilege.
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
    sim: EgmControllerSim
    true_t_s: np.ndarray
    true_q_deg: np.ndarray
    feedback_t_s: np.ndarray

    def undisturbed(self, recovery_s: float = 0.6, gap_cycles: float = 3.0) -> np.ndarray:
        """(n,) bool over the true trajectory: False within ``recovery_s`` after a gap of more than
        ``gap_cycles`` EGM cycles in the feedback's arrival. Such a gap means this process (which
        runs both the simulator and the executor) was not scheduled: the simulated arm then drifted
        on its last reference, which says nothing about the executor."""
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
    control: Callable[[MotionExecutor, EgmControllerSim], Awaitable[None]] | None = None,
    timeout_s: float = 120.0,
) -> Execution:
    """Start an endpoint (ephemeral port) and the controller simulator sending to it, execute
    ``plan``, run ``control(executor, sim)`` alongside (pause, faults, ...), and return the result
    with the simulator's true trajectory."""
    endpoint = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0))
    _, port = await endpoint.start()
    q0 = plan.trajectory.q_deg[0] + (np.zeros(6) if q_start_offset_deg is None else q_start_offset_deg)
    sim = EgmControllerSim(
        EgmSimConfig(sensor_host="127.0.0.1", sensor_port=port, q_start_deg=tuple(q0), seed=1)
    )
    await sim.start()
    try:
        executor = MotionExecutor.for_plan(endpoint, plan, settings, config)
        side = asyncio.get_running_loop().create_task(control(executor, sim)) if control else None
        with realtime_priority():
            result = await asyncio.wait_for(executor.run(), timeout_s)
            if side is not None:
                side.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await side
            await asyncio.sleep(0.3)  # let the arm settle on the last reference
    finally:
        await sim.stop()
        await endpoint.close()
    t, q = sim.trajectory.arrays()
    feedback_t_s = endpoint.history.arrays().t_host_ns / 1e9
    return Execution(result, sim, t, q, feedback_t_s)


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
