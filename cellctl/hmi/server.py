"""The HMI web server (aiohttp): the pages, a JSON API for them, and a websocket of live updates.

Every request that acts on the cell goes through :class:`~cellctl.hmi.link.CellLink` (Zenoh) and
is checked against the session's role first (:func:`cellctl.hmi.auth.allowed`); the page hiding a
button is a convenience, never the check. Cookies: ``HttpOnly``, ``SameSite=Strict``; every POST
but the log-in carries the session's CSRF token in ``X-CSRF-Token``. Log-ins are rate-limited per
client address and per user name (:class:`~cellctl.hmi.auth.LoginLimiter`), each attempt counted
before its password is checked. Bodies are UTF-8 JSON objects or refused (400); ids outside the
API's grammar are refused (404) before any path is built from them; a websocket needs the HMI's
own ``Origin`` and is closed when its session ends. Nothing a client sends (cookies, passwords,
bodies) reaches the log: aiohttp's own errors are logged without their values or locals.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import re
import time
import traceback
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import structlog
from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError

from analysis.contracts.results import read_report, read_results_arrays
from analysis.forming.plan_file import HEATING_PLAN_FILE, read_heating_plan
from analysis.rework import bounded_cell_mm, grid_deviation
from cellctl.api import DESIGN_SUFFIXES, MAX_TRIGGER_BYTES, ApiCallError
from cellctl.config import CellConfig
from cellctl.hmi.auth import (
    ACTION_ROLE,
    ZENOH_ROLE,
    Attempt,
    Authenticator,
    Session,
    allowed,
    role_cap,
    valid_name,
)
from cellctl.hmi.link import CellLink
from cellctl.jobstore.history import History
from cellctl.jobstore.jobs import JobStoreError, read_job_record

log = structlog.get_logger(__name__)

STATIC = Path(__file__).with_name("static")
COOKIE = "hmi_session"
#: the API's grammar of job and plate ids (cellctl.api's ``Ident``): never ``.`` or ``..``
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
#: files of a job a browser may download: (name, where in the job directory, content type)
DOWNLOADS = {
    "report.html": ("results/report.html", "text/html"),
    "report.pdf": ("results/report.pdf", "application/pdf"),
    "report.csv": ("results/report.csv", "text/csv"),
    "report.json": ("results/report.json", "application/json"),
    "cloud.ply": ("results/cloud.ply", "application/octet-stream"),
    # the design file's (ship) frame; and `cellctl export`'s files, once written (analysis.export)
    "lines-ship.csv": ("results/lines-ship.csv", "text/csv"),
    **{
        n: (f"results/{n}", "application/octet-stream")
        for n in ("cloud.las", "cloud.e57", "cloud-ship.ply", "cloud-ship.las", "cloud-ship.e57")
    },
    # the line-heating plan (docs/forming.md): the crew marks the plate from the DXF
    "heating-plan.json": ("results/heating-plan.json", "application/json"),
    "heating-plan.dxf": ("results/heating-plan.dxf", "application/dxf"),
}
MAX_BODY_BYTES = MAX_TRIGGER_BYTES  # a trigger is the largest body the HMI takes
#: a log-in body: {"user": <= 64 characters, "password": ...}
LOGIN_MAX_BYTES = 4096
#: password checks running at once (each a thread)
MAX_CONCURRENT_CHECKS = 2
#: the result page's deviation map (top view and 3D view): a raster of at most this many cells, each
#: the mean deviation of the stored map points in it, whatever the plate's size (issue 42)
MAP_MAX_CELLS = 20_000
#: the smallest cell of the map (mm): a small plate's raster is no finer than its stored points hold
MAP_MIN_CELL_MM = 5.0
#: each line's plot on the result page: at most this many samples (its plot is ~300 px wide: the
#: lowest and highest deviation of ~130 bins)
MAP_LINE_SAMPLES = 400
_SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; object-src 'none'; "
        "frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def _json_floats(values: np.ndarray, decimals: int) -> list[float | None]:
    """``values`` rounded for a JSON body, None (null) where there is no value (NaN)."""
    rounded = np.round(np.asarray(values, dtype=np.float64), decimals)
    return [None if v != v else v for v in rounded.tolist()]


def _err(status: int, code: str, message: str, field: str = "") -> web.Response:
    return web.json_response({"code": code, "field": field, "message": message}, status=status)


def client_key(remote: str | None) -> str:
    """The limiter's key of a client address: an IPv6 address by its /64 (one host's addresses
    are a whole /64, so single addresses would give an attacker as many fresh keys as it likes)."""
    try:
        ip = ipaddress.ip_address(remote or "")
    except ValueError:
        return remote or "?"
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.ip_network(f"{ip}/64", strict=False))
    return str(ip)


class _BodyError(Exception):
    def __init__(self, response: web.Response) -> None:
        self.response = response


async def _read_body(request: web.Request, limit: int) -> bytes:
    """The request's body, at most ``limit`` bytes (else 413), however it is sent (chunked too)."""
    if request.content_length is not None and request.content_length > limit:
        raise _BodyError(_err(413, "too_large", f"a body of at most {limit} bytes"))
    buf = bytearray()
    while len(buf) <= limit:
        chunk = await request.content.read(limit + 1 - len(buf))
        if not chunk:
            break
        buf += chunk
    if len(buf) > limit:
        raise _BodyError(_err(413, "too_large", f"a body of at most {limit} bytes"))
    return bytes(buf)


def _json_object(raw: bytes, *, empty: str | None = None) -> tuple[str, dict[str, Any]]:
    """``raw`` as text and as the JSON object it must be (UTF-8), else :class:`_BodyError` (400).
    ``empty``: the text an empty body stands for (None: an empty body is refused)."""
    if not raw.strip() and empty is not None:
        return empty, json.loads(empty)
    try:
        text = raw.decode("utf-8")
        value = json.loads(text)
    except (ValueError, RecursionError):  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise _BodyError(_err(400, "malformed", "the body must be a JSON object in UTF-8")) from None
    if not isinstance(value, dict):
        raise _BodyError(_err(400, "malformed", "the body must be a JSON object in UTF-8"))
    return text, value


def _as_user(obj: dict[str, Any], user: str) -> str:
    """The request as the daemon gets it: ``requested_by`` is the logged-in user, whatever the page
    sent (the daemon records it in the job's history and its audit log)."""
    return json.dumps({**obj, "requested_by": user})


class _NoClientDataInLogs(logging.Filter):
    """aiohttp's own error lines without what the client sent: a malformed request (a 20 kB cookie,
    a broken header) is logged as its status only, and any other exception as its type and
    traceback text (never its value, whose text or frame locals may hold a cookie or a password)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.exc_info or record.exc_info[1] is None:
            return True
        exc = record.exc_info[1]
        if isinstance(exc, HttpProcessingError):  # the client's fault, not the server's
            record.msg, record.args = "hmi_bad_http_request status=%s", (exc.code,)
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        else:
            tb = "".join(traceback.format_tb(exc.__traceback__))
            record.msg, record.args = "hmi_request_error %s\n%s", (type(exc).__name__, tb)
        record.exc_info, record.exc_text = None, None
        return True


_LOG_FILTER = _NoClientDataInLogs()
for _name in ("aiohttp.server", "aiohttp.web", "aiohttp.access", "aiohttp.websocket"):
    logging.getLogger(_name).addFilter(_LOG_FILTER)


class HmiServer:
    def __init__(
        self,
        cfg: CellConfig,
        auth: Authenticator,
        *,
        secure_cookie: bool = False,
        default_placement: dict[str, Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.default_placement = default_placement
        acc = cfg.zenoh.access
        self.cap = role_cap(acc.enabled, acc.user, {str(k): list(v) for k, v in acc.roles.items()})
        if self.cap != "engineer":
            log.warning("hmi_read_only", reason=f"zenoh user {acc.user!r} holds no operator role")
        self.auth = auth
        self.secure_cookie = secure_cookie
        self.data_dir = Path(cfg.cell.data_dir)
        self.designs_dir = Path(cfg.cell.designs_dir)
        self.history: History | None = None
        # scrypt costs ~50 ms and 16 MB a check: a flood of log-ins from many addresses queues here
        # instead of taking every worker thread from the history and the downloads
        self._checks = asyncio.Semaphore(MAX_CONCURRENT_CHECKS)
        #: open websockets and the session token each was opened with
        self.sockets: dict[web.WebSocketResponse, str] = {}
        self.link = CellLink(cfg, self._broadcast)
        self.link.on_job_end = self._job_ended
        self.app = self._build_app()

    # ---------------------------------------------------------------- app
    def _build_app(self) -> web.Application:
        app = web.Application(middlewares=[self._headers_mw, self._auth_mw], client_max_size=MAX_BODY_BYTES)
        r = app.router
        r.add_get("/", self.index)
        r.add_static("/static/", STATIC, show_index=False)
        r.add_post("/api/login", self.login)
        r.add_post("/api/logout", self.logout)
        r.add_get("/api/me", self.me)
        r.add_get("/api/status", self.status)
        r.add_get("/api/designs", self.designs)
        r.add_get("/api/designs/preview", self.design_preview)
        r.add_post("/api/trigger", self.trigger)
        r.add_post("/api/control/{action}", self.control)
        r.add_get("/api/jobs", self.jobs)
        r.add_get("/api/jobs/{job_id}", self.job)
        r.add_get("/api/jobs/{job_id}/map", self.job_map)
        r.add_get("/api/jobs/{job_id}/live", self.job_live)
        r.add_get("/api/jobs/{job_id}/files/{name}", self.job_file)
        r.add_get("/api/plates/{plate_id}/rounds", self.rounds)
        r.add_get("/ws", self.websocket)
        app.on_startup.append(self._on_startup)
        app.on_cleanup.append(self._on_cleanup)
        return app

    async def _on_startup(self, app: web.Application) -> None:
        self.history = History(self.data_dir)
        n = await asyncio.to_thread(self.history.rebuild)
        log.info("hmi_history_rebuilt", jobs=n)
        await self.link.start()

    async def _on_cleanup(self, app: web.Application) -> None:
        for ws in list(self.sockets):
            with contextlib.suppress(Exception):
                await ws.close(code=1001, message=b"server shutdown")
        await self.link.close()
        if self.history is not None:
            self.history.close()

    @web.middleware
    async def _headers_mw(self, request: web.Request, handler: Any) -> web.StreamResponse:
        resp = await handler(request)
        for k, v in _SECURITY_HEADERS.items():
            if k == "Cache-Control" and request.path.startswith("/static/"):
                continue
            resp.headers.setdefault(k, v)
        return resp

    @web.middleware
    async def _auth_mw(self, request: web.Request, handler: Any) -> web.StreamResponse:
        path = request.path
        if path == "/" or path.startswith("/static/") or path == "/api/login":
            return await handler(request)
        s = self.auth.session(request.cookies.get(COOKIE))
        if s is None:
            return _err(401, "not_logged_in", "log in first")
        if request.method == "POST" and request.headers.get("X-CSRF-Token") != s.csrf:
            return _err(403, "csrf", "missing or wrong CSRF token; reload the page")
        request["session"] = s
        return await handler(request)

    # ---------------------------------------------------------------- pages and log-in
    async def index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def login(self, request: web.Request) -> web.Response:
        # nothing is stored for a request refused here: a body too large or malformed, a user name
        # the users file could not hold, an attempt over the limits (docs/hmi.md, "Log-in limits")
        try:
            _, body = _json_object(await _read_body(request, LOGIN_MAX_BYTES))
        except _BodyError as exc:
            return exc.response
        name, password = body.get("user"), body.get("password")
        if not isinstance(name, str) or not isinstance(password, str):
            return _err(400, "malformed", 'expected {"user": ..., "password": ...}')
        if not valid_name(name):
            return _err(400, "invalid", "a user name is 1 to 64 letters, digits, _ . -", "user")
        attempt = self.auth.limiter.reserve(client_key(request.remote), name)
        if not isinstance(attempt, Attempt):
            return web.json_response(
                {
                    "code": "rate_limited",
                    "field": "",
                    "message": f"too many failed log-ins; try again in {attempt:.0f} s",
                },
                status=429,
                headers={"Retry-After": str(int(attempt) + 1)},
            )
        async with self._checks:
            s = await asyncio.to_thread(self.auth.login, name, password)
        self.auth.limiter.settle(attempt, ok=s is not None)
        if s is None:
            log.info("hmi_login_refused", user=name, peer=request.remote)
            return _err(401, "bad_login", "wrong user name or password")
        log.info("hmi_login", user=s.user, role=s.role)
        resp = web.json_response(self._me(s))
        resp.set_cookie(
            COOKIE, s.token, httponly=True, samesite="Strict", secure=self.secure_cookie, path="/",
            max_age=int(self.auth.ttl_s),
        )  # fmt: skip
        return resp

    async def logout(self, request: web.Request) -> web.Response:
        token = request.cookies.get(COOKIE)
        self.auth.logout(token)
        for ws, ws_token in list(self.sockets.items()):
            if ws_token == token:
                await self._close_ended(ws)
        resp = web.json_response({"ok": True})
        resp.del_cookie(COOKIE, path="/")
        return resp

    def _me(self, s: Session) -> dict[str, Any]:
        return {
            "user": s.user,
            "role": s.role,
            "zenoh_role": ZENOH_ROLE[s.role],
            "csrf": s.csrf,
            "may": [a for a in ACTION_ROLE if allowed(s.role, a, cap=self.cap)],
        }

    async def me(self, request: web.Request) -> web.Response:
        return web.json_response(self._me(request["session"]))

    # ---------------------------------------------------------------- the cell
    async def status(self, request: web.Request) -> web.Response:
        st = self.link.status
        return web.json_response({"status": st.model_dump(mode="json") if st else None})

    def _check(self, request: web.Request, action: str) -> web.Response | None:
        s: Session = request["session"]
        if not allowed(s.role, action, cap=self.cap):
            log.info("hmi_refused", user=s.user, role=s.role, action=action)
            need = ACTION_ROLE.get(action, "engineer")
            if allowed(s.role, action):
                return _err(
                    403,
                    "forbidden",
                    f"{action}: this HMI's Zenoh identity holds no operator role (read-only)",
                )
            return _err(403, "forbidden", f"{action} needs the {need} role; {s.user} is {s.role}")
        return None

    async def trigger(self, request: web.Request) -> web.Response:
        if (refused := self._check(request, "trigger")) is not None:
            return refused
        try:
            _, obj = _json_object(await _read_body(request, MAX_BODY_BYTES))
        except _BodyError as exc:
            return exc.response
        try:
            acc = await self.link.trigger(_as_user(obj, request["session"].user))
        except ApiCallError as exc:
            return _api_error(exc)
        log.info("hmi_trigger", user=request["session"].user, job_id=acc.job_id)
        return web.json_response(acc.model_dump(mode="json"))

    async def control(self, request: web.Request) -> web.Response:
        action = request.match_info["action"]
        if action not in ACTION_ROLE or action == "trigger":
            return _err(404, "invalid", f"no action {action!r}", "action")
        if (refused := self._check(request, action)) is not None:
            return refused
        try:
            _, obj = _json_object(await _read_body(request, MAX_BODY_BYTES), empty="{}")
        except _BodyError as exc:
            return exc.response
        try:
            reply = await self.link.control(action, _as_user(obj, request["session"].user))
        except ApiCallError as exc:
            return _api_error(exc)
        log.info("hmi_control", user=request["session"].user, action=action)
        return web.json_response(reply.model_dump(mode="json"))

    async def designs(self, request: web.Request) -> web.Response:
        root = self.designs_dir

        def scan() -> list[str]:
            if not root.is_dir():
                return []
            return sorted(
                p.relative_to(root).as_posix()
                for p in root.rglob("*")
                if p.is_file() and p.suffix.lower() in DESIGN_SUFFIXES
            )

        return web.json_response(
            {"designs": await asyncio.to_thread(scan), "default_placement": self.default_placement}
        )

    async def design_preview(self, request: web.Request) -> web.Response:
        rel = request.query.get("path", "")
        root = self.designs_dir.resolve()
        try:
            p = (root / rel).resolve()
            p.relative_to(root)
        except (ValueError, OSError):
            return _err(400, "invalid", "not a design in the designs directory", "path")
        if not p.is_file():
            return _err(404, "design_not_found", f"{rel}: no such design")

        def load() -> dict[str, Any]:
            from analysis.design.cad import design_mesh_from_file

            design = design_mesh_from_file(p)
            v = np.asarray(design.vertices_mm, float)
            idx = np.linspace(0, len(v) - 1, min(len(v), 4000)).astype(int)
            return {
                "xyz_mm": np.round(v[idx], 1).tolist(),
                "min_mm": v.min(0).tolist(),
                "max_mm": v.max(0).tolist(),
            }

        try:
            return web.json_response(await asyncio.to_thread(load))
        except Exception as exc:  # an unreadable design: say so, the page stays usable
            return _err(422, "invalid", f"{rel}: cannot read: {exc}", "path")

    # ---------------------------------------------------------------- jobs and history
    def _job_dir(self, job_id: str) -> Path | None:
        if not _ID.match(job_id):
            return None
        d = self.data_dir / "jobs" / job_id
        return d if d.is_dir() else None

    def _job_ended(self, job_id: str) -> None:
        async def later() -> None:
            # report.json is on disk before the job is published done; the retries cover a slow disk
            row, attempts = None, 0
            for delay in (0.5, 2.0, 5.0):
                await asyncio.sleep(delay)
                attempts += 1
                row = await asyncio.to_thread(self.history.index_job, job_id) if self.history else None
                if row and (row["verdict"] or row["state"] != "done"):
                    break
            log.info(
                "hmi_job_indexed", job_id=job_id, attempts=attempts, plate_id=row and row["plate_id"],
                state=row and row["state"], verdict=row and row["verdict"],
            )  # fmt: skip
            self._broadcast({"type": "history", "job_id": job_id})

        task = asyncio.get_running_loop().create_task(later())
        _TASKS.add(task)
        task.add_done_callback(_TASKS.discard)

    async def jobs(self, request: web.Request) -> web.Response:
        q = request.query
        rows = await asyncio.to_thread(
            self.history.jobs, plate_id=q.get("plate") or None, verdict=q.get("verdict") or None,
            date=q.get("date") or None,
        )  # fmt: skip
        return web.json_response({"jobs": rows})

    async def rounds(self, request: web.Request) -> web.Response:
        plate_id = request.match_info["plate_id"]
        if not _ID.match(plate_id):
            return _err(404, "no_plate", "not a plate id", "plate_id")
        return web.json_response({"rounds": await asyncio.to_thread(self.history.rounds, plate_id)})

    async def job(self, request: web.Request) -> web.Response:
        job_id = request.match_info["job_id"]
        d = self._job_dir(job_id)
        if d is None:
            return _err(404, "no_job", f"no job {job_id}")

        def read() -> dict[str, Any]:
            rec = read_job_record(d).as_json()
            rp = d / "results" / "report.json"
            if not rp.exists():
                rp = d / "report.json"
            report = read_report(rp).model_dump(mode="json") if rp.exists() else None
            files = [n for n, (rel, _) in DOWNLOADS.items() if (d / rel).is_file()]
            if (d / "cloud.bin").is_file():
                files.append("cloud.bin")
            prev = self.history.previous_round(job_id) if self.history else None
            return {"job": rec, "report": report, "files": files, "previous": prev,
                    "heating_plan": _heating_plan(d / "results")}  # fmt: skip

        try:
            return web.json_response(await asyncio.to_thread(read))
        except JobStoreError as exc:  # a record of another version, or damaged: said, not a 500
            return _err(
                409, "unreadable_job", f"job {job_id}: its record cannot be read ({exc.reason[:200]})"
            )

    async def job_map(self, request: web.Request) -> web.Response:
        d = self._job_dir(request.match_info["job_id"])
        path = d / "results" / "results.npz" if d else None
        if path is None or not path.is_file():
            return _err(404, "no_job", "no results for this job")

        def read() -> dict[str, Any]:
            res = read_results_arrays(path)
            cell = bounded_cell_mm(res.plate_size_mm, MAP_MAX_CELLS, MAP_MIN_CELL_MM)
            field = grid_deviation(res.plate_xy_mm, res.plate_deviation_mm, res.plate_size_mm, cell)
            nx, ny = field.mean_mm.shape
            lines = []
            for full in res.lines:  # read_results_arrays without a count: the lines stored, none missing
                assert full is not None
                series = full.decimated(MAP_LINE_SAMPLES)
                lines.append({"s_mm": _json_floats(series.s_mm, 1),
                              "deviation_mm": _json_floats(series.deviation_mm, 3)})  # fmt: skip
            return {
                "plate_size_mm": res.plate_size_mm.tolist(),
                # cell (i, j) covers x in [i, i + 1) * cell_mm, y in [j, j + 1) * cell_mm; i-major
                "cell_mm": round(cell, 3),
                "nx": nx,
                "ny": ny,
                "deviation_mm": _json_floats(field.mean_mm.ravel(), 2),
                "lines": lines,
            }

        resp = web.json_response(await asyncio.to_thread(read))
        resp.enable_compression()  # numbers in JSON: a third of the bytes on the plant network
        return resp

    async def job_live(self, request: web.Request) -> web.Response:
        job_id = request.match_info["job_id"]
        if not _ID.match(job_id):
            return _err(404, "no_job", "not a job id")
        xyz, seq = self.link.live_cloud(job_id)
        return web.json_response({"xyz_mm": xyz, "seq": seq})

    async def job_file(self, request: web.Request) -> web.StreamResponse:
        d = self._job_dir(request.match_info["job_id"])
        name = request.match_info["name"]
        if d is None:
            return _err(404, "no_job", "no such job")
        if name == "cloud.bin":
            rel, ctype = "cloud.bin", "application/x-cellctl-cloud"
        elif name in DOWNLOADS:
            rel, ctype = DOWNLOADS[name]
        else:
            return _err(404, "invalid", f"no download {name!r}")
        path = d / rel
        if not path.is_file():
            return _err(404, "no_file", f"{name} is not there (yet)")
        return web.FileResponse(
            path,
            headers={"Content-Type": ctype, "Content-Disposition": f'attachment; filename="{d.name}-{name}"'},
        )

    # ---------------------------------------------------------------- live updates
    async def websocket(self, request: web.Request) -> web.StreamResponse:
        origin = request.headers.get("Origin")
        # a browser always sends its page's origin: a page of another site riding the crew's cookie
        # is refused (a client without a browser holds the cookie itself and gains nothing)
        if origin is not None and urlsplit(origin).netloc.lower() != request.host.lower():
            log.info("hmi_ws_refused", reason="origin", origin=origin[:200])
            return _err(403, "origin", "a websocket from another site's page")
        token = request.cookies.get(COOKIE, "")
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=4096)
        await ws.prepare(request)
        self.sockets[ws] = token
        try:
            if self.link.status is not None:
                await ws.send_str(
                    json.dumps({"type": "status", "status": self.link.status.model_dump(mode="json")})
                )
            async for msg in ws:  # the page sends nothing; whatever arrives is dropped
                if msg.type == WSMsgType.ERROR or self.auth.session(token) is None:
                    break
        finally:
            self.sockets.pop(ws, None)
        return ws

    async def _close_ended(self, ws: web.WebSocketResponse) -> None:
        """Close a websocket whose session ended (log-out, expiry): 4401, the page shows the log-in."""
        self.sockets.pop(ws, None)
        with contextlib.suppress(Exception):
            await ws.close(code=4401, message=b"session ended")

    def _broadcast(self, event: dict[str, Any]) -> None:
        if not self.sockets:
            return
        event["t_server_ms"] = time.time() * 1000.0
        text = json.dumps(event)
        loop = asyncio.get_running_loop()
        for ws, token in list(self.sockets.items()):
            if ws.closed:
                self.sockets.pop(ws, None)
                continue
            # an expired session's socket is closed at the next event (the status, every second)
            coro = _send(ws, text) if self.auth.session(token) is not None else self._close_ended(ws)
            task = loop.create_task(coro)
            _TASKS.add(task)
            task.add_done_callback(_TASKS.discard)


_TASKS: set[asyncio.Task[Any]] = set()


async def _send(ws: web.WebSocketResponse, text: str) -> None:
    with contextlib.suppress(Exception):
        await ws.send_str(text)


def _api_error(exc: ApiCallError) -> web.Response:
    if exc.error is None:  # no reply: the daemon is down or too slow
        return _err(503, "no_reply", str(exc))
    e = exc.error
    status = {"busy": 409, "queue_full": 409, "not_allowed": 409, "no_job": 404, "design_not_found": 404}.get(
        e.code, 400
    )
    return _err(status, e.code, e.message, e.field)


async def serve(
    cfg: CellConfig, auth: Authenticator, host: str, port: int, stop: asyncio.Event, **kwargs: Any
) -> int:
    """Run until ``stop`` is set; prints the address once listening (``kwargs``: HmiServer's)."""
    server = HmiServer(cfg, auth, **kwargs)
    runner = web.AppRunner(server.app, access_log=None)
    await runner.setup()
    try:
        site = web.TCPSite(runner, host, port)
        await site.start()
        bound = runner.addresses[0] if runner.addresses else (host, port)
        print(json.dumps({"ready": True, "url": f"http://{bound[0]}:{bound[1]}/"}), flush=True)
        log.info("hmi_ready", host=bound[0], port=bound[1])
        await stop.wait()
        return 0
    finally:
        await runner.cleanup()


def _heating_plan(results: Path) -> dict[str, Any] | None:
    """heating-plan.json for the result page, each line with its sentence (the one the CLI prints);
    None when the job has none (yet); a file that cannot be read is a plan-less answer saying so."""
    if not (results / HEATING_PLAN_FILE).is_file():
        return None
    try:
        plan = read_heating_plan(results)
    except ValueError:  # the message names server paths, which the page never shows
        return {"status": "no_plan", "reason": "heating-plan.json cannot be read: `cellctl heat-plan` makes it again",
                "lines": []}  # fmt: skip
    out = plan.model_dump(mode="json", include={"status", "reason", "lines", "notes", "predicted"})
    for line, d in zip(plan.lines, out["lines"], strict=True):
        d["sentence"] = line.sentence()
    return out
