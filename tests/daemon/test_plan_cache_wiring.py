"""The daemon's planning step reuses a plan from ``<data_dir>/plan-cache`` (in process, no cell)."""

from __future__ import annotations

import asyncio
from typing import Any

from analysis.placement import Placement
from analysis.plates import design_mesh, plate_spec
from cellctl.api import JobState
from cellctl.config import CellConfig
from cellctl.daemon.jobs import ActiveJob, JobRecord, JobStore
from cellctl.daemon.scan import ScanRunner


class _Host:
    """Records the job states the runner reports."""

    def __init__(self) -> None:
        self.states: list[tuple[JobState, str, dict[str, Any]]] = []

    def job_state(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None:
        self.states.append((state, message, info))


def test_the_second_scan_of_the_same_plate_and_placement_reuses_the_stored_plan(tmp_path):
    cfg = CellConfig()
    store = JobStore(tmp_path / "data")
    host = _Host()
    runner = ScanRunner(cfg, store, drivers=None, host=host)  # planning needs no drivers
    design = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    placement = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0).model_dump()

    def plan_once(job_id: str):
        job = ActiveJob(JobRecord(job_id, "p", "d.ply", str(tmp_path / "d.ply"), placement))
        return asyncio.run(runner._plan(job, design))

    first = plan_once("j1")
    second = plan_once("j2")
    assert first is not None and second is not None
    planned = [info for state, msg, info in host.states if msg == "planned"]
    assert [i["plan_cache"] for i in planned] == ["miss", "hit"]
    assert planned[0]["plan"] == planned[1]["plan"]
    assert len(list((tmp_path / "data" / "plan-cache").glob("*.json"))) == 1
    assert planned[1]["plan"]["transitions_s"] > 0
