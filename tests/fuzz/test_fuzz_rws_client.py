"""Fuzz the RWS client (drivers/abb_egm/rws_client.py) with an aiohttp server of our own on loopback.

The server answers every request with what the example dictates: a status code, headers
(content types and charsets, digest challenges) and a body mutated from a valid RWS answer. Every
client call either returns a value or raises an ``RwsError`` subclass; never KeyError, TypeError,
UnicodeDecodeError and the like.
"""

from __future__ import annotations

import asyncio
import json
import threading

import pytest
from aiohttp import web
from fuzzlib import fuzz_settings, mutated
from hypothesis import example, given
from hypothesis import strategies as st

from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig, RwsError
from tests.conftest import SHARED


def _state(**item) -> bytes:
    return json.dumps({"_links": {}, "_embedded": {"_state": [dict(item, _type="x", _title="t")]}}).encode()


VALID_BODIES = (
    _state(ctrlstate="motoron"),
    _state(opmode="AUTO"),
    _state(ctrlexecstate="running", cycle="once"),
    _state(value="42.5"),
    _state(value="TRUE"),
    _state(value="[[0,0,0,0,30,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]"),
    _state(lvalue="1"),
    _state(seqnum="12", msgtype="1", code="10012", title="Motors on", desc="", tstamp="2024"),
    _state(**{f"rax_{i}": str(i * 1.5) for i in range(1, 7)}),
    _state(x="1", y="2", z="3", q1="1", q2="0", q3="0", q4="0"),
    json.dumps({"status": {"code": -1073442813, "msg": "Access denied"}}).encode(),
    b"",
    # captured controller answers (../shared/testdata/rws): both error shapes, XHTML pages
    *(
        (SHARED / "testdata/rws" / rel).read_bytes()
        for rel in (
            "rws1/errors/ichbinmeraj_400-exec-start-wrong-state-json.json",
            "rws1/errors/ichbinmeraj_404-module-xhtml.xml",
            "rws2/errors/ichbinmeraj_403-mastership-held-haljson.json",
            "rws1/doc_get_rapid_tasks.xml",
            "rws1/doc_post_subscription_persvar_201.xml",
            "rws2/blueicaro_get_elog_0_95_lang_en.json",
            "rws2/ichbinmeraj_get_iosystem_signals_paged.PARTIAL.json",
        )
    ),
)
CALLS = {
    "ctrl_state": lambda c: c.get_ctrl_state(),
    "opmode": lambda c: c.get_opmode(),
    "execution": lambda c: c.get_execution_state(),
    "num": lambda c: c.get_rapid_num("T_ROB1", "n", "CellEgm"),
    "bool": lambda c: c.get_rapid_bool("T_ROB1", "b"),
    "string": lambda c: c.get_rapid_string("T_ROB1", "s"),
    "jointtarget": lambda c: c.get_rapid_jointtarget("T_ROB1", "jt"),
    "io": lambda c: c.get_io("DO1"),
    "elog": lambda c: c.read_event_log(),
    "joints": lambda c: c.get_joint_position(),
    "cartesian": lambda c: c.get_cartesian(),
    "motors_on": lambda c: c.motors_on(),
    "set_bool": lambda c: c.set_rapid_bool("T_ROB1", "b", True),
    "start": lambda c: c.start_rapid(),
    "tasks": lambda c: c.get_tasks(),
    "signals": lambda c: c.list_signals(),
    "event": lambda c: c.read_event(0, 1),
}
CONTENT_TYPES = (
    "application/json",
    "application/hal+json;v=2.0",
    "application/json; charset=utf-8",
    "application/json; charset=bogus-8",
    "application/json; charset=utf-16",
    "text/html",
    "application/xhtml+xml",
    "application/xhtml+xml;v=2.0",
    "",
)
CHALLENGES = (
    'Digest realm="validusers@robapi.abb", nonce="abc", qop="auth", opaque="xyz"',
    'Digest realm="r", nonce="n", qop="auth-int"',
    'Digest realm="r", nonce="n", algorithm=SHA-256',
    "Basic realm=x",
    "Digest",
    "",
)


class Server:
    """An aiohttp server on a loop in a background thread; ``answer`` is what the next requests get."""

    def __init__(self) -> None:
        self.answer: tuple[int, dict[str, str], bytes] = (200, {}, b"")
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.port = self.run(self._start())

    def run(self, coro, timeout_s: float = 30.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        status, headers, body = self.answer
        await request.read()
        return web.Response(status=status, headers=headers, body=body)

    async def _start(self) -> int:
        app = web.Application()
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self.runner = web.AppRunner(app, access_log=None)
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", 0)
        await site.start()
        return site._server.sockets[0].getsockname()[1]

    def close(self) -> None:
        self.run(self.runner.cleanup())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


@pytest.fixture(scope="module")
def server():
    s = Server()
    try:
        yield s
    finally:
        s.close()


async def _call(port: int, profile: str, name: str):
    base = f"http://127.0.0.1:{port}"
    cfg = RwsClientConfig(base_url=base, profile=profile, password="pw", timeout_s=2.0, poll_interval_s=0.05)
    async with RwsClient(cfg) as client:
        return await CALLS[name](client)


@st.composite
def _answer(draw: st.DrawFn) -> tuple[int, dict[str, str], bytes]:
    status = draw(st.sampled_from([200, 201, 204, 400, 401, 403, 404, 409, 500, 503]) | st.integers(200, 599))
    headers = {}
    ctype = draw(st.sampled_from(CONTENT_TYPES))
    if ctype:
        headers["Content-Type"] = ctype
    if status == 401:
        headers["WWW-Authenticate"] = draw(
            st.sampled_from(CHALLENGES) | st.text(max_size=60).filter(str.isprintable)
        )
    body = draw(
        st.sampled_from(VALID_BODIES).flatmap(lambda b: mutated(b, VALID_BODIES))
        | st.sampled_from(VALID_BODIES)
    )
    return status, headers, body


@fuzz_settings(120)
@given(answer=_answer(), profile=st.sampled_from(["rws1", "rws2"]), name=st.sampled_from(sorted(CALLS)))
# found by fuzzing: these escaped as KeyError, ValueError (RapidValueError), UnicodeDecodeError, LookupError
@example(
    answer=(200, {"Content-Type": "application/json"}, _state(other="x")), profile="rws1", name="ctrl_state"
)
@example(answer=(200, {"Content-Type": "application/json"}, _state(value="abc")), profile="rws1", name="num")
@example(answer=(200, {"Content-Type": "application/json"}, _state(seqnum="x")), profile="rws1", name="elog")
@example(
    answer=(200, {"Content-Type": "application/json; charset=utf-8"}, b'{"a": "\xff"}'),
    profile="rws2",
    name="opmode",
)
@example(
    answer=(200, {"Content-Type": "application/json; charset=bogus-8"}, b"{}"), profile="rws2", name="opmode"
)
@example(
    answer=(200, {"Content-Type": "application/json"}, b'{"_embedded": {"_state": [1]}}'),
    profile="rws1",
    name="io",
)
def test_rws_client_answers_any_response_with_a_value_or_an_rws_error(server, answer, profile, name):
    server.answer = answer
    try:
        asyncio.run(asyncio.wait_for(_call(server.port, profile, name), 20))
    except RwsError as err:
        assert str(err)
