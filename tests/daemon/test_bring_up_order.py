"""The scan's bring-up around its plan (cellctl/daemon/scan.py): the sensor comes up while the scan is
planned, the EGM program only once it is planned (in process, no cell: the drivers are recorders).

From the program's start the controller wants an answer every EGM cycle and ends the session after
its communication timeout (1 s); the planner's thread holds the interpreter for seconds on a 6 m
plate, so a session opened during the plan faulted the long cell's scan ("no commandable feedback").
"""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.api import JobState
from cellctl.config import CellConfig, LocateSection
from cellctl.daemon import scan as scan_module
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.scan import ScanRunner
from cellctl.jobstore.jobs import JobRecord, JobStore


class _Recorder:
    """What happened, in order: ``(event, plan_running)``."""

    def __init__(self) -> None:
        self.events: list[tuple[str, bool]] = []
        self.planning = False

    def mark(self, event: str) -> None:
        self.events.append((event, self.planning))


class _Host:
    def __init__(self) -> None:
        self.states: list[tuple[JobState, str]] = []

    def to_cell(self, *_: Any, **__: Any) -> None:
        pass

    def job_state(self, job: ActiveJob, state: JobState, message: str = "", **_: Any) -> None:
        self.states.append((state, message))

    def stop_requested(self, job: ActiveJob) -> bool:
        return False


class _Program:
    def __init__(self, rec: _Recorder) -> None:
        self.rec = rec

    async def start(self) -> None:
        self.rec.mark("program.start")

    async def end(self) -> None:
        self.rec.mark("program.end")


class _Motion:
    """The motion process's link as the scan sees it: alive, and feedback once the program runs."""

    alive = True
    death = None

    def __init__(self, rec: _Recorder) -> None:
        self.rec = rec

    async def wait_for_feedback(self, timeout_s: float) -> None:
        self.rec.mark("feedback")


class _Client:
    def __init__(self, rec: _Recorder) -> None:
        self.rec = rec

    async def close(self) -> None:
        self.rec.mark("sensor.close")


def _run(tmp_path, monkeypatch, *, plan_refused: bool) -> tuple[_Recorder, _Host]:
    rec = _Recorder()
    host = _Host()
    cfg = CellConfig(locate=LocateSection(check_given=False))
    drivers = SimpleNamespace(program=_Program(rec), motion=_Motion(rec))
    runner = ScanRunner(cfg, JobStore(tmp_path / "data"), drivers=drivers, host=host)
    design = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    monkeypatch.setattr(scan_module, "design_mesh_from_file", lambda path: design)
    sensor_up = asyncio.Event()

    async def sensor_ready() -> _Client:
        rec.mark("sensor.ready")
        sensor_up.set()
        return _Client(rec)

    async def plan(job: ActiveJob, design: Any) -> Any:
        rec.planning = True
        try:
            # the plan is long: the sensor comes up meanwhile, and the loop stays free for the bring-up
            await asyncio.wait_for(sensor_up.wait(), 10.0)
            for _ in range(20):
                await asyncio.sleep(0)
        finally:
            rec.planning = False
        rec.mark("planned")
        return None if plan_refused else (SimpleNamespace(scan_time_s=1.0), None, None)

    async def preflight(job: ActiveJob, plan: Any) -> bool:
        # the bring-up goes on beside the pre-flight: let it finish, then stop before any motion
        for _ in range(50):
            await asyncio.sleep(0)
        rec.mark("preflight")
        return False

    monkeypatch.setattr(runner, "_sensor_ready", sensor_ready)
    monkeypatch.setattr(runner, "_plan", plan)
    monkeypatch.setattr(runner, "_preflight", preflight)
    placement = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0).model_dump()
    job = ActiveJob(JobRecord("j1", "p", "d.ply", str(tmp_path / "d.ply"), placement))
    assert asyncio.run(runner.scan(job)) is False
    return rec, host


def test_the_sensor_comes_up_during_the_plan_and_the_egm_program_only_after_it(tmp_path, monkeypatch):
    rec, _ = _run(tmp_path, monkeypatch, plan_refused=False)
    names = [e for e, _ in rec.events]
    assert ("sensor.ready", True) in rec.events, rec.events  # overlapped with the plan
    assert not [e for e, planning in rec.events if e.startswith("program") and planning], rec.events
    assert names.index("planned") < names.index("program.start") < names.index("feedback")
    # the pre-flight stopped the job: what the bring-up started is ended again
    assert names[-2:] == ["program.end", "sensor.close"], names


def test_a_refused_plan_never_starts_the_egm_program(tmp_path, monkeypatch):
    rec, _ = _run(tmp_path, monkeypatch, plan_refused=True)
    names = [e for e, _ in rec.events]
    assert "program.start" not in names, names
    assert names[-1] == "sensor.close", names
