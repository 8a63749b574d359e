"""``python -m drivers.laser.sim``: a stand-alone simulator that prints its ports and stops on a signal."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from laser_helpers import collect, run

from drivers.laser.client import HD8Client
from drivers.laser.source import ProfileBatch

pytestmark = pytest.mark.process  # the simulator as `python -m drivers.laser.sim`

REPO = Path(__file__).resolve().parents[2]


def test_sim_module_serves_a_step_and_exits_cleanly_on_sigterm() -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.laser.sim", "--scene", "step", "--step-mm", "5", "--rate", "400"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )
    try:
        line = ""
        assert proc.stdout is not None
        while not line.startswith("{"):
            line = proc.stdout.readline()
            assert line, f"simulator exited early: {proc.stderr.read() if proc.stderr else ''}"
        ports = json.loads(line)

        async def scenario() -> ProfileBatch:
            client = HD8Client(ports["host"], ports["control_port"], ports["data_port"])
            try:
                await client.connect()
                await client.start()
                return ProfileBatch.concat(await collect(client, 40))
            finally:
                await client.close()

        b = run(scenario())
        z = b.z_mm[b.valid]
        # step 5 mm high at x = 0 under a sensor 100 mm up: two depth levels
        assert np.isclose(z, 100.0, atol=0.15).mean() > 0.4 and np.isclose(z, 95.0, atol=0.15).mean() > 0.4
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
