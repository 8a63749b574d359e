"""The daemon's planning step reuses a plan from ``<data_dir>/plan-cache`` (in process, no cell; the
arm's position, which picks the start corner, from the RWS simulator on loopback). A fresh plan is
written by the call the step returns, which the runner makes once the arm is at rest."""

from __future__ import annotations

import asyncio
import types
from typing import Any

import numpy as np

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.api import JobState
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.scan import ScanRunner
from cellctl.jobstore.jobs import JobRecord, JobStore
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer


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
    design = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    placement = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0).model_dump()

    async def plan_twice():
        model = ControllerModel()  # the arm at the simulator's home
        model.set_position_source(
            lambda: (np.array([0, 0, 0, 0, 30.0, 0]), np.zeros(3), np.array([1.0, 0, 0, 0]))
        )
        server = RwsServer(model, profile="rws1", host="127.0.0.1", port=0)  # type: ignore[arg-type]
        await server.start()
        client = RwsClient(RwsClientConfig(base_url=server.base_url, profile="rws1", password="robotics"))  # type: ignore[arg-type]
        runner = ScanRunner(
            cfg, store, drivers=types.SimpleNamespace(rws=client), host=host
        )  # planning: RWS only
        try:
            out = []
            for j in ("j1", "j2"):
                got = await runner._plan(
                    ActiveJob(JobRecord(j, "p", "d.ply", str(tmp_path / "d.ply"), placement)), design
                )
                # the fresh plan is not written between the plan and the motion: the runner writes
                # it with the call it returns once the arm is at rest (a hit returns none)
                cached = list((tmp_path / "data" / "plan-cache").glob("*.npz"))
                out.append((got, len(cached)))
                if got is not None and got[2] is not None:
                    await asyncio.to_thread(got[2])
            return out
        finally:
            await client.close()
            await server.stop()

    (first, cached_after_first), (second, cached_after_second) = asyncio.run(plan_twice())
    assert first is not None and second is not None
    assert cached_after_first == 0 and first[2] is not None  # written later, by the returned call
    assert cached_after_second == 1 and second[2] is None  # a hit: nothing more to write
    planned = [info for state, msg, info in host.states if msg == "planned"]
    assert [i["plan_cache"] for i in planned] == ["miss", "hit"]
    assert planned[0]["plan"] == planned[1]["plan"]
    assert len(list((tmp_path / "data" / "plan-cache").glob("*.npz"))) == 1
    assert planned[1]["plan"]["transitions_s"] > 0
