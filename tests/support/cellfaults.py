"""Helpers of the Zenoh / worker / daemon / disk fault cases and the soak (benchmarks/soak.py).

The simulated cell runs as real processes (tests/support/e2e_cell.py); faults are made the way they
happen: a TCP link cut (tcp_forwarder.py), ``kill -9`` of processes, a full or read-only mount.
Everything here judges from the outside: the Zenoh API, the job records and the raw files.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cellctl.commands.demo_cmd import to_toml
from cellctl.config import load_config
from cellctl.jobstore.rawstore import RawReader
from tests.support.e2e_cell import Cell, wait_status
from tests.support.faultcell import (
    FINAL_JOB_STATES,
    PARTIAL_CLOUD_REFUSED,
    SENSOR_STARVED_SHARE,
    FaultCell,
    fault_cell_config,
    sensor_starved,
)

__all__ = [
    "FINAL",
    "PARTIAL_CLOUD_REFUSED",
    "Cell",
    "FaultCell",
    "RawCheck",
    "SensorCounters",
    "children_of",
    "expect_analysed",
    "fault_cell_config",
    "kill9_tree",
    "raw_check",
    "rws_client",
    "sensor_overruns",
    "stop_cell",
    "wait_status",
    "worker_config_via",
]

FINAL = FINAL_JOB_STATES


@dataclass(frozen=True)
class SensorCounters:
    """The simulated HD8's frames since it started (these cases' cells run one job): how many it
    acquired and how many it could not render in time."""

    overrun_frames: int
    frames_acquired: int

    @property
    def starved(self) -> bool:
        """More than SENSOR_STARVED_SHARE of the frames overran: the machine starved the simulator."""
        return sensor_starved(self.overrun_frames, self.frames_acquired)

    def __str__(self) -> str:
        return f"sensor overruns {self.overrun_frames} of {self.frames_acquired} frames"


async def sensor_overruns(cell: FaultCell) -> SensorCounters:
    """The simulated HD8's frame counters (:class:`SensorCounters`)."""
    laser = (await cell.fault()).stats["laser"]
    return SensorCounters(int(laser["overrun_frames"]), int(laser["frames_acquired"]))


def expect_analysed(state: str, message: str, sensor: SensorCounters) -> None:
    """The worker's report of a whole scan reached the daemon and the job is ``done``. The one
    fallback: when the machine starved the simulated sensor (more than SENSOR_STARVED_SHARE of its
    frames overran), the analysis may refuse the holed cloud as covering only part of the plate
    (:data:`PARTIAL_CLOUD_REFUSED`, that refusal only); the report still came back once, which is
    what the Zenoh and worker cases are about, and the case is skipped as a fallback (counted by
    .ci/run). Call it last, after the case's other checks."""
    if state == "done":
        return
    if sensor.starved and state == "failed" and message.startswith(PARTIAL_CLOUD_REFUSED):
        pytest.skip(f"fallback: simulators starved ({sensor}): job failed: {message}")
    raise AssertionError(
        f"job {state}: {message} ({sensor}; starved above {SENSOR_STARVED_SHARE:.0%}: {sensor.starved})"
    )


def stop_cell(cell: Cell, grace_s: float = 180.0) -> dict[str, Any]:
    """Stop the cell's processes (SIGTERM; SIGKILL after ``grace_s``); returns their exit codes.

    The daemon finishes a report render in progress before it exits (by design): tens of seconds on
    a loaded machine, more than the e2e helper's 30 s grace.
    """
    codes = cell.procs.stop_all(grace_s=grace_s)
    codes.update(cell.stop())
    return codes


def rws_client(cell: Cell) -> Any:
    """An RWS client to the simulated controller (close it with ``await c.close()``)."""
    from cellctl.daemon.wiring import rws_client_config
    from drivers.abb_egm.rws_client import RwsClient

    return RwsClient(rws_client_config(cell.cfg.robot, cell.procs.env["CELL_RWS_PASSWORD"], timeout_s=10.0))


def worker_config_via(cell: Cell, endpoint: str, name: str = "worker-via.toml") -> Path:
    """A copy of the cell's configuration whose Zenoh clients connect to ``endpoint`` (a forwarder)."""
    data = load_config(cell.config_path).model_dump(mode="json")
    data["zenoh"]["connect"] = [endpoint]
    path = cell.out / name
    path.write_text(to_toml(data), encoding="utf-8")
    load_config(path)  # the copy must validate as the original does
    return path


def children_of(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux /proc)."""
    out: list[int] = []
    with contextlib.suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError):
                out += [int(c) for c in Path(f"/proc/{pid}/task/{task}/children").read_text().split()]
    return out


def kill9_tree(pid: int) -> list[int]:
    """``kill -9`` a process and its descendants (children first listed, all killed at once).

    Returns every pid signalled.
    """
    pids, todo = [], [pid]
    while todo:
        p = todo.pop()
        pids.append(p)
        todo += children_of(p)
    for p in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGKILL)
    return pids


def pid_alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


class RawCheck:
    """What a job's raw files hold: ``profiles`` in the intact records, the reader's ``problems``,
    ``torn_bytes`` dropped at each stream's end, and the profile ``frames`` (sensor frame indices)."""

    def __init__(self, raw_dir: Path) -> None:
        reader = RawReader(raw_dir)
        recs = reader.records()
        import numpy as np

        frames = [r.arrays["frame_index"] for r in recs if r.stream == "profiles"]
        self.frames = np.concatenate(frames) if frames else np.zeros(0, dtype=np.uint64)
        self.profiles = int(self.frames.size)
        self.problems = list(reader.report.problems)
        self.torn_bytes = dict(reader.report.torn_bytes)
        self.records_used = reader.report.records_used

    @property
    def unique_frames(self) -> bool:
        """No profile stored twice."""
        import numpy as np

        return int(np.unique(self.frames).size) == self.profiles


def raw_check(cell: Cell, job_id: str) -> RawCheck:
    """Read the job's raw files the way re-analysis does (never raises on a torn tail)."""
    return RawCheck(cell.jobs_dir / job_id / "raw")


def job_history(cell: Cell, job_id: str) -> list[str]:
    """The job's state history, oldest first."""
    return [h["state"] for h in cell.job_record(job_id)["history"]]


async def wait_until(pred, timeout_s: float, period_s: float = 0.2, what: str = "condition") -> Any:
    """Poll ``pred()`` until truthy (returns its value) or raise TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} not met within {timeout_s} s")
        await asyncio.sleep(period_s)
