"""The sensor simulator as a GigE Vision profiler (drivers.laser.sim.gige_device), read by the GigE
Vision source through Aravis on 127.0.0.1: the same profiles and the same sensor clock as its HD8 side."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.laser.gige import GigeProfileSource, GigeSourceConfig
from drivers.laser.sim.gige_device import GigeSimDevice
from drivers.laser.sim.scene import step_scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig, fixed_pose
from tests.laser.laser_helpers import collect, looking_down, run, sim_and_client

pytestmark = [pytest.mark.process, pytest.mark.slow]  # UDP 3956 is one per address: one at a time

#: no noise or outliers: the two transports must then carry the very same profiles
QUIET = SimConfig(rate_hz=1000.0, noise_sigma_mm=0.0, outlier_probability=0.0, clock_offset_us=5_000_000,
                  clock_drift_ppm=80.0)  # fmt: skip
SCENE = step_scene(step_x_mm=5.0, low_z_mm=0.0, high_z_mm=12.0)
POSE = looking_down(100.0)


async def _read_gige(n: int, *, lost: float = 0.0, rows: int = 20) -> tuple[list, GigeProfileSource, tuple]:
    sim = LaserSimulator(SCENE, fixed_pose(POSE), config=QUIET)
    with GigeSimDevice(sim, lost_packet_ratio=lost) as dev:
        src = GigeProfileSource("127.0.0.1", config=GigeSourceConfig(rows_per_buffer=rows, width=QUIET.width))
        await src.connect()
        await src.configure(rate_hz=QUIET.rate_hz, exposure_ns=QUIET.exposure_ns)
        t0 = time.monotonic()
        await src.start()
        out, got = [], 0
        async with asyncio.timeout(20):
            async for b in src:
                out.append(b)
                got += len(b)
                if got >= n:
                    break
        t1 = time.monotonic()
        await src.close()
        window = (float(sim.sensor_time_us(t0 - 1.0)), float(sim.sensor_time_us(t1)))
        assert dev.fill_errors == 0
    return out, src, window


def test_the_gige_device_carries_the_same_profiles_as_the_hd8_side_of_the_simulator():
    async def hd8():
        async with sim_and_client(SCENE, POSE, config=QUIET) as (_sim, client):
            await client.configure(rate_hz=QUIET.rate_hz)
            await client.start()
            return await collect(client, 50)

    hd8_batches = run(hd8())
    gige_batches, src, _ = run(_read_gige(200), timeout_s=40)
    h, g = hd8_batches[0], gige_batches[0]
    np.testing.assert_allclose(g.x_mm[0], h.x_mm[0], atol=1e-4)  # one point grid
    assert (g.valid[0] == h.valid[0]).all()
    # both quantise z to 2 um; a static scene without noise: equal to the quantum
    np.testing.assert_allclose(g.z_mm[0][g.valid[0]], h.z_mm[0][h.valid[0]], atol=0.0021)
    assert np.nanmin(g.z_mm) == pytest.approx(100.0 - 12.0, abs=0.01)
    assert np.nanmax(g.z_mm) == pytest.approx(100.0, abs=0.01)
    assert src.info is not None and src.info.serial == "SIMGIGE"


def test_profiles_are_stamped_with_the_simulated_sensor_clock_one_line_period_apart():
    batches, src, (lo_us, hi_us) = run(_read_gige(400), timeout_s=40)
    t = np.concatenate([b.sensor_time_us for b in batches]).astype(np.int64)
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    # a frame period the fake device's thread let pass is a whole block missing, as a profiler's lost
    # lines would be (a loaded machine): never a repeat, never out of order
    assert (np.diff(fi) > 0).all() and src.stats.torn_buffers == 0
    assert src.stats.missing_frames % 20 == 0
    assert lo_us <= t[0] and t[-1] <= hi_us  # the sensor's clock (5 s offset, 80 ppm), not the host's
    within = np.diff(batches[0].sensor_time_us.astype(np.int64))
    assert np.all(np.abs(within - 1000) <= 1)  # 1 kHz rows
    assert (np.diff(t) > 0).all()  # in order across buffers too
    # the stamps follow the frame index: one line period per index, gaps included (the device stamps
    # each block; its rows at the nominal period, so 80 ppm of drift shows as ~2 us at a block's end)
    np.testing.assert_allclose(np.diff(t) / np.diff(fi), 1000.0, atol=2.5)


def test_packet_loss_on_the_simulated_device_tears_buffers_that_are_never_delivered():
    batches, src, _ = run(_read_gige(1500, lost=0.02, rows=20), timeout_s=40)
    st = src.stats
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    assert (np.diff(fi) > 0).all()
    assert st.torn_buffers > 0 and st.frames + st.missing_frames == st.last_frame_index + 1
    for b in batches:
        assert np.nanmax(b.z_mm) == pytest.approx(100.0, abs=0.01)  # intact rows only


def test_sim_module_serves_gige_vision_and_exits_cleanly_on_sigterm():
    """``python -m drivers.laser.sim --protocol gige``: a step 5 mm high, read through Aravis."""
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.laser.sim", "--protocol", "gige", "--serial", "WT49CLI",
         "--scene", "step", "--step-mm", "5", "--rate", "500"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=repo,
        env={**os.environ, "PYTHONPATH": str(repo)},
    )  # fmt: skip

    async def read() -> list:
        src = GigeProfileSource("127.0.0.1", config=GigeSourceConfig(rows_per_buffer=10, width=500))
        await src.connect()
        assert src.info is not None and src.info.serial == "WT49CLI"
        await src.configure(rate_hz=500.0)
        await src.start()
        out = await collect(src, 100)
        await src.close()
        return out

    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("{"), f"simulator exited early: {proc.stderr.read() if proc.stderr else ''}"
        assert json.loads(line) == {"protocol": "gige", "host": "127.0.0.1", "serial": "WT49CLI"}
        batches = run(read())
        z = np.concatenate([b.z_mm for b in batches])
        # the step, seen from 100 mm (percentiles: the simulator's rare outliers stay out)
        assert np.nanpercentile(z, 90) - np.nanpercentile(z, 10) == pytest.approx(5.0, abs=0.1)
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
