"""Every route of the HMI and its websocket, fuzzed (issue 44, item 2).

Raw HTTP requests (any method, path, id, header and body bytes) against one HMI server in this
process (tests/support/hmi_server.py: no cell). Whatever arrives: no 500, nothing written under the
HMI's directories, nothing of what the client sent (cookie, session token, password) in the log and
no unhandled exception there. Websockets: any message leaves the server serving; a socket closes
when its session ends or expires; a foreign ``Origin`` is refused.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from cellctl.hmi.server import COOKIE, LOGIN_MAX_BYTES
from tests.fuzz.fuzzlib import fuzz_settings, mutated
from tests.support.hmi_server import USERS, LocalHmi
from tests.support.waits import wait_until_sync

JOB = "20261201T100000-abcd1234"
CANARY = "canary-Pa55word-"  # in every password the fuzzer sends: must never reach the log


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def hmi(tmp_path_factory) -> Iterator[LocalHmi]:
    root = tmp_path_factory.mktemp("hmi-fuzz")
    d = root / "data" / "jobs" / JOB
    (d / "results").mkdir(parents=True)
    rec = {"job_id": JOB, "plate_id": "P1", "design": "p.ply", "design_path": "/srv/p.ply", "placement": None, "state": "done", "created_utc": "2026-12-01T10:00:00Z",
           "history": [{"state": "done", "t_utc": "2026-12-01T10:01:00Z", "message": "done"}], "info": {}}  # fmt: skip
    (d / "job.json").write_text(json.dumps(rec))
    (d / "results" / "report.csv").write_text("line,zmax\nT1,1.0\n")
    with LocalHmi(root) as h:
        yield h


class Client:
    """A logged-in operator's cookie and CSRF token (logged in again when a case logged it out)."""

    def __init__(self, hmi: LocalHmi) -> None:
        self.hmi = hmi
        self.token = ""
        self.csrf = ""
        self.tokens: set[str] = set()

    def fresh(self) -> Client:
        if self.hmi.auth.session(self.token) is None:
            s = self.hmi.auth.login("olga", USERS["olga"][1])
            assert s is not None
            self.token, self.csrf = s.token, s.csrf
            self.tokens.add(s.token)
        return self


@pytest.fixture(scope="module")
def client(hmi: LocalHmi) -> Client:
    return Client(hmi)


async def _raw(port: int, request: bytes, timeout_s: float = 20.0) -> tuple[int, bytes]:
    """Send ``request`` as it is; the status and body of the answer (0: the server closed first)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request)
        await writer.drain()
        data = await asyncio.wait_for(reader.read(), timeout_s)
    finally:
        writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    parts = head.split(b" ", 2)
    return (int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0), body


def _request(method: str, path: bytes, headers: list[tuple[bytes, bytes]], body: bytes) -> bytes:
    lines = [method.encode() + b" " + path + b" HTTP/1.1", b"Host: 127.0.0.1", b"Connection: close"]
    lines += [k + b": " + v for k, v in headers]
    if body or method in ("POST", "PUT", "PATCH"):
        lines.append(b"Content-Length: " + str(len(body)).encode())
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


ROUTES = [
    ("GET", "/"),
    ("GET", "/static/{id}"),
    ("POST", "/api/login"),
    ("POST", "/api/logout"),
    ("GET", "/api/me"),
    ("GET", "/api/status"),
    ("GET", "/api/designs"),
    ("GET", "/api/designs/preview?path={id}"),
    ("POST", "/api/trigger"),
    ("POST", "/api/control/{id}"),
    ("GET", "/api/jobs?plate={id}&verdict={id}&date={id}"),
    ("GET", "/api/jobs/{id}"),
    ("GET", "/api/jobs/{id}/map"),
    ("GET", "/api/jobs/{id}/live"),
    ("GET", "/api/jobs/{id}/files/{id}"),
    ("GET", "/api/plates/{id}/rounds"),
    ("GET", "/ws"),
]
ODD_IDS = [
    ".", "..", "%2e%2e", "%2E.", ".%2e", "...", "a/..", "..%2f..", "%2e%2e%2fetc", "%00", "%ff%fe", "pause",
    "abort", "reset", JOB, "report.csv", "cloud.bin", "-x", "x" * 300, "%25", "app.js", "../hmi-users",
    "..%5c..", "%c0%ae%c0%ae", "~", "P1", "2026-12-01", "fail",
]  # fmt: skip
ids = st.one_of(
    st.sampled_from(ODD_IDS),
    st.text(min_size=0, max_size=40).map(lambda t: "".join(f"%{b:02x}" for b in t.encode())),
    st.from_regex(r"[A-Za-z0-9_.~%-]{0,30}", fullmatch=True),
)
VALID_BODIES = (
    json.dumps({"user": "olga", "password": CANARY + "1"}).encode(),
    json.dumps({"plate_id": "P1", "design": "p.ply", "placement": {"pos_mm": [1500, 0, 300]}}).encode(),
    json.dumps({"job_id": JOB}).encode(),
    b"{}",
)
bodies = st.one_of(
    st.sampled_from(VALID_BODIES),
    st.sampled_from(VALID_BODIES).flatmap(lambda v: mutated(v, VALID_BODIES)),
    st.integers(1, 4000).map(lambda n: b"[" * n),
    st.integers(1, 2000).map(lambda n: b'{"a":' * n),
    st.just(b"\xff\xfe\xfd"),
    st.just(b'{"user": "' + b"u" * 70 + b'", "password": "' + CANARY.encode() + b'"}'),
    st.just(b"x" * (LOGIN_MAX_BYTES + 10)),
    st.binary(max_size=200),
)
header_values = st.one_of(
    st.binary(max_size=60).map(lambda b: bytes(c for c in b if c not in b"\r\n")),
    st.sampled_from([b"application/json", b"text/plain; charset=latin-1", b"multipart/form-data; boundary=x",
                     b"null", b"http://evil.example", b"A" * 9000]),
)  # fmt: skip


@st.composite
def requests(draw: st.DrawFn) -> tuple[str, bytes, list[tuple[str, bytes]], bytes]:
    method, template = draw(st.sampled_from(ROUTES))
    method = draw(
        st.sampled_from([method, method, "GET", "POST", "PUT", "DELETE", "HEAD", "OPTIONS", "PATCH"])
    )
    path = template
    while "{id}" in path:
        path = path.replace("{id}", draw(ids), 1)
    extra = draw(
        st.lists(st.tuples(st.sampled_from(["Content-Type", "Origin", "X-CSRF-Token", "Cookie", "Accept",
                                             "Transfer-Encoding", "Upgrade", "X-Forwarded-For"]), header_values),
                 max_size=3)
    )  # fmt: skip
    cookie = draw(st.sampled_from(["session", "session", "none", "junk"]))
    csrf = draw(st.sampled_from(["right", "right", "none", "wrong"]))
    return (
        method,
        path.encode("latin-1"),
        [*extra, ("_cookie", cookie.encode()), ("_csrf", csrf.encode())],
        draw(bodies),
    )


def _check_log(hmi: LocalHmi, client: Client) -> None:
    text = hmi.log.getvalue()
    assert CANARY not in text
    assert "hmi_request_error" not in text and "Traceback" not in text, text[-3000:]
    for token in client.tokens:
        assert token not in text
    assert "hmi_session=" not in text


@given(req=requests())
@fuzz_settings(300)
@example(req=("GET", b"/api/jobs/..", [("_cookie", b"session")], b""))
@example(req=("GET", b"/api/jobs/.", [("_cookie", b"session")], b""))
@example(req=("GET", b"/api/jobs/%2e%2e", [("_cookie", b"session")], b""))
@example(req=("POST", b"/api/trigger", [("_cookie", b"session"), ("_csrf", b"right")], b"\xff\xfe{"))
@example(req=("POST", b"/api/login", [], b"[" * 3000))
@example(req=("GET", b"/api/me", [("Cookie", b"hmi_session=" + b"A" * 20_000)], b""))
def test_every_route_answers_any_request_without_a_500_a_write_or_a_leak(hmi, client, req) -> None:
    method, path, headers, body = req
    c = client.fresh()
    before = _tree(hmi.root)
    sent: list[tuple[bytes, bytes]] = []
    for k, v in headers:
        if k == "_cookie":
            cookie = {b"session": f"{COOKIE}={c.token}".encode(), b"junk": b"hmi_session=nope; x=1"}.get(v)
            if cookie:
                sent.append((b"Cookie", cookie))
        elif k == "_csrf":
            csrf = {b"right": c.csrf.encode(), b"wrong": b"0" * 43}.get(v)
            if csrf:
                sent.append((b"X-CSRF-Token", csrf))
        else:
            sent.append((k.encode(), v))
    status, _ = asyncio.run(_raw(hmi.port, _request(method, path, sent, body)))
    assert status != 0 and (status < 500 or status == 503), (status, method, path[:100], body[:100])
    assert _tree(hmi.root) == before
    _check_log(hmi, c)


@pytest.mark.parametrize("job_id", [".", "..", "%2e%2e", "%2E%2E", ".%2e", "...", "%2e"])
@pytest.mark.parametrize("tail", ["", "/map", "/live", "/files/report.csv"])
def test_ids_outside_the_job_id_grammar_are_refused_with_404(hmi, client, job_id, tail) -> None:
    c = client.fresh()
    cookie = [(b"Cookie", f"{COOKIE}={c.token}".encode())]
    status, body = asyncio.run(
        _raw(hmi.port, _request("GET", f"/api/jobs/{job_id}{tail}".encode(), cookie, b""))
    )
    assert status in (400, 404), (status, body)
    status, _ = asyncio.run(
        _raw(hmi.port, _request("GET", f"/api/plates/{job_id}/rounds".encode(), cookie, b""))
    )
    assert status in (400, 404)
    # the grammar's own ids still work
    status, _ = asyncio.run(
        _raw(hmi.port, _request("GET", f"/api/jobs/{JOB}/files/report.csv".encode(), cookie, b""))
    )
    assert status == 200


@pytest.mark.parametrize("path", ["/api/trigger", "/api/control/pause", "/api/login"])
@pytest.mark.parametrize("body", [b"\xff\xfe{}", b"[" * 3000, b"[1, 2]", b'"text"', b"{", b"null"])
def test_bodies_that_are_not_utf8_json_objects_are_refused_with_400(hmi, client, path, body) -> None:
    c = client.fresh()
    h = [(b"Cookie", f"{COOKIE}={c.token}".encode()), (b"X-CSRF-Token", c.csrf.encode())]
    status, answer = asyncio.run(_raw(hmi.port, _request("POST", path.encode(), h, body)))
    assert status == 400, (status, answer)
    assert not hmi.link.sent or all(b not in body.decode("utf-8", "replace") for _, b in hmi.link.sent)


def test_a_huge_cookie_is_refused_and_never_logged(tmp_path) -> None:
    # a server of its own: on the module's shared server, after any earlier request, aiohttp's line
    # for this refusal did not reach the captured log (a shuffled run found it; in file order the
    # line the route fuzzer's own 20 kB cookie example left made the check pass without this one)
    with LocalHmi(tmp_path) as hmi:
        junk = "hmi_session=" + "Q" * 20_000
        status, _ = asyncio.run(
            _raw(hmi.port, _request("GET", b"/api/me", [(b"Cookie", junk.encode())], b""))
        )
        assert status == 400
        # the server logs the refusal on its own thread, after the answer has gone: wait for it
        wait_until_sync(lambda: "hmi_bad_http_request" in hmi.log.getvalue(), 5.0, "the refusal logged")
        text = hmi.log.getvalue()
        assert "QQQQQQQQ" not in text and "hmi_session=" not in text


# ---------------------------------------------------------------------------------------- websocket


async def _ws_session(hmi: LocalHmi, user: str = "olga") -> aiohttp.ClientSession:
    s = aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))
    async with s.post(hmi.url + "/api/login", json={"user": user, "password": USERS[user][1]}) as r:
        assert r.status == 200
        s.csrf = (await r.json())["csrf"]  # type: ignore[attr-defined]
    return s


@given(
    msgs=st.lists(st.one_of(st.text(max_size=300), st.binary(max_size=300), st.just("x" * 5000)), max_size=5)
)
@fuzz_settings(40)
def test_websocket_messages_never_break_the_server(hmi, msgs) -> None:
    async def run() -> int:
        s = await _ws_session(hmi, "vic")
        try:
            async with s.ws_connect(hmi.url + "/ws", origin=hmi.url) as ws:
                for m in msgs:
                    try:
                        await (ws.send_str(m) if isinstance(m, str) else ws.send_bytes(m))
                    except ConnectionResetError:
                        break  # the server closed a socket that sent too much: fine
            async with s.get(hmi.url + "/api/me") as r:
                return r.status
        finally:
            await s.close()

    assert asyncio.run(run()) == 200
    assert "hmi_request_error" not in hmi.log.getvalue()


def _status(n: int) -> dict:
    return {"cell_id": "c", "state": "idle", "t_utc": f"2026-12-01T10:00:{n % 60:02d}.000Z"}


def test_the_websocket_closes_at_logout_and_when_its_session_expires(hmi) -> None:
    async def logout_case() -> tuple[object, int]:
        s = await _ws_session(hmi)
        try:
            async with s.ws_connect(hmi.url + "/ws", origin=hmi.url) as ws:
                async with s.post(hmi.url + "/api/logout", headers={"X-CSRF-Token": s.csrf}) as r:  # type: ignore[attr-defined]
                    assert r.status == 200
                t0 = time.monotonic()
                received, code = 0, None
                while time.monotonic() - t0 < 5:
                    await asyncio.to_thread(hmi.publish, _status(received))
                    msg = await ws.receive(timeout=1.0)
                    if msg.type != aiohttp.WSMsgType.TEXT:
                        code = msg.data if msg.type == aiohttp.WSMsgType.CLOSE else msg.type
                        break
                    received += 1
                return code, received
        finally:
            await s.close()

    code, received = asyncio.run(logout_case())
    assert code == 4401 and received <= 1, (code, received)  # at most one status already on its way

    async def expiry_case() -> object:
        s = await _ws_session(hmi)
        try:
            async with s.ws_connect(hmi.url + "/ws", origin=hmi.url) as ws:
                for sess in hmi.auth.sessions.values():
                    sess.expires = time.time() - 1  # every session has expired
                for n in range(5):
                    await asyncio.to_thread(hmi.publish, _status(n))
                    msg = await ws.receive(timeout=2.0)
                    if msg.type != aiohttp.WSMsgType.TEXT:
                        return msg.data if msg.type == aiohttp.WSMsgType.CLOSE else msg.type
                return None
        finally:
            await s.close()

    assert asyncio.run(expiry_case()) == 4401
    assert not hmi.server.sockets


@pytest.mark.parametrize(
    "origin", ["http://evil.example", "http://127.0.0.1.evil.example", "null", "http://127.0.0.1"]
)
def test_a_websocket_from_another_origin_is_refused(hmi, origin) -> None:
    async def run() -> tuple[int, int]:
        s = await _ws_session(hmi, "vic")
        try:
            try:
                async with s.ws_connect(hmi.url + "/ws", origin=origin):
                    refused = 101
            except aiohttp.WSServerHandshakeError as exc:
                refused = exc.status
            async with s.ws_connect(hmi.url + "/ws", origin=hmi.url) as ws:  # its own page's origin
                own = 101 if not ws.closed else 0
            return refused, own
        finally:
            await s.close()

    assert asyncio.run(run()) == (403, 101)
