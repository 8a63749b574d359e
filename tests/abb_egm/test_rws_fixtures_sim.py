"""The simulated controller's RWS answers held to the captured ones of ../shared/testdata/rws.

Each captured exchange is repeated against the simulator over loopback (the same request, with the
simulator in the state the capture implies); the answer must have the same envelope: the exact
Content-Type, the JSON / XHTML shape and item fields, the error shape of the profile with the
controller's status and return code, the cookies, the subscription answer and its websocket.
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any
from urllib.parse import urlsplit

import aiohttp
import pytest

from drivers.abb_egm.rws_client import (
    RwsClient,
    RwsClientConfig,
    StateChange,
    _states,
    parse_event_xhtml,
    parse_xhtml,
)
from drivers.abb_egm.sim.model import ControllerModel, IoSignal
from drivers.abb_egm.sim.rws_server import RwsServer
from tests.conftest import SHARED

FIX = SHARED / "testdata" / "rws"
CTYPE = {
    ("rws1", True): "application/json",
    ("rws1", False): "application/xhtml+xml",
    ("rws2", True): "application/hal+json;v=2.0",
    ("rws2", False): "application/xhtml+xml;v=2.0",
}


def _text(rel: str) -> str:
    return (FIX / rel).read_text(encoding="utf-8")


class Sim:
    """A simulator and one logged-in client session to it; ``raw`` sends a request in that session."""

    def __init__(self, profile: str, model: ControllerModel, server: RwsServer, client: RwsClient) -> None:
        self.profile, self.model, self.server, self.client = profile, model, server, client

    async def raw(
        self,
        method: str,
        path: str,
        *,
        as_json: bool = True,
        data: str | None = None,
        session: RwsClient | None = None,
    ) -> tuple[int, Any, str]:
        c = session or self.client
        await c.get_opmode()  # logged in
        headers: dict[str, str] = {}
        if self.profile == "rws1":
            if as_json:
                path += ("&" if "?" in path else "?") + "json=1"
            if data is not None:
                headers["Content-Type"] = "application/x-www-form-urlencoded"
        else:
            headers["Accept"] = CTYPE[("rws2", as_json)]
            if data is not None:
                headers["Content-Type"] = "application/x-www-form-urlencoded;v=2.0"
        async with c._session().request(
            method, self.server.base_url + path, data=data, headers=headers
        ) as resp:
            return resp.status, resp.headers, await resp.text()

    async def other_session_holds_mastership(self) -> RwsClient:
        other = RwsClient(RwsClientConfig(base_url=self.server.base_url, profile=self.profile))  # type: ignore[arg-type]
        path = (
            "/rw/mastership/rapid?action=request" if self.profile == "rws1" else "/rw/mastership/edit/request"
        )
        status, _, _ = await self.raw("POST", path, data="", session=other)
        assert status == 204
        return other


@asynccontextmanager
async def sim(profile: str) -> AsyncIterator[Sim]:
    model = ControllerModel()
    server = RwsServer(model, profile=profile)  # type: ignore[arg-type]
    await server.start()
    client = RwsClient(RwsClientConfig(base_url=server.base_url, profile=profile))  # type: ignore[arg-type]
    try:
        yield Sim(profile, model, server, client)
    finally:
        await client.close()
        await server.stop()


def run(profile: str, body) -> None:
    async def main() -> None:
        async with sim(profile) as s:
            await body(s)

    asyncio.run(asyncio.wait_for(main(), 30))


def _shape(value: Any) -> Any:
    """The structure of a JSON value: dict keys with their shapes, list element shapes, leaf types."""
    if isinstance(value, dict):
        return {k: _shape(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_shape(v) for v in value[:1]]
    return type(value).__name__


def _assert_same_json_envelope(fixture: dict, ours: dict) -> None:
    # RWS 2.0 lists carry "status" in one capture and not in another: optional at the top level.
    assert set(fixture) - {"status"} <= set(ours) <= set(fixture) | {"status"}, (set(fixture), set(ours))
    base_f, base_o = fixture["_links"]["base"]["href"], ours["_links"]["base"]["href"]
    assert urlsplit(base_f).path == urlsplit(base_o).path, (base_f, base_o)
    if "self" in fixture["_links"] and "?" not in fixture["_links"]["self"]["href"]:
        assert ours["_links"]["self"]["href"] == fixture["_links"]["self"]["href"]
    if "status" in ours:
        assert ours["status"] == {"code": 294912}
    if "_embedded" in fixture:
        assert set(fixture["_embedded"]) == set(ours["_embedded"])


def _assert_items_cover(
    fixture_items: list[dict], our_items: list[dict], ignore: set[str] = frozenset()
) -> None:
    """Each item type of the capture appears in our answer, with at least the capture's fields."""
    ours_by_type = {it["_type"]: it for it in our_items}
    for it in fixture_items:
        assert it["_type"] in ours_by_type, (it["_type"], list(ours_by_type))
        missing = set(it) - set(ours_by_type[it["_type"]]) - ignore
        assert not missing, (it["_type"], missing)


# ---- success answers --------------------------------------------------------------------------

# (profile, fixture, request path, JSON?, fields the simulator does not have, with the reason)
SUCCESS = [
    ("rws1", "rws1/doc_get_panel_ctrlstate.xml", "/rw/panel/ctrlstate", False, set()),
    ("rws1", "rws1/doc_get_panel_opmode.xml", "/rw/panel/opmode", False, set()),
    ("rws1", "rws1/doc_get_rapid_execution.xml", "/rw/rapid/execution", False, set()),
    ("rws1", "rws1/zwj12_get_rapid_execution_json1.REFORMATTED.json", "/rw/rapid/execution", True, set()),
    ("rws1", "rws1/doc_get_rapid_tasks.xml", "/rw/rapid/tasks", False, set()),
    ("rws1", "rws1/doc_get_rapid_tasks_T_ROB1.xml", "/rw/rapid/tasks/T_ROB1", False, set()),
    ("rws1", "rws1/doc_get_ms_mechunits_ROB_1_jointtarget.xml", "/rw/motionsystem/mechunits/ROB_1/jointtarget", False, set()),
    ("rws1", "rws1/doc_get_ms_mechunits_ROB_1_robtarget.xml", "/rw/motionsystem/mechunits/ROB_1/robtarget", False, set()),
    ("rws1", "rws1/doc_get_ios_signal_Local_DRV_1_DRV1CHAIN2.xml", "/rw/iosystem/signals/Local/DRV_1/DO_EGM_END", False, set()),
    # src-name: the event's source (a mechanical unit); argv: the simulator's events have no arguments
    ("rws1", "rws1/doc_get_elog_0_8_message.xml", "/rw/elog/0/1", False, {"src-name", "argv"}),
    ("rws2", "rws2/ichbinmeraj_get_panel_ctrl-state.json", "/rw/panel/ctrl-state", True, set()),
    ("rws2", "rws2/ichbinmeraj_get_ms_mechunits_ROB_1_jointtarget.json", "/rw/motionsystem/mechunits/ROB_1/jointtarget", True, set()),
    ("rws2", "rws2/ichbinmeraj_get_rapid_tasks.json", "/rw/rapid/tasks", True, set()),
    ("rws2", "rws2/ichbinmeraj_get_rapid_tasks_T_ROB1_modules.json", "/rw/rapid/tasks/T_ROB1/modules", True, set()),
    ("rws2", "rws2/blueicaro_get_elog_0_95_lang_en.json", "/rw/elog/0/1?lang=en", True, {"argv"}),
    ("rws2", "rws2/blueicaro_get_elog_1_84_lang_en.REFORMATTED.json", "/rw/elog/0/1?lang=en", True, set()),
    ("rws2", "rws2/ichbinmeraj_get_elog_0_lang_en.PARTIAL.json", "/rw/elog/0?lang=en", True, set()),
    ("rws2", "rws2/blueicaro_get_elog_domains.json", "/rw/elog", True, set()),
    ("rws2", "rws2/blueicaro_get_iosystem_signals.json", "/rw/iosystem/signals", True, set()),
    ("rws2", "rws2/blueicaro_get_rapid_tasks_t_rob1_execution_lowercase.json", "/rw/rapid/tasks/t_rob1", True, None),
]  # fmt: skip


@pytest.mark.parametrize(
    ("profile", "fixture", "path", "as_json", "ignore"), SUCCESS, ids=[s[1] for s in SUCCESS]
)
def test_simulator_answers_each_captured_request_in_the_same_envelope(
    profile, fixture, path, as_json, ignore
) -> None:
    async def body(s: Sim) -> None:
        s.model.log_event(10011, "Motors ON state", "Motors switched on.", "info")  # event 1
        status, headers, text = await s.raw("GET", path, as_json=as_json)
        assert status == 200, text
        assert headers["Content-Type"] == CTYPE[(profile, as_json)]
        if ignore is None:  # lower-case task name: RobotWare 7 answers it, with the name as asked
            assert json.loads(text)["_links"]["self"]["href"] == "tasks/t_rob1"
            return
        ours = json.loads(text) if as_json else parse_xhtml(text)
        ref = json.loads(_text(fixture)) if as_json else parse_xhtml(_text(fixture))
        if as_json:
            _assert_same_json_envelope(ref, ours)
        else:
            has_title = "<title>" in text
            assert has_title == (profile == "rws1")
            assert (
                urlsplit(ours["_links"]["base"]["href"]).path == urlsplit(ref["_links"]["base"]["href"]).path
            )
        _assert_items_cover(_states(ref), _states(ours), ignore)

    run(profile, body)


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
@pytest.mark.parametrize("as_json", [True, False])
def test_content_type_is_the_controllers_exact_string_for_json_and_xhtml(profile: str, as_json: bool) -> None:
    async def body(s: Sim) -> None:
        status, headers, text = await s.raw("GET", "/rw/panel/opmode", as_json=as_json)
        assert status == 200 and headers["Content-Type"] == CTYPE[(profile, as_json)]
        if not as_json:
            assert text.startswith(
                '<?xml version="1.0" encoding="UTF-8"?><html xmlns="http://www.w3.org/1999/xhtml">'
            )
            assert '<li class="pnl-opmode" title="opmode"><span class="opmode">AUTO</span></li>' in text

    run(profile, body)


def test_trailing_slash_and_query_name_the_same_resource() -> None:
    async def body(s: Sim) -> None:
        s.model.log_event(80001, "note", "", "info")
        a = await s.raw("GET", "/rw/elog/0?lang=en")
        b = await s.raw("GET", "/rw/elog/0/?lang=en")  # as abb-robot-client sends it
        assert a[0] == b[0] == 200
        assert _states(json.loads(a[2])) == _states(json.loads(b[2]))
        assert _states(json.loads(a[2]))[0]["title"] == "note"
        no_lang = _states(json.loads((await s.raw("GET", "/rw/elog/0"))[2]))[0]
        assert "title" not in no_lang and no_lang["code"] == "80001"  # texts only in a language asked for

    run("rws1", body)


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_signal_and_event_lists_page_with_next_links_the_client_follows(profile: str) -> None:
    async def body(s: Sim) -> None:
        for i in range(150):
            s.model.define_signal(IoSignal(f"DO_{i:03d}", "DO"))
        status, _, text = await s.raw("GET", "/rw/iosystem/signals?limit=40")
        page = json.loads(text)
        assert status == 200 and len(_states(page)) == 40
        assert page["_links"]["next"]["href"] == "signals?start=40&limit=40"
        names = [sig.name for sig in await s.client.list_signals()]
        assert len(names) == len(s.model.signals) == 152 and len(set(names)) == 152
        for i in range(120):
            s.model.log_event(80000 + i, "note", "", "info")
        entries = await s.client.read_event_log()
        assert len(entries) == 120 and entries[0].code == 80119

    run(profile, body)


# ---- errors -----------------------------------------------------------------------------------


async def _scenario(s: Sim, name: str) -> tuple[str, str, str | None]:
    """Put the simulator in the state of a captured error; returns (method, path, form body)."""
    if name in ("held", "symbol_held", "start_held"):
        await s.other_session_holds_mastership()
    v1 = s.profile == "rws1"
    return {
        "held": ("POST", "/rw/mastership/rapid?action=request" if v1 else "/rw/mastership/edit/request", ""),
        "symbol_held": ("POST", "/rw/rapid/symbol/data/RAPID/T_ROB1/user/reg1?action=set", "value=1"),
        "start_wrong_state": ("POST", "/rw/rapid/execution?action=start", ""),
        "start_held": ("POST", "/rw/rapid/execution/start", ""),
        "module": ("GET", "/rw/rapid/tasks/T_ROB1/modules/NoSuchModule", None),
        "signal_write": ("POST", "/rw/iosystem/signals/DI_PLATE_PRESENT" + ("?action=set" if v1 else "/set-value?mastership=implicit"), "lvalue=1"),
        "signal": ("GET", "/rw/iosystem/signals/NoSuchNet/NoSuchDev/NoSuchSig", None),
        "symbol": ("GET", "/rw/rapid/symbol/data/RAPID/T_ROB1/NoMod/noSym" if v1 else "/rw/rapid/symbol/RAPID/T_ROB1/BASE/no_such_var/data", None),
        "speedratio": ("POST", "/rw/panel/speedratio?action=setspeedratio", "speed-ratio=50"),
        "task": ("GET", "/rw/rapid/tasks/NO_SUCH_TASK", None),
    }[name]  # fmt: skip


# (profile, fixture, scenario, JSON?, HTTP status); the code is the fixture's
ERRORS = [
    ("rws1", "rws1/doc_error_400_rapid_symbol_set_no_mastership.xml", "symbol_held", False, 400),
    ("rws1", "rws1/errors/ichbinmeraj_400-exec-start-wrong-state-json.json", "start_wrong_state", True, 400),
    ("rws1", "rws1/errors/ichbinmeraj_403-mastership-held-json.json", "held", True, 403),
    ("rws1", "rws1/errors/ichbinmeraj_403-mastership-held-xhtml.xml", "held", False, 403),
    ("rws1", "rws1/errors/ichbinmeraj_403-signal-write-no-rmmp-json.json", "signal_write", True, 403),
    ("rws1", "rws1/errors/ichbinmeraj_404-module-json.json", "module", True, 404),
    ("rws1", "rws1/errors/ichbinmeraj_404-module-xhtml.xml", "module", False, 404),
    ("rws1", "rws1/errors/ichbinmeraj_404-signal-json.json", "signal", True, 404),
    ("rws1", "rws1/errors/ichbinmeraj_404-symbol-json.json", "symbol", True, 400),
    ("rws2", "rws2/errors/ichbinmeraj_400-module-missing-haljson.json", "module", True, 400),
    ("rws2", "rws2/errors/ichbinmeraj_400-module-missing-xhtml.xml", "module", False, 400),
    ("rws2", "rws2/errors/ichbinmeraj_403-exec-start-blocked-haljson.json", "start_held", True, 403),
    ("rws2", "rws2/errors/ichbinmeraj_403-mastership-held-haljson.json", "held", True, 403),
    ("rws2", "rws2/errors/ichbinmeraj_403-mastership-held-xhtml.xml", "held", False, 403),
    ("rws2", "rws2/errors/ichbinmeraj_403-signal-write-no-rmmp-haljson.json", "signal_write", True, 403),
    ("rws2", "rws2/errors/ichbinmeraj_403-speedratio-no-mastership-haljson.json", "speedratio", True, 403),
    ("rws2", "rws2/errors/ichbinmeraj_403-speedratio-no-mastership-xhtml.xml", "speedratio", False, 403),
    ("rws2", "rws2/errors/ichbinmeraj_404-signal-haljson.json", "signal", True, 404),
    ("rws2", "rws2/errors/ichbinmeraj_404-symbol-overloaded-code-haljson.json", "symbol", True, 404),
    ("rws2", "rws2/ichbinmeraj_error_task_not_found.json", "task", True, 400),
]  # fmt: skip
_XHTML_CODE = re.compile(
    r'<div class="status">\s*<span class="code">(-?\d+)</span>\s*<span class="msg">[^<]*</span>\s*</div>'
)


@pytest.mark.parametrize(
    ("profile", "fixture", "scenario", "as_json", "status"), ERRORS, ids=[e[1] for e in ERRORS]
)
def test_simulator_refuses_as_the_captured_controller_with_its_status_code_and_error_shape(
    profile, fixture, scenario, as_json, status
) -> None:
    async def body(s: Sim) -> None:
        s.model.define_var("T_ROB1", "user", "reg1", "num", "0")
        method, path, form = await _scenario(s, scenario)
        got_status, headers, text = await s.raw(method, path, as_json=as_json, data=form)
        ref_text = _text(fixture)
        assert got_status == status, text
        assert headers["Content-Type"] == CTYPE[(profile, as_json)]
        if as_json:
            ref, ours = json.loads(ref_text), json.loads(text)
            assert _shape(ours) == _shape(ref)  # RWS 1.0: status under _embedded beside []; 2.0: top level
            st_ref = ref["status"] if profile == "rws2" else ref["_embedded"]["status"]
            st_ours = ours["status"] if profile == "rws2" else ours["_embedded"]["status"]
            assert st_ours["code"] == st_ref["code"]
            assert urlsplit(ours["_links"]["base"]["href"]).path == "/"
        else:
            ref_code = _XHTML_CODE.search(ref_text)
            ours_code = _XHTML_CODE.search(text)
            assert ref_code and ours_code, text
            assert ours_code.group(1) == ref_code.group(1)
            assert ("<title>rw</title>" in text) == ("<title>rw</title>" in ref_text) == (profile == "rws1")

    run(profile, body)


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_unknown_resources_and_wrong_methods_get_the_error_envelope(profile: str) -> None:
    async def body(s: Sim) -> None:
        status, headers, text = await s.raw("GET", "/rw/no/such/resource")
        assert status == 404 and headers["Content-Type"] == CTYPE[(profile, True)]
        st = json.loads(text)["_embedded"]["status"] if profile == "rws1" else json.loads(text)["status"]
        assert st["code"] == -1073414146
        status, _, text = await s.raw("DELETE", "/rw/panel/opmode")
        assert status == 405 and "DELETE" in text
        if profile == "rws1":  # an action the resource does not have
            status, _, text = await s.raw("POST", "/rw/rapid/execution?action=jump", data="")
            assert status == 400 and json.loads(text)["_embedded"]["status"]["code"] == -1073445879

    run(profile, body)


# ---- cookies, subscriptions, websocket --------------------------------------------------------


def _cookie_attrs(line: str) -> tuple[str, str, set[str]]:
    name_value, *attrs = [p.strip() for p in line.split(";")]
    name, _, value = name_value.partition("=")
    return name, value.strip('"'), {a.split("=")[0].lower() for a in attrs if a}


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_login_sets_the_controllers_two_cookies_in_their_captured_form(profile: str) -> None:
    if profile == "rws1":  # the cookie jar rendering of an IRC5's Set-Cookie
        lines = [
            ln.removeprefix("Set-Cookie3: ")
            for ln in _text("headers/rws1_irc5_cookies_lwp_cookiejar_zwj12.txt").splitlines()[1:]
        ]
    else:
        lines = [
            ln.removeprefix("Set-Cookie: ")
            for ln in _text("headers/rws2_set_cookie_pair.from_fpc_test.txt").splitlines()
        ]
    captured = {n: (v, a) for n, v, a in map(_cookie_attrs, lines)}
    assert set(captured) == {"-http-session-", "ABBCX"}

    async def body(s: Sim) -> None:
        async with aiohttp.ClientSession() as http:
            url = s.server.base_url + ("/rw/panel/opmode?json=1" if profile == "rws1" else "/rw/panel/opmode")
            async with http.get(url, ssl=False) as r401:
                assert r401.status == 401
            c = RwsClient(RwsClientConfig(base_url=s.server.base_url, profile=profile))  # type: ignore[arg-type]
            try:
                trace: list[str] = []

                async def on_end(_session, _ctx, params) -> None:
                    trace.extend(params.response.headers.getall("Set-Cookie", []))

                tc = aiohttp.TraceConfig()
                tc.on_request_end.append(on_end)
                c._session()._trace_configs.append(tc)  # type: ignore[attr-defined]
                tc.freeze()
                await c.get_opmode()
            finally:
                await c.close()
        ours: dict[str, tuple[str, set[str]]] = {}
        for n, v, a in map(_cookie_attrs, trace):  # the login's; logout's deletions come after
            ours.setdefault(n, (v, a))
        assert set(ours) == set(captured)
        assert re.fullmatch(r"\d+::http\.session::[0-9a-f]{32}", ours["-http-session-"][0])
        assert re.fullmatch(r"\d+::http\.session::[0-9a-f]{32}", captured["-http-session-"][0])
        assert ours["ABBCX"][0].isdigit() and captured["ABBCX"][0].isdigit()
        for name in ours:
            assert "path" in ours[name][1] and "httponly" in ours[name][1]
            if profile == "rws2":
                assert {"secure", "samesite"} <= ours[name][1] and {"secure", "samesite"} <= captured[name][1]

    run(profile, body)


@pytest.mark.parametrize("profile", ["rws1", "rws2"])
def test_subscription_answers_201_xhtml_with_location_and_serves_events_on_the_profiles_subprotocol(
    profile: str,
) -> None:
    ref = _text("rws1/doc_post_subscription_execution_201.xml")
    event_ref = _text("rws1/doc_ws_event_rapid_task_syncstate.xml")
    proto = {"rws1": "robapi2_subscription", "rws2": "rws_subscription"}[profile]

    async def body(s: Sim) -> None:
        form = "resources=1&1=%2Frw%2Fpanel%2Fctrlstate&1-p=1&resources=2&2=%2Frw%2Frapid%2Fexecution%3Bctrlexecstate&2-p=1"
        status, headers, text = await s.raw("POST", "/subscription", data=form)  # JSON asked: XHTML answered
        assert status == 201 and headers["Content-Type"] == CTYPE[(profile, False)]
        scheme = "wss" if profile == "rws2" else "ws"
        m = re.search(
            rf'<a href="({scheme}://[^"]+/poll/(\d+))" rel="self"></a>', text
        )  # abb-robot-client's regex form
        assert m and headers["Location"] == m.group(1)
        for rel in ("group", "action"):  # the manual's page has these links too
            assert f'rel="{rel}"' in ref and re.search(
                rf'<a href="subscription/{m.group(2)}[^"]*" rel="{rel}">', text
            )
        assert parse_event_xhtml(text) == [
            StateChange("ctrlstate", "ctrlstate", "motoroff"),
            StateChange("execution", "ctrlexecstate", "stopped"),
        ]
        http = s.client._session()
        async with http.ws_connect(m.group(1), protocols=("other",), ssl=False) as bad:
            msg = await bad.receive(timeout=5)
            assert msg.type == aiohttp.WSMsgType.CLOSE and msg.data == 1002
        async with http.ws_connect(m.group(1), protocols=(proto,), ssl=False) as ws:
            assert ws.protocol == proto
            s.model.motors_on()
            msg = await ws.receive(timeout=5)
            assert msg.type == aiohttp.WSMsgType.TEXT
            frame = msg.data
        assert parse_event_xhtml(frame) == [StateChange("ctrlstate", "ctrlstate", "motoron")]
        for rel in ("group", "self", "action"):  # the frame has the manual's event-page links
            assert f'rel="{rel}"' in event_ref and f'rel="{rel}"' in frame
        assert (
            '<li class="pnl-ctrlstate-ev" title="ctrlstate"><a href="/rw/panel/ctrlstate" rel="self"/>'
            in frame
        )
        status, _, _ = await s.raw("DELETE", f"/subscription/{m.group(2)}")
        assert status == 204

    run(profile, body)
