"""Fixtures for the Zenoh tests: a loopback-only hub session, worker processes, free ports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import structlog

from cellctl.config import ZenohSection
from tests.support.ports import free_port

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent


@pytest.fixture(autouse=True)
def _plain_structlog() -> Iterator[None]:
    """Tests that run `cellctl.cli.main` in-process bind structlog to a captured stream that pytest
    closes afterwards; in-process dispatchers and queryables here must not log into it."""
    structlog.reset_defaults()
    yield
    structlog.reset_defaults()


@dataclass
class Hub:
    """One test cell: its [zenoh] section (the daemon's), key prefix and a cell.toml for workers."""

    section: ZenohSection
    prefix: str
    toml: Path
    tmp: Path


@pytest.fixture
def hub(tmp_path: Path) -> Hub:
    port = free_port()
    cell_id = "t" + uuid.uuid4().hex[:8]
    toml = tmp_path / "cell.toml"
    toml.write_text(
        f'[cell]\nid = "{cell_id}"\n\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        "multicast_scouting = false\n"
    )
    section = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    return Hub(section=section, prefix=f"cell/{cell_id}", toml=toml, tmp=tmp_path)


@dataclass
class WorkerProc:
    worker_id: str
    proc: subprocess.Popen
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


@pytest.fixture
def start_worker(hub: Hub) -> Iterator[Callable[..., WorkerProc]]:
    """Start `cellctl worker` processes for the hub; all are stopped (SIGTERM, then SIGKILL) after the test."""
    procs: list[WorkerProc] = []

    def start(worker_id: str, analysis: str = "zworker_fns:centroid_after_sleep", heartbeat_s: float = 0.3):
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
