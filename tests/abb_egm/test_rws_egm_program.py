"""The CellEgm program driven through RWS against the simulated controller (both profiles)."""

from __future__ import annotations

import asyncio

import pytest

from drivers.abb_egm.cell_egm import CellEgmProgram, EgmProgramError, EgmProgramSettings
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig, RwsError
from drivers.abb_egm.sim.model import EVENT_EGM_COMM_TIMEOUT, ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer

PROFILES = ["rws1", "rws2"]


async def _with_program(profile: str, model: ControllerModel, fn, settings: EgmProgramSettings | None = None):
    server = RwsServer(model, profile=profile)  # type: ignore[arg-type]
    await server.start()
    client = RwsClient(RwsClientConfig(base_url=server.base_url, profile=profile))  # type: ignore[arg-type]
    try:
        return await fn(CellEgmProgram(client, settings), server)
    finally:
        await client.close()
        await server.stop()


def run(coro) -> None:
    asyncio.run(asyncio.wait_for(coro, 30))


@pytest.mark.parametrize("profile", PROFILES)
def test_start_brings_the_program_into_egm_with_the_settings_and_end_stops_it_cleanly(profile: str) -> None:
    model = ControllerModel()
    settings = EgmProgramSettings(comm_timeout_s=0.5, pos_corr_gain=0.8, max_speed_deviation_deg_s=300)

    async def body(prog: CellEgmProgram, server: RwsServer) -> None:
        await prog.start()
        assert model.egm_wanted and model.ctrl_state == "motoron"
        p = model.egm_params
        assert p is not None
        assert (p.comm_timeout_s, p.pos_corr_gain, p.max_speed_deviation_deg_s) == (0.5, 0.8, 300.0)
        assert await prog.status() == 1
        assert await prog.end() == 2
        assert model.rapid_state == "stopped" and not model.egm_wanted
        assert server.stats["sessions_created"] == 1

    run(_with_program(profile, model, body, settings))


def test_start_restarts_a_program_left_running_from_main() -> None:
    model = ControllerModel()
    model.motors_on()
    model.start_rapid()
    model.stop_rapid()
    model.start_rapid()  # running, inside an old session

    async def body(prog: CellEgmProgram, server: RwsServer) -> None:
        old_params = model.egm_params
        await prog.start()
        assert model.egm_wanted and model.egm_params is not old_params  # a fresh session from main

    run(_with_program("rws1", model, body))


def test_start_refuses_manual_mode_without_touching_the_controller() -> None:
    model = ControllerModel(opmode="MANR")

    async def body(prog: CellEgmProgram, server: RwsServer) -> None:
        with pytest.raises(EgmProgramError, match="MANR"):
            await prog.start()
        assert model.ctrl_state == "motoroff" and model.rapid_state == "stopped"

    run(_with_program("rws1", model, body))


def test_start_during_emergency_stop_reports_the_controller_refusal() -> None:
    model = ControllerModel()
    model.emergency_stop()

    async def body(prog: CellEgmProgram, server: RwsServer) -> None:
        with pytest.raises(RwsError, match="emergencystop") as err:
            await prog.start()
        assert err.value.status == 400

    run(_with_program("rws1", model, body))


def test_status_reports_a_communication_timeout_after_the_session_ended() -> None:
    model = ControllerModel()

    async def body(prog: CellEgmProgram, server: RwsServer) -> None:
        await prog.start()
        model.egm_session_ended("no EgmSensor for 0.5 s", EVENT_EGM_COMM_TIMEOUT)
        assert await prog.status() == -41822
        events = await prog.rws.read_event_log()
        assert events[0].code == 41822
        assert await prog.end() == -41822  # already stopped: end() returns at once with the status

    run(_with_program("rws2", model, body))


@pytest.mark.parametrize("kwargs", [{"comm_timeout_s": 0}, {"pos_corr_gain": 1.5}, {"sample_rate_ms": 6}])
def test_settings_outside_the_rapid_ranges_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        EgmProgramSettings(**kwargs)
