"""The daemon's planning step starts the serpentine at the plate's corner nearest the arm, which it
asks the controller for over RWS (the RWS simulator on loopback; no cell)."""

from __future__ import annotations

import asyncio
import types
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.plates import design_mesh, plate_spec
from cellctl.api import JobState
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.scan import ScanRunner
from cellctl.jobstore.jobs import JobRecord, JobStore
from cellctl.planning import PlannerSettings
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer

PLACEMENT = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0)
DESIGN = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)


class _Host:
    def __init__(self) -> None:
        self.states: list[tuple[JobState, str, dict[str, Any]]] = []

    def job_state(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None:
        self.states.append((state, message, info))


def _plate_xy(p_world: np.ndarray) -> np.ndarray:
    T = placement_transform(PLACEMENT)
    return (T[:3, :3].T @ (p_world - T[:3, 3]))[:2]


def _plan_with_arm_at(tmp_path, q_deg: np.ndarray | None):
    """The runner's plan with the simulated controller's arm at ``q_deg`` (None: the controller
    stopped, RWS does not answer): the planned state's info, the plan and the log lines."""
    cfg = CellConfig()
    host = _Host()

    async def body():
        model = ControllerModel()
        model.set_position_source(lambda: (q_deg, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])))
        server = RwsServer(model, profile="rws1", host="127.0.0.1", port=0)  # type: ignore[arg-type]
        await server.start()
        client = RwsClient(
            RwsClientConfig(base_url=server.base_url, profile="rws1", password="robotics", timeout_s=2.0)  # type: ignore[arg-type]
        )
        try:
            if q_deg is None:
                await server.stop()
            runner = ScanRunner(
                cfg, JobStore(tmp_path / "data"), drivers=types.SimpleNamespace(rws=client), host=host
            )
            job = ActiveJob(JobRecord("j1", "p", "d.ply", str(tmp_path / "d.ply"), PLACEMENT.model_dump()))
            return await runner._plan(job, DESIGN)
        finally:
            await client.close()
            if q_deg is not None:
                await server.stop()

    with capture_logs() as logs:
        planned = asyncio.run(asyncio.wait_for(body(), 120))
    assert planned is not None
    info = next(i for _, msg, i in host.states if msg == "planned")
    return info, planned[0], logs


@pytest.mark.parametrize("q1_deg", [0.0, 25.0])
def test_the_serpentine_starts_at_the_corner_nearest_the_arm(tmp_path, q1_deg):
    q = np.array([q1_deg, 0.0, 0.0, 0.0, 30.0, 0.0])
    settings = PlannerSettings.from_config(CellConfig())
    arm_xy = _plate_xy(fk_batch(q[None], settings.T_flange_sensor)[0, :3, 3])
    info, plan, _ = _plan_with_arm_at(tmp_path, q)
    want = [1 if arm_xy[0] > 0 else -1, 1 if arm_xy[1] > 0 else -1]
    assert want == ([1, -1] if q1_deg == 0.0 else [-1, 1])  # the arm over opposite corners of the plate
    assert info["plan"]["choices"]["start_corner"] == want
    start_xy = _plate_xy(plan.segments[0].pos_mm[0])  # the approach, above the first pass's start
    assert np.sign(start_xy).tolist() == want
    # no other corner is nearer the arm than the one the plan starts from
    corners = [np.array([sx, sy]) * np.abs(start_xy) for sx in (-1, 1) for sy in (-1, 1)]
    assert np.linalg.norm(start_xy - arm_xy) <= min(np.linalg.norm(c - arm_xy) for c in corners) + 1e-6


def test_a_controller_that_does_not_say_where_the_arm_is_leaves_the_default_corner(tmp_path):
    info, plan, logs = _plan_with_arm_at(tmp_path, None)
    assert "start_corner" not in info["plan"]["choices"]
    assert [e for e in logs if e["event"] == "start_corner_unknown"]
    # the default: the first pass starts on the footprint's low side in x and y
    assert (_plate_xy(plan.segments[0].pos_mm[0]) < 0).all()
