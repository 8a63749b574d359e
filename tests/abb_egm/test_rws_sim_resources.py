"""The simulator's RWS resources beyond the daemon's own calls: tasks, speed ratio, modules, mastership,
documented start parameters, task names, over loopback with the RWS client and raw requests."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest

from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig, RwsError, TaskState
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer

T = "T_ROB1"


@asynccontextmanager
async def sim(profile: str) -> AsyncIterator[tuple[ControllerModel, RwsServer, RwsClient]]:
    model = ControllerModel()
    server = RwsServer(model, profile=profile)  # type: ignore[arg-type]
    await server.start()
    client = RwsClient(RwsClientConfig(base_url=server.base_url, profile=profile))  # type: ignore[arg-type]
    try:
        yield model, server, client
    finally:
        await client.close()
        await server.stop()


def run(coro) -> None:
    asyncio.run(asyncio.wait_for(coro, 30))


async def post(
    client: RwsClient, rws1: tuple[str, str], rws2: str, form: dict[str, str] | None = None
) -> None:
    """A mutating call in the profile's form: RWS 1.0 ``path?action=...``, RWS 2.0 a sub-resource."""
    if client.config.profile == "rws1":
        await client._request("POST", rws1[0], query={"action": rws1[1]}, form=form or {})
    else:
        await client._request("POST", rws2, form=form or {})


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_a_deactivated_task_does_not_start_until_activated_again(profile: str) -> None:
    async def body() -> None:
        async with sim(profile) as (_model, _server, client):
            assert await client.get_tasks() == [
                TaskState(T, "norm" if profile == "rws1" else "normal", "linked", "ready", True, True)
            ]
            if profile == "rws2":  # the (de)activation is a write: edit mastership (or mastership=implicit)
                await client._request("POST", "/rw/mastership/edit/request", form={})
            await post(client, (f"/rw/rapid/tasks/{T}", "deactivate"), f"/rw/rapid/tasks/{T}/deactivate")
            assert not (await client.get_task(T)).active
            await client.motors_on()
            with pytest.raises(RwsError) as err:
                await client.start_rapid()
            assert (err.value.status, err.value.code) == (400, -1073442809)
            await post(client, (f"/rw/rapid/tasks/{T}", "activate"), f"/rw/rapid/tasks/{T}/activate")
            await client.start_rapid(cycle="once")
            assert (await client.get_task(T)).excstate == "started"
            execution = await client.get_execution_state()
            assert (execution.ctrlexecstate, execution.cycle) == ("running", "once")

    run(body())


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_speed_ratio_is_set_within_0_to_100(profile: str) -> None:
    async def body() -> None:
        async with sim(profile) as (model, _server, client):
            q = {"mastership": "implicit"} if profile == "rws2" else {"action": "setspeedratio"}
            await client._request("POST", "/rw/panel/speedratio", query=q, form={"speed-ratio": "50"})
            assert model.speed_ratio_pct == 50
            body = (await client._request("GET", "/rw/panel/speedratio")).body
            assert (body["_embedded"]["_state"] if profile == "rws1" else body["state"])[0][
                "speedratio"
            ] == "50"
            with pytest.raises(RwsError) as err:
                await client._request("POST", "/rw/panel/speedratio", query=q, form={"speed-ratio": "150"})
            assert err.value.status == 400 and "150" in err.value.message

    run(body())


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_modules_of_the_task_are_listed_at_the_documented_path(profile: str) -> None:
    async def body() -> None:
        async with sim(profile) as (_model, _server, client):
            assert await client.get_modules(T) == [
                ("BASE", "SysMod"),
                ("user", "SysMod"),
                ("CellEgm", "ProgMod"),
            ]

    run(body())


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_symbol_data_with_and_without_the_module_and_mastership_held_by_another_client(profile: str) -> None:
    async def body() -> None:
        async with sim(profile) as (model, server, client):
            await client.set_rapid_num(T, "egm_ramp_in_s", 0.1)  # without the module
            await client.set_rapid_num(T, "egm_ramp_in_s", 0.2, module="CellEgm")  # with it
            assert model.get_num(T, "CellEgm", "egm_ramp_in_s") == 0.2
            other = RwsClient(RwsClientConfig(base_url=server.base_url, profile=profile))  # type: ignore[arg-type]
            try:
                if profile == "rws1":
                    await other._request("POST", "/rw/mastership", query={"action": "request"}, form={})
                else:
                    await other._request("POST", "/rw/mastership/edit/request", form={})
                with pytest.raises(RwsError) as err:
                    await client.set_rapid_num(T, "egm_ramp_in_s", 0.3)
                # RW6: 400 with the manual's code; RW7: 403 "held by someone else"
                assert (err.value.status, err.value.code) == (
                    (400, -1073414146) if profile == "rws1" else (403, -1073445862)
                )
                if profile == "rws1":
                    await other._request("POST", "/rw/mastership", query={"action": "release"}, form={})
                else:
                    await other._request("POST", "/rw/mastership/edit/release", form={})
                await client.set_rapid_num(T, "egm_ramp_in_s", 0.3)
                assert model.get_num(T, "CellEgm", "egm_ramp_in_s") == 0.3
            finally:
                await other.close()

    run(body())


def test_rws2_edit_mastership_lets_writes_through_without_implicit_and_is_shown() -> None:
    async def body() -> None:
        async with sim("rws2") as (model, _server, client):
            await client._request("POST", "/rw/mastership/edit/request", form={})
            state = (await client._request("GET", "/rw/mastership/edit")).body["state"][0]
            assert state["mastership"] != "nomaster"
            path = f"/rw/rapid/symbol/RAPID/{T}/egm_ramp_in_s/data"
            await client._request("POST", path, form={"value": "0.4"})  # no mastership=implicit
            assert model.get_num(T, None, "egm_ramp_in_s") == 0.4
            await client._request("POST", "/rw/mastership/edit/release", form={})
            with pytest.raises(RwsError) as err:
                await client._request("POST", path, form={"value": "0.5"})
            assert (err.value.status, err.value.code) == (403, -1073445859)

    run(body())


def test_task_names_are_case_insensitive_on_rws2_only() -> None:
    async def body() -> None:
        for profile, ok in (("rws2", True), ("rws1", False)):
            async with sim(profile) as (_model, _server, client):
                if ok:
                    assert (await client.get_task("t_rob1")).name == T
                else:
                    with pytest.raises(RwsError) as err:
                        await client.get_task("t_rob1")
                    assert (err.value.status, err.value.code) == (400, -1073445879)

    run(body())


def test_start_rejects_an_undocumented_parameter_value_and_keeps_serving() -> None:
    async def body() -> None:
        async with sim("rws1") as (model, _server, client):
            await client.motors_on()
            with pytest.raises(RwsError) as err:
                await client._request(
                    "POST", "/rw/rapid/execution", query={"action": "start"}, form={"cycle": "twice"}
                )
            assert err.value.status == 400 and "cycle" in err.value.message
            assert model.rapid_state == "stopped"
            answer = await client._request("GET", "/rw/rapid/execution", query={"json": "1"})
            assert json.loads(answer.text)["_embedded"]["_state"][0]["ctrlexecstate"] == "stopped"

    run(body())
