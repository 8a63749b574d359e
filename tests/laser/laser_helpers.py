"""Helpers for the HD8 driver tests: run a coroutine with a deadline, start a simulator on loopback,
set its faults and read its counters over its fault channel (a socket, as its data and commands)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterable, AsyncIterator, Coroutine
from typing import Any

import numpy as np

from drivers.laser.client import HD8Client, HD8ClientConfig
from drivers.laser.sim.scene import Scene, plane_scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig, fixed_pose
from drivers.sim.fault_channel import send_fault_request


def looking_down(standoff_mm: float, x_mm: float = 0.0, y_mm: float = 0.0) -> np.ndarray:
    """T_world_sensor of a sensor ``standoff_mm`` above (x, y, 0), laser axis down, sensor x = world x."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [x_mm, y_mm, standoff_mm]
    return T


def run(coro: Coroutine[Any, Any, Any], timeout_s: float = 20.0) -> Any:
    """Run ``coro`` in a fresh event loop; fail the test instead of hanging."""

    async def guarded() -> Any:
        return await asyncio.wait_for(coro, timeout_s)

    return asyncio.run(guarded())


@contextlib.asynccontextmanager
async def sim_and_client(
    scene: Scene | None = None,
    T_world_sensor: np.ndarray | None = None,
    *,
    config: SimConfig | None = None,
    client_config: HD8ClientConfig | None = None,
) -> AsyncIterator[tuple[LaserSimulator, HD8Client]]:
    """A simulator on ephemeral loopback ports (control, data, fault channel) and a connected client;
    both closed afterwards."""
    sim = LaserSimulator(
        scene if scene is not None else plane_scene(0.0),
        fixed_pose(T_world_sensor if T_world_sensor is not None else looking_down(100.0)),
        config=config or SimConfig(),
        fault_port=0,
    )
    ctl, dat = await sim.start()
    client = HD8Client("127.0.0.1", ctl, dat, config=client_config)
    try:
        await client.connect()
        yield sim, client
    finally:
        await client.close()
        await sim.stop()


async def collect(client: AsyncIterable[Any], n_frames: int, timeout_s: float | None = None) -> list[Any]:
    """Read batches (of any ProfileSource) until at least ``n_frames`` profiles arrived, failing past
    ``timeout_s`` (None: no bound of its own)."""
    out = []
    got = 0
    async with asyncio.timeout(timeout_s):
        async for b in client:
            out.append(b)
            got += len(b)
            if got >= n_frames:
                break
    return out


async def sensor_faults(sim: LaserSimulator, **laser: Any) -> dict[str, Any]:
    """Set fault knobs over the simulator's fault channel (``sensor_faults(sim, drop_frames=7)``;
    none: only read); returns its reply: the knobs in force and its counters (``["stats"]``)."""
    assert sim.fault_address is not None, "start the simulator with fault_port=0"
    reply = await send_fault_request(sim.fault_address, {"laser": laser})
    assert reply["ok"], reply
    return reply


async def sensor_stats(sim: LaserSimulator) -> dict[str, Any]:
    """The simulator's counters, read over its fault channel."""
    return (await sensor_faults(sim))["stats"]
