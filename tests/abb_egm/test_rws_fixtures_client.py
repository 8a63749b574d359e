"""The RWS client against the captured controller answers of ../shared/testdata/rws (see its SOURCES.md).

A loopback server answers each request with one fixture body, its status and Content-Type; the
client's public calls must give the values a person reads off the file, and every error body (both
profiles, JSON and XHTML) the typed error with the controller's status, code and message.
"""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from aiohttp import web

from drivers.abb_egm.rws_client import (
    ElogEntry,
    ExecutionState,
    RwsClient,
    RwsClientConfig,
    RwsError,
    RwsProtocolError,
    StateChange,
    TaskState,
    _states,
    parse_event_xhtml,
    parse_xhtml,
    subscription_ws_url,
)
from tests.conftest import SHARED

FIX = SHARED / "testdata" / "rws"
JSON1, XHTML1 = "application/json", "application/xhtml+xml"
JSON2, XHTML2 = "application/hal+json;v=2.0", "application/xhtml+xml;v=2.0"


def _text(rel: str) -> str:
    return (FIX / rel).read_text(encoding="utf-8")


class FixtureServer:
    """Answers ``answers[path]`` = (status, Content-Type, body) and records the requests (path + query)."""

    def __init__(self, answers: dict[str, tuple[int, str, str]]) -> None:
        self.answers = answers
        self.requests: list[str] = []

    async def _handle(self, request: web.Request) -> web.Response:
        self.requests.append(request.path_qs)
        await request.read()
        key = request.path_qs if request.path_qs in self.answers else request.path
        status, ctype, body = self.answers.get(key, (404, "text/plain", "no fixture for this path"))
        return web.Response(status=status, body=body.encode(), headers={"Content-Type": ctype})

    async def __aenter__(self) -> str:
        app = web.Application()
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self.runner = web.AppRunner(app, access_log=None)
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", 0)
        await site.start()
        return f"http://127.0.0.1:{site._server.sockets[0].getsockname()[1]}"  # type: ignore[union-attr]

    async def __aexit__(self, *exc: object) -> None:
        await self.runner.cleanup()


def _call(profile: str, answers: dict[str, tuple[int, str, str]], fn: Callable[[RwsClient], object]):
    async def main():
        srv = FixtureServer(answers)
        async with srv as base:
            client = RwsClient(RwsClientConfig(base_url=base, profile=profile, timeout_s=5.0))  # type: ignore[arg-type]
            try:
                return await fn(client), srv.requests  # type: ignore[misc]
            finally:
                client._logged_in = False  # the fixture server has no logout to answer
                await client.close()

    return asyncio.run(asyncio.wait_for(main(), 20))


# ---- success bodies ---------------------------------------------------------------------------

TASK_DOC = TaskState("T_ROB1", "norm", "link", "read", True, True)
# (profile, fixture, Content-Type, request path, client call, expected value)
SUCCESS = [
    ("rws1", "rws1/doc_get_panel_ctrlstate.xml", XHTML1, "/rw/panel/ctrlstate", lambda c: c.get_ctrl_state(), "motoron"),
    ("rws1", "rws1/doc_get_panel_opmode.xml", XHTML1, "/rw/panel/opmode", lambda c: c.get_opmode(), "MANR"),
    ("rws1", "rws1/doc_get_rapid_execution.xml", XHTML1, "/rw/rapid/execution",
     lambda c: c.get_execution_state(), ExecutionState("stopped", "forever")),
    ("rws1", "rws1/zwj12_get_rapid_execution_json1.REFORMATTED.json", JSON1, "/rw/rapid/execution",
     lambda c: c.get_execution_state(), ExecutionState("stopped", "forever")),
    ("rws1", "rws1/doc_get_rapid_tasks.xml", XHTML1, "/rw/rapid/tasks", lambda c: c.get_tasks(),
     [TASK_DOC, TaskState("T_ROB2", "norm", "link", "read", True, True)]),
    ("rws1", "rws1/doc_get_rapid_tasks_T_ROB1.xml", XHTML1, "/rw/rapid/tasks/T_ROB1", lambda c: c.get_task("T_ROB1"),
     TaskState("T_ROB1", "norm", "linked", "ready", True, True)),
    ("rws1", "rws1/doc_get_ios_signal_Local_DRV_1_DRV1CHAIN2.xml", XHTML1, "/rw/iosystem/signals/Local/DRV_1/DRV1CHAIN2",
     lambda c: c.get_io("DRV1CHAIN2", "Local", "DRV_1"), 0.0),
    ("rws1", "rws1/doc_get_elog_0_8_message.xml", XHTML1, "/rw/elog/0/8", lambda c: c.read_event(0, 8),
     ElogEntry(8, 2, 20573, "", "", "2013-09-08 T 11:22:10", args=("EIO", "6.0"))),
    ("rws2", "rws2/ichbinmeraj_get_panel_ctrl-state.json", JSON2, "/rw/panel/ctrl-state",
     lambda c: c.get_ctrl_state(), "motoroff"),
    ("rws2", "rws2/ichbinmeraj_get_rapid_tasks.json", JSON2, "/rw/rapid/tasks", lambda c: c.get_tasks(),
     [TaskState("T_ROB1", "normal", "linked", "ready", True, True)]),
    ("rws2", "rws2/ichbinmeraj_get_rapid_tasks_T_ROB1_modules.json", JSON2, "/rw/rapid/tasks/T_ROB1/modules",
     lambda c: c.get_modules("T_ROB1"), [("BASE", "SysMod"), ("MainModule", "ProgMod")]),
    ("rws2", "rws2/blueicaro_get_elog_0_95_lang_en.json", JSON2, "/rw/elog/0/95", lambda c: c.read_event(0, 95),
     ElogEntry(95, 1, 10126, "Program stopped",
               "The task T_ROB1 has stopped. The reason is that an error has occurred.",
               "2024-01-10 T 14:53:00", args=("1", "T_ROB1"))),
    ("rws2", "rws2/blueicaro_get_elog_1_84_lang_en.REFORMATTED.json", JSON2, "/rw/elog/1/84",
     lambda c: c.read_event(1, 84),
     ElogEntry(84, 1, 10017, "Automatic mode confirmed", "The system is in the Automatic mode.",
               "2024-01-10 T 11:55:16",
               conseqs="The enabling device is disconnected. The robot can move without human intervention.")),
    ("rws2", "rws2/blueicaro_get_elog_domains.json", JSON2, "/rw/elog", lambda c: c.read_event_log_domains(),
     {0: 66, 1: 50, 2: 0, 3: 0, 4: 0, 5: 0, 7: 8, 8: 0, 9: 0, 10: 0, 11: 0, 12: 0, 15: 0, 17: 0}),
]  # fmt: skip


@pytest.mark.parametrize(
    ("profile", "fixture", "ctype", "path", "call", "expected"), SUCCESS, ids=[s[1] for s in SUCCESS]
)
def test_client_reads_the_values_of_each_captured_answer(
    profile, fixture, ctype, path, call, expected
) -> None:
    value, requests = _call(profile, {path: (200, ctype, _text(fixture))}, call)
    assert value == expected
    assert requests[0].split("?")[0] == path


@pytest.mark.parametrize(
    ("profile", "fixture", "ctype", "joints"),
    [
        ("rws1", "rws1/doc_get_ms_mechunits_ROB_1_jointtarget.xml", XHTML1, np.zeros(6)),
        (
            "rws2",
            "rws2/ichbinmeraj_get_ms_mechunits_ROB_1_jointtarget.json",
            JSON2,
            [10, 15, -10, 20, 30, 45],
        ),
    ],
    ids=["rws1-doc", "rws2-ichbinmeraj"],
)
def test_client_reads_the_joint_target_of_the_captured_answers(profile, fixture, ctype, joints) -> None:
    path = "/rw/motionsystem/mechunits/ROB_1/jointtarget"
    q, _ = _call(profile, {path: (200, ctype, _text(fixture))}, lambda c: c.get_joint_position())
    np.testing.assert_array_equal(q, joints)
    # both answers print 0 (not 9E9) in eax_a..eax_f: a 0 is a value, not "unused"
    mj, _ = _call(profile, {path: (200, ctype, _text(fixture))}, lambda c: c.get_mechunit_joints())
    np.testing.assert_array_equal(mj.q_deg, joints)
    assert mj.external_axes_mm == (0.0,) * 6


def test_client_reads_the_robot_target_of_the_manual() -> None:
    path = "/rw/motionsystem/mechunits/ROB_1/robtarget"
    body = _text("rws1/doc_get_ms_mechunits_ROB_1_robtarget.xml")
    pose, requests = _call("rws1", {path: (200, XHTML1, body)}, lambda c: c.get_cartesian())
    np.testing.assert_array_equal(pose.pos_mm, [515, 0, 712])
    np.testing.assert_array_equal(pose.quat_wxyz, [0.7071068, 0, 0.7071068, 0])
    assert "coordinate=Base" in requests[0] and "tool=tool0" in requests[0]
    # the manual prints an unused external axis as 8.999999e+009: RAPID's 9E9, so None
    assert pose.external_axes_mm == (None,) * 6


@pytest.mark.parametrize(
    ("printed", "value"),
    [("9E+09", None), ("8.999999e+009", None), ("8999999488", None), ("-9E+09", None),
     ("0", 0.0), ("1250.5", 1250.5), ("-350", -350.0)],
)  # fmt: skip
def test_client_reads_an_external_axis_as_its_value_or_none_for_9e9(printed, value) -> None:
    """9E9 as RWS prints it (the simulator, ABB's manual, and 9E9 stored as a 32-bit RAPID num)."""
    path = "/rw/motionsystem/mechunits/ROB_1/jointtarget"
    body = _text("rws2/ichbinmeraj_get_ms_mechunits_ROB_1_jointtarget.json").replace(
        '"eax_a" : "0"', f'"eax_a" : "{printed}"'
    )
    assert f'"eax_a" : "{printed}"' in body
    mj, _ = _call("rws2", {path: (200, JSON2, body)}, lambda c: c.get_mechunit_joints())
    assert mj.external_axes_mm == (value, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_client_lists_the_signals_of_the_robotware_7_answer() -> None:
    body = _text("rws2/blueicaro_get_iosystem_signals.json")
    signals, _ = _call("rws2", {"/rw/iosystem/signals": (200, JSON2, body)}, lambda c: c.list_signals())
    assert len(signals) == body.count('"ios-signal-li"') > 3
    first = signals[0]
    assert (first.name, first.path, first.type, first.lvalue) == (
        "SafetyEnable", "SC_Feedback_Net/SC_Feedback_Dev/SafetyEnable", "DI", 1.0,
    )  # fmt: skip
    assert [(s.name, s.lvalue) for s in signals[1:3]] == [("ProtectiveStop", 1.0), ("ManualMode", 0.0)]


def test_client_follows_the_xml_escaped_next_link_of_a_signal_page() -> None:
    """RobotWare 7 writes ``signals?start=3&amp;limit=3`` inside its JSON: the client asks for
    ``start=3&limit=3`` (page 2 below is this test's own, an empty last page)."""
    page1 = _text("rws2/ichbinmeraj_get_iosystem_signals_paged.PARTIAL.json")
    page2 = json.dumps(
        {"_links": {"base": {"href": "https://127.0.0.1:5466/rw/iosystem/"}}, "_embedded": {"resources": []}}
    )
    answers = {
        "/rw/iosystem/signals": (200, JSON2, page1),
        "/rw/iosystem/signals?start=3&limit=3": (200, JSON2, page2),
    }
    signals, requests = _call("rws2", answers, lambda c: c.list_signals())
    assert [s.name for s in signals] == ["doGripper", "diSensor"]
    assert requests == ["/rw/iosystem/signals", "/rw/iosystem/signals?start=3&limit=3"]


@pytest.mark.parametrize(
    ("fixture", "item"),
    [
        ("rws2/blueicaro_get_rapid_aliasio_empty_state.json", None),
        ("rws2/blueicaro_get_rapid_symbols_status_only.json", None),
        (
            "rws2/blueicaro_get_iosystem_networks_SC_Feedback_Net.json",
            {"name": "SC_Feedback_Net", "lstate": "started"},
        ),
        (
            "rws2/blueicaro_get_rapid_tasks_t_rob1_execution_lowercase.json",
            {"module": "ModuloMain", "routine": "Main"},
        ),
    ],
)
def test_client_finds_the_state_items_of_other_robotware_7_answers(fixture: str, item: dict | None) -> None:
    items = _states(json.loads(_text(fixture)))
    if item is None:
        assert items == []
    else:
        assert len(items) == 1 and item.items() <= items[0].items()


@pytest.mark.parametrize(
    ("fixture", "titles"),
    [
        ("rws2/blueicaro_get_root_xhtml_v2_a.xml", ["ctrl", "fileservice", "progress", "rw", "subscription", "uas", "users"]),
        ("rws2/blueicaro_get_root_xhtml_v2_b.xml", ["ctrl", "rw", "progress", "fileservice", "users", "subscription", "uas"]),
        ("rws2/blueicaro_post_unknown_xhtml_v2_empty_state.xml", []),
    ],
)  # fmt: skip
def test_client_parses_robotware_7_xhtml_pages(fixture: str, titles: list[str]) -> None:
    page = parse_xhtml(_text(fixture))
    assert [it["_title"] for it in _states(page)] == titles
    assert page["_links"]["base"]["href"] == "https://localhost:80/"


# ---- subscription answers and events ----------------------------------------------------------

EVENTS = [
    ("rws1/doc_post_subscription_ctrlstate_201.xml", [StateChange("ctrlstate", "ctrlstate", "motoroff")], None),
    ("rws1/doc_post_subscription_execution_201.xml", [StateChange("execution", "ctrlexecstate", "stopped")],
     "ws://localhost/poll/4"),
    ("rws1/doc_post_subscription_persvar_201.xml", [StateChange("rapid-data", "PNum", "4")],
     "ws://127.0.0.1:9696/poll/9"),
    ("rws1/doc_post_subscription_elog_201.xml", [StateChange("elog", "15", "")], "ws://localhost/poll/1"),
    ("rws1/doc_post_subscription_signals_201.xml",
     [StateChange("signal", "di1", "0"), StateChange("signal", "di2", "0")], None),
    ("rws1/doc_post_subscription_coldetstate_201.xml", [], "ws://localhost:80/poll/1"),
    ("rws1/doc_post_subscription_syncstate_201_no_initial.xml", [], "ws://localhost/poll/4"),
    ("rws1/doc_ws_event_rapid_task_syncstate.xml", [], "ws://localhost/poll/4"),
    ("rws1/doc_ws_event_rapid_motionpointer.xml", [], "ws://localhost/poll/4"),
    ("rws2/blueicaro_ws_event_ios_signalstate.PROVENANCE_UNCLEAR.xml", [StateChange("signal", "do0", "0")],
     "wss://localhost:80/poll/9"),
]  # fmt: skip


@pytest.mark.parametrize(("fixture", "changes", "ws_url"), EVENTS, ids=[e[0] for e in EVENTS])
def test_client_reads_the_values_and_websocket_of_each_subscription_page(fixture, changes, ws_url) -> None:
    body = _text(fixture)
    assert parse_event_xhtml(body) == changes
    if ws_url is None:  # these pages of the manual name no websocket: the Location header must
        with pytest.raises(RwsProtocolError):
            subscription_ws_url({}, body)
        assert subscription_ws_url({"Location": "ws://h/poll/3"}, body) == "ws://h/poll/3"
    else:
        assert subscription_ws_url({}, body) == ws_url


# ---- error bodies -----------------------------------------------------------------------------

# (fixture, HTTP status and Content-Type as recorded in SOURCES.md, code and message start off the file)
ERRORS = [
    ("rws1/doc_error_400_rapid_symbol_set_no_mastership.xml", 400, XHTML1, -1073414146, "rws_resource_rapid_symbol_data.cpp[534]"),
    ("rws1/errors/ichbinmeraj_400-cfg-write-invalid-json.json", 400, JSON1, -1073445879, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_400-cfg-write-invalid-xhtml.xml", 400, XHTML1, -1073445879, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_400-exec-start-wrong-state-json.json", 400, JSON1, -1073442809, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_400-jog-invalid-input-json.json", 400, JSON1, -1073445879, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_400-loadmod-missing-path.xml", 400, XHTML1, -1073438708, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_400-unload-unknown-module.xml", 400, XHTML1, -1073442816, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_403-mastership-held-json.json", 403, JSON1, -1073445862, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_403-mastership-held-xhtml.xml", 403, XHTML1, -1073445862, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_403-signal-write-no-rmmp-json.json", 403, JSON1, -1073445881, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_404-file.xml", 404, XHTML1, -1073414146, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_404-module-json.json", 404, JSON1, -1073414146, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_404-module-xhtml.xml", 404, XHTML1, -1073414146, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_404-signal-json.json", 404, JSON1, -1073445866, "C:\\BUILDAGENTS"),
    ("rws1/errors/ichbinmeraj_404-symbol-json.json", 400, JSON1, -1073414146, "C:\\BUILDAGENTS"),
    ("rws2/ichbinmeraj_error_task_not_found.json", 400, JSON2, -1073445879, "rws_resource_rapid_task.cpp[620]"),
    ("rws2/errors/ichbinmeraj_400-bad-volume-haljson.json", 400, JSON2, -1073438716, "rapi_file_service.cpp[237]"),
    ("rws2/errors/ichbinmeraj_400-bad-volume-xhtml.xml", 400, XHTML2, -1073438716, "rapi_file_service.cpp[237]"),
    ("rws2/errors/ichbinmeraj_400-module-missing-haljson.json", 400, JSON2, -1073442813, "rws_resource_rapid_module.cpp[1233]"),
    ("rws2/errors/ichbinmeraj_400-module-missing-xhtml.xml", 400, XHTML2, -1073442813, "rws_resource_rapid_module.cpp[1233]"),
    ("rws2/errors/ichbinmeraj_403-exec-start-blocked-haljson.json", 403, JSON2, -1073445862, "rws_resource_rapid_execution.cpp[1543]"),
    ("rws2/errors/ichbinmeraj_403-mastership-held-haljson.json", 403, JSON2, -1073445862, "rws_resource_mastership.cpp[593]"),
    ("rws2/errors/ichbinmeraj_403-mastership-held-xhtml.xml", 403, XHTML2, -1073445862, "rws_resource_mastership.cpp[593]"),
    ("rws2/errors/ichbinmeraj_403-signal-write-no-rmmp-haljson.json", 403, JSON2, -1073445881, "rws_resource_iosystem.cpp[3156]"),
    ("rws2/errors/ichbinmeraj_403-speedratio-no-mastership-haljson.json", 403, JSON2, -1073445859, "rws_resource_panel.cpp[1688]"),
    ("rws2/errors/ichbinmeraj_403-speedratio-no-mastership-xhtml.xml", 403, XHTML2, -1073445859, "rws_resource_panel.cpp[1688]"),
    ("rws2/errors/ichbinmeraj_403-uas-not-allowed-haljson.json", 403, JSON2, -1073445867, "rapi_uas_resource.cpp[2995]"),
    ("rws2/errors/ichbinmeraj_404-file-haljson.json", 404, "text/html", -1073438713, "rapi_file_service.cpp[218]"),
    ("rws2/errors/ichbinmeraj_404-signal-haljson.json", 404, JSON2, -1073445866, "rws_resource_iosystem.cpp[2500]"),
    ("rws2/errors/ichbinmeraj_404-symbol-overloaded-code-haljson.json", 404, JSON2, -1073442816, "rws_resource_rapid_symbol_data.cpp[254]"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("fixture", "status", "ctype", "code", "msg_start"), ERRORS, ids=[e[0] for e in ERRORS]
)
def test_client_turns_each_captured_error_body_into_an_rws_error_with_the_controllers_code(
    fixture: str, status: int, ctype: str, code: int, msg_start: str
) -> None:
    profile = fixture.split("/")[0]
    body = _text(fixture)
    with pytest.raises(RwsError) as err:
        _call(profile, {"/rw/rapid/execution": (status, ctype, body)}, lambda c: c.get_execution_state())
    e = err.value
    assert (e.status, e.code) == (status, code)
    assert e.message.startswith(msg_start)
    # the whole message as the file has it (JSON unescaped, XHTML text)
    file_msg = re.search(r'"msg"\s*:\s*"((?:[^"\\]|\\.)*)"|<span class="msg">([^<]*)<', body)
    assert file_msg is not None
    expected = json.loads(f'"{file_msg.group(1)}"') if file_msg.group(1) is not None else file_msg.group(2)
    assert e.message == expected


def test_every_complete_fixture_is_used_by_a_client_or_simulator_test() -> None:
    """A fixture added to ../shared/testdata/rws must get a test (partial ones are listed apart)."""
    here = Path(__file__).parent
    used_text = "".join(p.read_text() for p in here.glob("test_rws_*.py"))
    files = [
        p.relative_to(FIX).as_posix()
        for p in FIX.rglob("*")
        if p.is_file() and p.suffix in (".xml", ".json", ".txt")
    ]
    unused = [f for f in files if Path(f).name not in used_text and "PARTIAL" not in f]
    assert unused == []
