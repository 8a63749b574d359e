"""RWS client against the RWS server simulator over loopback, both profiles."""

from __future__ import annotations

import asyncio
import base64
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import aclosing, asynccontextmanager

import aiohttp
import numpy as np
import pytest

from drivers.abb_egm.digest import parse_auth_params
from drivers.abb_egm.rapid_values import RC_IO_ACCESS_DENIED
from drivers.abb_egm.rws_client import (
    RwsAuthError,
    RwsBusyError,
    RwsClient,
    RwsClientConfig,
    RwsError,
    RwsTimeoutError,
    StateChange,
    _DigestState,
)
from drivers.abb_egm.sim.model import EVENT_EGM_COMM_TIMEOUT, ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer
from tests.support.waits import wait_until

T = "T_ROB1"


def run(coro_fn: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(coro_fn(), 30))


@asynccontextmanager
async def cell(
    profile: str = "rws1", *, password: str = "robotics", max_sessions: int = 70, timeout_s: float = 5.0
) -> AsyncIterator[tuple[ControllerModel, RwsServer, RwsClient]]:
    model = ControllerModel()
    server = RwsServer(model, profile=profile, host="127.0.0.1", port=0, max_sessions=max_sessions)  # type: ignore[arg-type]
    await server.start()
    client = RwsClient(
        RwsClientConfig(
            base_url=server.base_url,
            profile=profile,
            password=password,
            timeout_s=timeout_s,
            poll_interval_s=0.02,
        )  # type: ignore[arg-type]
    )
    try:
        yield model, server, client
    finally:
        await client.close()
        await server.stop()


PROFILES = ["rws1", "rws2"]


# ---- auth -------------------------------------------------------------------------------------


def test_rws1_answers_401_with_a_digest_challenge_before_login() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, _client), aiohttp.ClientSession() as http:
            async with http.get(server.base_url + "/rw/panel/ctrlstate?json=1") as resp:
                assert resp.status == 401
                challenge = resp.headers["WWW-Authenticate"]
            assert challenge.startswith("Digest ")
            assert 'qop="auth"' in challenge and "nonce=" in challenge
            assert server.stats["sessions_created"] == 0

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_client_logs_in_and_reads_controller_state(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, _server, client):
            assert await client.get_ctrl_state() == "motoroff"
            assert await client.get_opmode() == "AUTO"
            assert client.logins == 1

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_wrong_password_raises_auth_error_naming_the_user(profile: str) -> None:
    async def body() -> None:
        async with cell(profile, password="wrong") as (_, server, client):
            with pytest.raises(RwsAuthError) as err:
                await client.get_ctrl_state()
            assert err.value.status == 401
            assert "Default User" in str(err.value)
            assert server.stats["sessions_created"] == 0
            assert server.stats["auth_failures"] >= 1

    run(body)


def test_digest_response_with_wrong_uri_is_refused() -> None:
    """A digest answer computed for another URI must not open a session (the server checks uri)."""

    async def body() -> None:
        async with cell("rws1") as (_, server, client), aiohttp.ClientSession() as http:
            async with http.get(server.base_url + "/rw/panel/ctrlstate?json=1") as resp:
                state = _DigestState(parse_auth_params(resp.headers["WWW-Authenticate"][7:]))
            header = state.header("GET", "/rw/panel/opmode?json=1", "Default User", "robotics")
            async with http.get(
                server.base_url + "/rw/panel/ctrlstate?json=1", headers={"Authorization": header}
            ) as r2:
                assert r2.status == 401
            assert server.stats["sessions_created"] == 0
            del client

    run(body)


def test_rws2_refuses_requests_without_v2_media_type() -> None:
    async def body() -> None:
        async with cell("rws2") as (_, server, _client), aiohttp.ClientSession() as http:
            token = base64.b64encode(b"Default User:robotics").decode()
            headers = {"Authorization": f"Basic {token}", "Accept": "application/hal+json"}
            async with http.get(server.base_url + "/rw/panel/ctrl-state", headers=headers, ssl=False) as resp:
                assert resp.status == 406
                assert resp.headers["Content-Type"] == "application/hal+json;v=2.0"
                assert "v=2.0" in (await resp.json(content_type=None))["status"]["msg"]

    run(body)


def test_rws2_refuses_mutation_without_mastership() -> None:
    async def body() -> None:
        async with cell("rws2") as (model, server, _client), aiohttp.ClientSession() as http:
            token = base64.b64encode(b"Default User:robotics").decode()
            headers = {
                "Authorization": f"Basic {token}",
                "Accept": "application/hal+json;v=2.0",
                "Content-Type": "application/x-www-form-urlencoded;v=2.0",
            }
            url = server.base_url + "/rw/panel/ctrl-state"
            async with http.post(url, data="ctrl-state=motoron", headers=headers, ssl=False) as resp:
                assert resp.status == 403
            assert model.ctrl_state == "motoroff"
            async with http.post(
                url + "?mastership=implicit", data="ctrl-state=motoron", headers=headers, ssl=False
            ) as r:
                assert r.status == 204
            assert model.ctrl_state == "motoron"

    run(body)


def test_rws2_serves_https_with_a_self_signed_certificate() -> None:
    async def body() -> None:
        async with cell("rws2") as (_, server, _client):
            assert server.base_url.startswith("https://")
            assert server.cert_path is not None
            # A verifying client pinned to the generated certificate connects; an unpinned one fails.
            pinned = RwsClient(
                RwsClientConfig(base_url=server.base_url, profile="rws2", tls_ca_file=server.cert_path)
            )
            try:
                assert await pinned.get_ctrl_state() == "motoroff"
            finally:
                await pinned.close()
            async with aiohttp.ClientSession() as http:
                with pytest.raises(aiohttp.ClientConnectorCertificateError):
                    await http.get(server.base_url + "/rw/panel/ctrl-state")

    run(body)


# ---- sessions ---------------------------------------------------------------------------------


@pytest.mark.parametrize("profile", PROFILES)
def test_client_reuses_one_session_for_many_requests(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, server, client):
            for _ in range(20):
                await client.get_ctrl_state()
                await client.get_execution_state()
            await asyncio.gather(*(client.get_opmode() for _ in range(10)))
            assert server.stats["sessions_created"] == 1
            assert len(server.sessions) == 1

    run(body)


def test_concurrent_first_requests_open_only_one_session() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            await asyncio.gather(*(client.get_ctrl_state() for _ in range(8)))
            assert server.stats["sessions_created"] == 1

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_client_logs_in_again_when_the_controller_drops_the_session(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, server, client):
            await client.get_ctrl_state()
            server.expire_sessions()
            assert await client.get_ctrl_state() == "motoroff"
            assert client.logins == 2
            assert server.stats["sessions_created"] == 2

    run(body)


def test_close_logs_out_and_frees_the_session() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            await client.get_ctrl_state()
            assert len(server.sessions) == 1
            await client.close()
            assert len(server.sessions) == 0

    run(body)


def test_server_answers_503_beyond_the_session_limit_and_keeps_serving() -> None:
    async def body() -> None:
        async with cell("rws1", max_sessions=2) as (_, server, client):
            others = [RwsClient(RwsClientConfig(base_url=server.base_url)) for _ in range(2)]
            try:
                for o in others:
                    await o.get_ctrl_state()
                with pytest.raises(RwsBusyError) as err:
                    await client.get_ctrl_state()
                assert err.value.status == 503
                assert server.stats["rejected_busy"] == 1
                await others[0].close()
                assert await client.get_ctrl_state() == "motoroff"
            finally:
                for o in others:
                    await o.close()

    run(body)


# ---- panel and execution ----------------------------------------------------------------------


@pytest.mark.parametrize("profile", PROFILES)
def test_motors_on_start_stop_and_reset_pp(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, _server, client):
            await client.motors_on()
            assert await client.get_ctrl_state() == "motoron"
            await client.start_rapid()
            assert (await client.get_execution_state()).ctrlexecstate == "running"
            assert model.egm_wanted
            await client.stop_rapid()
            assert (await client.get_execution_state()).ctrlexecstate == "stopped"
            assert not model.egm_wanted
            await client.reset_pp()
            await client.motors_off()
            assert await client.get_ctrl_state() == "motoroff"

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_start_with_motors_off_carries_the_controller_code_and_message(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, _server, client):
            with pytest.raises(RwsError) as err:
                await client.start_rapid()
            assert err.value.status == 400
            assert err.value.code is not None and err.value.code < 0
            assert "motors are not on" in err.value.message

    run(body)


def test_motors_on_is_refused_during_emergency_stop() -> None:
    async def body() -> None:
        async with cell("rws1") as (model, _server, client):
            model.emergency_stop()
            assert await client.get_ctrl_state() == "emergencystop"
            with pytest.raises(RwsError, match="emergencystop"):
                await client.motors_on()
            model.reset_emergency_stop()
            await client.motors_on()
            assert await client.get_ctrl_state() == "motoron"

    run(body)


# ---- RAPID variables, IO, event log, position -------------------------------------------------


@pytest.mark.parametrize("profile", PROFILES)
def test_rapid_variables_round_trip_num_bool_string_jointtarget(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, _server, client):
            model.define_var(T, "CellEgm", "plate_id", "string", '""')
            model.define_var(
                T, "CellEgm", "home_jt", "jointtarget", "[[0,0,0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]]"
            )
            await client.set_rapid_num(T, "egm_comm_timeout_s", 2.5)
            assert await client.get_rapid_num(T, "egm_comm_timeout_s") == 2.5
            await client.set_rapid_bool(T, "egm_end", True, module="CellEgm")
            assert await client.get_rapid_bool(T, "egm_end", module="CellEgm") is True
            await client.set_rapid_string(T, "plate_id", 'P-7 "bow" & stern')
            assert await client.get_rapid_string(T, "plate_id") == 'P-7 "bow" & stern'
            q = np.array([10.5, -20.0, 30.25, 0.0, 45.0, -90.0])
            await client.set_rapid_jointtarget(T, "home_jt", q)
            jt = await client.get_rapid_jointtarget(T, "home_jt")
            np.testing.assert_allclose(jt.robax_deg, q)
            assert model.get_jointtarget(T, None, "home_jt").extax[0] == 9e9

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_writing_a_malformed_literal_is_refused_with_the_value_named(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, server, client):
            with pytest.raises(RwsError) as err:
                await client.set_rapid_var(T, "egm_comm_timeout_s", "fast")
            assert err.value.status == 400 and "'fast'" in err.value.message
            with pytest.raises(RwsError) as err2:
                await client.get_rapid_var(T, "no_such_var")
            # RobotWare 6 answers an unknown symbol with 400 (captured answer), RobotWare 7 with 404.
            assert err2.value.status == (400 if profile == "rws1" else 404)
            assert "no_such_var" in err2.value.message
            assert server.stats["bad_requests"] == 2
            assert await client.get_rapid_num(T, "egm_comm_timeout_s") == 1.0  # still serving

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_io_signals_read_write_and_access_level_refusal(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, _server, client):
            assert await client.get_io("DO_EGM_END") == 0.0
            await client.set_io("DO_EGM_END", 1, network="Local", device="DRV_1")
            assert model.get_io("DO_EGM_END") == 1.0
            assert await client.get_io("DO_EGM_END", network="Local", device="DRV_1") == 1.0
            with pytest.raises(RwsError) as err:
                await client.set_io("DI_PLATE_PRESENT", 1)
            assert err.value.code == RC_IO_ACCESS_DENIED and err.value.status == 403
            with pytest.raises(RwsError) as err2:
                await client.get_io("DO_EGM_END", network="Other", device="DRV_1")
            assert err2.value.status == 404

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_event_log_lists_newest_first_with_codes(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, _server, client):
            await client.motors_on()
            await client.start_rapid()
            model.egm_session_ended("no sensor data for 1.0 s", EVENT_EGM_COMM_TIMEOUT)
            entries = await client.read_event_log()
            assert entries[0].code == EVENT_EGM_COMM_TIMEOUT and entries[0].msgtype == 3
            assert entries[0].title == "No data from the UdpUc device"
            assert [e.seqnum for e in entries] == sorted((e.seqnum for e in entries), reverse=True)
            assert (await client.get_execution_state()).ctrlexecstate == "stopped"
            assert await client.get_rapid_num(T, "egm_status") == -EVENT_EGM_COMM_TIMEOUT

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_joint_and_cartesian_position_come_from_the_position_source(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, _server, client):
            np.testing.assert_allclose(await client.get_joint_position(), np.zeros(6))
            pose = await client.get_cartesian()
            np.testing.assert_allclose(pose.pos_mm, [1580.0, 0.0, 1765.0])
            q = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.5])
            quat = np.array([0.5, 0.5, 0.5, 0.5])
            model.set_position_source(lambda: (q, np.array([1000.0, -200.5, 900.0]), quat))
            np.testing.assert_allclose(await client.get_joint_position(), q)
            pose = await client.get_cartesian()
            np.testing.assert_allclose(pose.pos_mm, [1000.0, -200.5, 900.0])
            np.testing.assert_allclose(pose.quat_wxyz, quat)
            # no additional axis: eax_a..eax_f are 9E+09 on the wire, None in the client
            assert (await client.get_mechunit_joints()).external_axes_mm == (None,) * 6
            assert pose.external_axes_mm == (None,) * 6
            model.set_external_axes_source(lambda: np.array([1234.5678, 9e9, 9e9, 9e9, 9e9, 9e9]))
            mj = await client.get_mechunit_joints()
            np.testing.assert_allclose(mj.q_deg, q)
            assert mj.external_axes_mm == (1234.5678, None, None, None, None, None)
            assert (await client.get_cartesian()).external_axes_mm == mj.external_axes_mm

    run(body)


# ---- faults and timeouts ----------------------------------------------------------------------


def test_injected_error_carries_status_code_and_message() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            server.inject_error(
                "/rw/rapid/execution", status=500, code=-1073442813, message="RAPI unidentified error"
            )
            with pytest.raises(RwsError) as err:
                await client.get_execution_state()
            assert (err.value.status, err.value.code) == (500, -1073442813)
            assert "RAPI unidentified error" in str(err.value)
            assert await client.get_ctrl_state() == "motoroff"  # other endpoints unaffected
            server.clear_faults()
            assert (await client.get_execution_state()).ctrlexecstate == "stopped"

    run(body)


def test_slow_controller_gives_a_bounded_timeout_error() -> None:
    async def body() -> None:
        async with cell("rws1", timeout_s=0.3) as (_, server, client):
            await client.get_ctrl_state()
            # the server would answer after 10 s: the client gave up on its own 0.3 s timeout, long
            # before (bounded by the server's delay, not by a figure load can trip)
            server.set_delay(10.0, "/rw/panel/opmode")
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            with pytest.raises(RwsTimeoutError):
                await client.get_opmode()
            assert loop.time() - t0 < 5.0
            server.set_delay(0, "/rw/panel/opmode")
            assert await client.get_opmode() == "AUTO"

    run(body)


def test_server_survives_malformed_form_bodies_and_counts_them() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            await client.get_ctrl_state()
            http = client._session()  # same cookie jar: an authenticated session
            url = server.base_url + "/rw/rapid/symbol/data/RAPID/T_ROB1/egm_end?action=set&json=1"
            ctype = {"Content-Type": "application/x-www-form-urlencoded"}
            for data in (b"\xff\xfe", b"value", b"novalue=1"):
                async with http.post(url, data=data, headers=ctype) as resp:
                    assert resp.status == 400
                    assert (await resp.json())["_embedded"]["status"]["msg"]
            assert server.stats["bad_requests"] == 3
            assert await client.get_ctrl_state() == "motoroff"

    run(body)


# ---- state changes ----------------------------------------------------------------------------


async def _collect(
    client: RwsClient, n: int, into: list[StateChange] | None = None, **kw: object
) -> list[StateChange]:
    out: list[StateChange] = [] if into is None else into
    async with aclosing(client.changes(**kw)) as it:  # type: ignore[arg-type]
        async for ch in it:
            out.append(ch)
            if len(out) >= n:
                break
    return out


@pytest.mark.parametrize("profile", PROFILES)
def test_state_changes_arrive_for_motors_execution_and_end_variable(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (model, server, client):
            seen: list[StateChange] = []
            requests0 = server.stats["requests"]
            task = asyncio.create_task(
                _collect(client, 4, seen, ctrl_state=True, execution=True, rapid_vars=[(T, "egm_status")])
            )

            def seen_kinds() -> list[tuple[str, str]]:
                return [(c.kind, c.value) for c in seen]

            # in place before the changes: the websocket subscribed (rws1), or the first poll's three
            # reads answered (rws2: a request of the second poll has come, the login's 401 aside)
            await wait_until(
                lambda: (
                    (len(server._subs) == 1 and bool(server._websockets))
                    if profile == "rws1"
                    else server.stats["requests"] - requests0 >= 5
                ),
                0.3,
                "the subscription or first poll",
            )
            model.motors_on()
            await wait_until(lambda: ("ctrlstate", "motoron") in seen_kinds(), 0.1, "motors on reported")
            model.start_rapid()
            await wait_until(
                lambda: ("execution", "running") in seen_kinds() or ("rapid-data", "1") in seen_kinds(),
                0.1,
                "the program's start reported",
            )
            model.set_bool(T, None, "egm_end", True)
            changes = await asyncio.wait_for(task, 5)
            kinds = [(c.kind, c.value) for c in changes]
            assert ("ctrlstate", "motoron") in kinds
            assert ("execution", "running") in kinds or ("rapid-data", "1") in kinds
            assert ("rapid-data", "2") in kinds or ("execution", "stopped") in kinds

    run(body)


def test_rws1_subscription_uses_a_websocket_and_reports_signals_and_elog() -> None:
    async def body() -> None:
        async with cell("rws1") as (model, server, client):
            task = asyncio.create_task(
                _collect(client, 2, ctrl_state=False, execution=False, signals=["DO_EGM_END"], elog=True)
            )
            await wait_until(lambda: len(server._subs) == 1, 0.3)  # subscribed before the changes
            model.set_io("DO_EGM_END", 1)
            model.log_event(80001, "Cell note", "from the test", "warning")
            changes = await asyncio.wait_for(task, 5)
            assert StateChange("signal", "DO_EGM_END", "1") in changes
            assert any(c.kind == "elog" and c.value == "80001" for c in changes)
            await wait_until(lambda: len(server._subs) == 0, 0.1)  # leaving the iterator deletes it
            assert server.stats["sessions_created"] == 1

    run(body)


def test_rws1_subscription_is_renewed_when_the_controller_closes_the_websocket() -> None:
    async def body() -> None:
        async with cell("rws1") as (model, server, client):
            task = asyncio.create_task(_collect(client, 1, ctrl_state=True, execution=False))
            await wait_until(
                lambda: len(server._subs) == 1 and server._websockets, 0.3, "the first subscription"
            )
            await server.close_subscriptions()
            await wait_until(
                lambda: server.stats["subscriptions_created"] >= 2 and server._websockets,
                2.0,
                "a new subscription",
            )
            assert server.stats["subscriptions_created"] == 2
            model.motors_on()
            changes = await asyncio.wait_for(task, 5)
            assert changes == [StateChange("ctrlstate", "ctrlstate", "motoron")]

    run(body)


# ---- wire details -----------------------------------------------------------------------------


def test_rws1_without_json_answers_xhtml_shaped_like_the_controller() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            await client.get_ctrl_state()
            async with client._session().get(server.base_url + "/rw/panel/ctrlstate") as resp:
                text = await resp.text()
                assert resp.status == 200 and "xhtml" in resp.headers["Content-Type"]
            assert (
                '<li class="pnl-ctrlstate" title="ctrlstate"><span class="ctrlstate">motoroff</span></li>'
                in text
            )
            async with client._session().get(server.base_url + "/rw/panel/ctrlstate?json=1") as resp:
                body = await resp.json()
            assert body["_embedded"]["_state"][0] == {
                "_type": "pnl-ctrlstate",
                "_title": "ctrlstate",
                "ctrlstate": "motoroff",
            }

    run(body)


def test_rws2_json_uses_top_level_state_and_embedded_resources() -> None:
    async def body() -> None:
        async with cell("rws2") as (model, server, client):
            model.log_event(80002, "note", "", "info")
            await client.get_ctrl_state()
            headers = {"Accept": "application/hal+json;v=2.0"}
            http = client._session()
            async with http.get(server.base_url + "/rw/panel/ctrl-state", headers=headers) as resp:
                assert (await resp.json())["state"][0]["ctrlstate"] == "motoroff"
            async with http.get(server.base_url + "/rw/elog/0", headers=headers) as resp:
                assert (await resp.json())["_embedded"]["resources"][0]["code"] == "80002"
            # RWS 1.0 paths do not exist on the RWS 2.0 profile.
            with pytest.raises(RwsError) as err:
                await client._request("GET", "/rw/panel/ctrlstate")
            assert err.value.status == 404

    run(body)


def test_expired_digest_nonce_is_answered_with_stale_and_a_fresh_nonce() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, _client), aiohttp.ClientSession() as http:
            server.nonce_lifetime_s = 0.05
            url = server.base_url + "/rw/panel/ctrlstate?json=1"
            async with http.get(url) as resp:
                state = _DigestState(parse_auth_params(resp.headers["WWW-Authenticate"][7:]))
            await asyncio.sleep(0.1)  # stays: the nonce's 0.05 s lifetime running out is the case
            header = state.header("GET", "/rw/panel/ctrlstate?json=1", "Default User", "robotics")
            async with http.get(url, headers={"Authorization": header}) as resp:
                assert resp.status == 401
                assert 'stale="TRUE"' in resp.headers["WWW-Authenticate"]
            assert server.stats["sessions_created"] == 0

    run(body)


def test_replayed_digest_nonce_count_is_refused() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, _client):
            url = server.base_url + "/rw/panel/ctrlstate?json=1"
            async with aiohttp.ClientSession() as http, http.get(url) as resp:
                state = _DigestState(parse_auth_params(resp.headers["WWW-Authenticate"][7:]))
            header = state.header("GET", "/rw/panel/ctrlstate?json=1", "Default User", "robotics")
            for expected in (200, 401):  # a fresh client each time, so no cookie helps
                async with (
                    aiohttp.ClientSession() as http,
                    http.get(url, headers={"Authorization": header}) as r,
                ):
                    assert r.status == expected

    run(body)


def test_idle_session_expires_and_the_client_logs_in_again() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            server.session_idle_s = 0.1
            await client.get_ctrl_state()
            await asyncio.sleep(0.2)  # stays: the session's 0.1 s idle time running out is the case
            await client.get_ctrl_state()
            assert client.logins == 2 and len(server.sessions) == 1

    run(body)


@pytest.mark.parametrize("profile", PROFILES)
def test_session_opened_by_a_failing_first_request_is_reused(profile: str) -> None:
    async def body() -> None:
        async with cell(profile) as (_, server, client):
            with pytest.raises(RwsError):
                await client.start_rapid()  # refused: motors off; the login happened on this request
            await client.get_ctrl_state()
            await client.motors_on()
            assert server.stats["sessions_created"] == 1 and client.logins == 1

    run(body)


@pytest.mark.parametrize("backend", ["cryptography", pytest.param("openssl", marks=pytest.mark.process)])
def test_certificate_generation_gives_a_loadable_cert_for_the_host(
    backend: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil
    import ssl

    from drivers.abb_egm.sim import rws_server

    if backend == "openssl":
        if shutil.which("openssl") is None:
            pytest.skip("no openssl command on this machine")

        def no_cryptography(*_a: object) -> None:
            raise ImportError("cryptography hidden by the test")

        monkeypatch.setattr(rws_server, "_cert_with_cryptography", no_cryptography)
    cert, key = asyncio.run(rws_server.generate_self_signed_cert(str(tmp_path), "127.0.0.1"))
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.load_cert_chain(cert, key)  # raises if the pair does not match
    client_ctx = ssl.create_default_context(cafile=cert)
    assert client_ctx.cert_store_stats()["x509_ca"] == 1  # self-signed: usable as its own CA


def test_server_survives_garbage_bytes_on_its_socket() -> None:
    async def body() -> None:
        async with cell("rws1") as (_, server, client):
            for junk in (b"\x00\xff\x13garbage\r\n\r\n", b"GET /rw/panel/ctrlstate HTTP/9.9\r\nHost\r\n\r\n"):
                reader, writer = await asyncio.open_connection(server.host, server.port)
                writer.write(junk)
                await writer.drain()
                answer = await asyncio.wait_for(reader.read(200), 2)
                assert answer.startswith(b"HTTP/1.") and b" 400 " in answer.split(b"\r\n")[0] + b" "
                writer.close()
                await writer.wait_closed()
            assert await client.get_ctrl_state() == "motoroff"

    run(body)
