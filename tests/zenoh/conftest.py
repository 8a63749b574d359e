"""Fixtures for the Zenoh tests: worker processes for a hub, and the loopback-only hub itself
(tests/support/hub.py, shared with tests/api)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.support.hub import Hub, _plain_structlog, hub  # noqa: F401 (the fixtures)

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent


@dataclass
class WorkerProc:
    worker_id: str
    proc: subprocess.Popen
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


@pytest.fixture
def start_worker(hub: Hub) -> Iterator[Callable[..., WorkerProc]]:  # noqa: F811 (the fixture hub)
    """Start `cellctl worker` processes for the hub; all are stopped (SIGTERM, then SIGKILL) after the test."""
    procs: list[WorkerProc] = []

    def start(
        worker_id: str,
        analysis: str = "tests.support.zworker_fns:centroid_after_sleep",
        heartbeat_s: float = 0.3,
    ):
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(HERE), env.get("PYTHONPATH", "")])
        log_path = hub.tmp / f"{worker_id}.log"
        cmd = [sys.executable, "-m", "cellctl", "--log-format", "json", "worker", "--config", str(hub.toml)]
        cmd += ["--worker-id", worker_id, "--analysis", analysis, "--heartbeat-s", str(heartbeat_s)]
        with log_path.open("wb") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=hub.tmp)
        wp = WorkerProc(worker_id, proc, log_path)
        procs.append(wp)
        return wp

    try:
        yield start
    finally:
        for wp in procs:
            if wp.proc.poll() is None:
                wp.proc.send_signal(signal.SIGTERM)
        for wp in procs:
            try:
                wp.proc.wait(15)
            except subprocess.TimeoutExpired:
                wp.proc.kill()
                wp.proc.wait(5)
