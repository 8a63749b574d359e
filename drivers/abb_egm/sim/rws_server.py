"""Robot Web Services server of the simulated controller (aiohttp), RWS 1.0 and RWS 2.0 profiles.

Answers as the controllers do in the captured exchanges of ``../shared/testdata/rws`` (see
``docs/robot-setup.md`` for which RobotWare versions they come from), on top of a ``ControllerModel``:

- ``rws1`` (IRC5, RobotWare 6): plain HTTP, digest auth (RFC 2617 MD5, qop=auth; realm
  ``validusers@robapi.abb``, opaque, ``stale="FALSE"`` as the controller sends them), session cookies
  ``-http-session-`` (``<n>::http.session::<32 hex>``) and ``ABBCX``; ``json=1`` answers are
  ``application/json`` shaped ``{"_links": ..., "_embedded": {"_state": [...]}}``, XHTML
  (``application/xhtml+xml``) without it; errors carry ``status`` under ``_embedded`` beside an empty
  ``_state``; operations chosen with ``?action=``.
- ``rws2`` (OmniCore, RobotWare 7): HTTPS with a self-signed certificate generated at start, basic
  auth, ``application/hal+json;v=2.0`` / ``application/xhtml+xml;v=2.0`` chosen by ``Accept`` (406
  without ``;v=2.0``); single resources ``{"_links", "status", "state": [...]}``, lists
  ``{"_links", "_embedded": {"resources": [...]}}``, errors with ``status`` at the top level;
  operations as sub-resources (``/rw/rapid/execution/start``); mutating calls refused with 403 unless
  ``mastership=implicit`` or edit mastership was requested.

Both: POST ``/subscription`` -> 201 with an XHTML body naming the websocket (``<a href="ws://.../poll/N"
rel="self">``) and the same URL in ``Location``; the websocket (``robapi2_subscription`` /
``rws_subscription``) carries XHTML event frames. A trailing slash names the same resource; unknown
resources get the controller's 404 body, wrong methods 405 in the same envelope.

Sessions are limited (``max_sessions``; 503 beyond) and expire after ``session_idle_s``. Fault knobs
(``inject_error``, ``set_delay``, ``expire_sessions``) act at run time. A bad request never stops the
server: it gets a 4xx naming the offending field, and is counted and logged (rate limited).
"""

from __future__ import annotations

import asyncio
import base64
import html
import itertools
import json
import os
import re
import secrets
import shutil
import ssl
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote, unquote

import structlog
from aiohttp import WSMsgType, web

from drivers.abb_egm import rws_protocol as rw
from drivers.abb_egm.digest import digest_response, parse_auth_params
from drivers.abb_egm.rapid_values import (
    RC_IO_ACCESS_DENIED,
    ControllerError,
    RapidValueError,
    format_extax,
    format_num,
)
from drivers.abb_egm.rws_protocol import Profile
from drivers.abb_egm.sim.model import (
    AccessDenied,
    ControllerModel,
    SignalNotFound,
    StateRefused,
    SymbolNotFound,
)

log = structlog.get_logger(__name__)

REALM = "validusers@robapi.abb"
DIGEST_OPAQUE = "799d5"
SESSION_COOKIE = "-http-session-"
ABBCX_COOKIE = "ABBCX"
CONTENT_TYPE = {
    ("rws1", True): rw.JSON,
    ("rws1", False): rw.XHTML,
    ("rws2", True): rw.HAL_JSON_V2,
    ("rws2", False): rw.XHTML_V2,
}

# Controller return codes as the captured answers carry them (../shared/testdata/rws, SOURCES.md).
RC_OK = 294912  # SYS_CTRL_S_OK, in every RWS 2.0 "status"
RC_RESOURCE_NOT_FOUND = -1073414146  # RWS 1.0 unknown resource / symbol (rws_services.cpp, rapid_symbol_data)
RC_INVALID_PARAMETER = -1073445879  # "Invalid action parameter value"; RW7 "Task ... does not exist"
RC_PGM_STATE = -1073442809  # execution start refused in this program / controller state
RC_SIGNAL_NOT_FOUND = -1073445866  # eio_signal_open_by_name failed / invalid IO signal name
RC_SIGNAL_REJECTED = RC_IO_ACCESS_DENIED  # -1073445881 "Rejected": the signal's access level
RC_HELD_BY_OTHER = -1073445862  # "Requested resource is held by someone else" (mastership)
RC_NO_MASTERSHIP = -1073445859  # "The user does not have required mastership for the operation"
RC_SYMBOL_NOT_FOUND_V2 = -1073442816  # RW7 symbol not found; RW6 "Unknown module name"
RC_MODULE_INVALID_V2 = -1073442813  # RW7 "module name/parameter is invalid or missing"
# Simulator's own codes (no captured answer to copy): outside the controller's range.
RC_METHOD_NOT_ALLOWED = -7008
RC_BUSY = -7005
RC_NOT_ACCEPTABLE = -7007

ELOG_DOMAINS = (0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12, 15, 17)  # as RobotWare 7 lists them
PAGE_LIMIT_MAX = 100  # items per page; larger limits are cut to this

Handler = Callable[["_Request"], Awaitable[web.StreamResponse]]


class RwsRequestError(Exception):
    """A request the server rejects; carries the HTTP status, the controller return code and a message."""

    def __init__(self, status: int, message: str, code: int = RC_INVALID_PARAMETER) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.code = code


@dataclass
class Session:
    """One authenticated client session (what the cookies point at).

    ``abbcx``: the value of the ``ABBCX`` cookie (the controller's client number; its websocket
    handshake may carry only this cookie and the digest header, as abb-robot-client sends it).
    """

    sid: str
    user: str
    created_s: float
    last_used_s: float
    abbcx: str = ""
    mastership: set[str] = field(default_factory=set)


@dataclass
class _Subscription:
    sid: str
    session_id: str
    resources: dict[str, int]  # resource key -> priority
    queue: asyncio.Queue[str] = field(default_factory=lambda: asyncio.Queue(maxsize=1000))
    dropped: int = 0


@dataclass
class _Fault:
    status: int
    code: int
    message: str


@dataclass
class _Request:
    req: web.Request
    session: Session
    match: re.Match[str]
    form: dict[str, str]
    json: bool
    multi: list[tuple[str, str]] = field(default_factory=list)  # form fields in order, repeats kept
    path: str = ""  # the request path without a trailing slash


def _x(value: object) -> str:
    """XML-escape a value for XHTML text or an attribute."""
    return html.escape(str(value), quote=True)


async def generate_self_signed_cert(directory: str, host: str) -> tuple[str, str]:
    """Create a self-signed certificate and key for ``host`` in ``directory``; returns (cert path, key path).

    Uses the ``cryptography`` package when it is installed, else the ``openssl`` command line (the
    controller's certificate is self-signed too, so clients must not verify it against a CA).
    """
    cert_path = os.path.join(directory, "rws_cert.pem")
    key_path = os.path.join(directory, "rws_key.pem")
    try:
        await asyncio.to_thread(_cert_with_cryptography, cert_path, key_path, host)
        return cert_path, key_path
    except ImportError:
        pass
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError("RWS 2.0 profile needs the 'cryptography' package or the openssl command for TLS")
    san = f"IP:{host}" if re.match(r"^[\d.]+$", host) else f"DNS:{host}"
    proc = await asyncio.create_subprocess_exec(
        openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
        "-keyout", key_path, "-out", cert_path, "-days", "3650", "-subj", "/CN=cellctl-sim-controller",
        "-addext", f"subjectAltName={san}",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"openssl failed to create the RWS certificate: {err.decode(errors='replace')}")
    return cert_path, key_path


def _cert_with_cryptography(cert_path: str, key_path: str, host: str) -> None:
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "cellctl-sim-controller")])
    try:
        alt: x509.GeneralName = x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        alt = x509.DNSName(host)
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=3650))
        .add_extension(x509.SubjectAlternativeName([alt]), critical=False)
        # CA:TRUE, as `openssl req -x509` makes it: clients can pin the certificate as its own CA.
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    with open(key_path, "wb") as f:
        f.write(
            key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
            )
        )
    with open(cert_path, "wb") as f:
        f.write(cert.public_bytes(serialization.Encoding.PEM))


class RwsServer:
    """RWS endpoint of the simulated controller.

    ``users`` maps user name to password (default: ``Default User`` / ``robotics``). ``port`` 0 binds an
    ephemeral port; ``start()`` returns the bound ``(host, port)``. ``base_url`` is set after start.
    """

    def __init__(
        self,
        model: ControllerModel,
        *,
        profile: Profile = "rws1",
        host: str = "127.0.0.1",
        port: int = 0,
        users: dict[str, str] | None = None,
        max_sessions: int = 70,
        session_idle_s: float = 300.0,
        nonce_lifetime_s: float = 300.0,
        mechunit: str = "ROB_1",
    ) -> None:
        if profile not in ("rws1", "rws2"):
            raise ValueError(f"unknown RWS profile {profile!r} (use 'rws1' or 'rws2')")
        self.model = model
        self.profile: Profile = profile
        self.host = host
        self.port = port
        self.users = dict(users) if users is not None else {"Default User": "robotics"}
        self.max_sessions = max_sessions
        self.session_idle_s = session_idle_s
        self.nonce_lifetime_s = nonce_lifetime_s
        self.mechunit = mechunit
        self.sessions: dict[str, Session] = {}
        self.stats: dict[str, int] = {
            "requests": 0,
            "sessions_created": 0,
            "auth_failures": 0,
            "bad_requests": 0,
            "rejected_busy": 0,
            "events_dropped": 0,
            "subscriptions_created": 0,
        }
        self.cert_path: str | None = None
        self._nonces: dict[str, float] = {}
        self._nonce_nc: dict[str, int] = {}
        self._subs: dict[str, _Subscription] = {}
        self._sub_seq = 0
        self._session_seq = itertools.count(1)
        self._abbcx_seq = itertools.count(int(secrets.randbelow(1000)) + 1)
        self._cycle = "once"  # the run mode of the last start (CellEgm runs once)
        self._master: dict[str, str] = {}  # mastership domain ("edit", "motion") -> session id
        self._faults: dict[str, _Fault] = {}
        self._delays: dict[str, float] = {}
        self._runner: web.AppRunner | None = None
        self._tmpdir: tempfile.TemporaryDirectory[str] | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._last_bad_log_s = 0.0
        self._websockets: set[web.WebSocketResponse] = set()
        self._routes = self._build_routes()

    # ---- lifecycle ----------------------------------------------------------------------------

    @property
    def scheme(self) -> str:
        """``http`` for RWS 1.0, ``https`` for RWS 2.0."""
        return "https" if self.profile == "rws2" else "http"

    @property
    def base_url(self) -> str:
        """``scheme://host:port`` of the running server."""
        return f"{self.scheme}://{self.host}:{self.port}"

    async def start(self) -> tuple[str, int]:
        """Bind and serve; returns the bound ``(host, port)``."""
        app = web.Application(client_max_size=1 << 20)
        app.router.add_route("*", "/{tail:.*}", self._dispatch)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        ssl_ctx: ssl.SSLContext | None = None
        if self.profile == "rws2":
            if self._tmpdir is None:
                self._tmpdir = tempfile.TemporaryDirectory(prefix="rws-cert-")
                self.cert_path, self._key_path = await generate_self_signed_cert(self._tmpdir.name, self.host)
            ssl_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ssl_ctx.load_cert_chain(self.cert_path, self._key_path)  # type: ignore[arg-type]
        site = web.TCPSite(self._runner, self.host, self.port, ssl_context=ssl_ctx)
        await site.start()
        server = site._server  # aiohttp keeps the asyncio server here; needed for the ephemeral port
        assert server is not None and server.sockets
        self.port = server.sockets[0].getsockname()[1]
        self._unsubscribe = self.model.subscribe(self._on_model_change)
        log.info("rws_server_started", profile=self.profile, url=self.base_url)
        return self.host, self.port

    async def stop(self) -> None:
        """Close websockets and the listener; drop all sessions."""
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        for ws in list(self._websockets):
            await ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None
        self.sessions.clear()
        self._subs.clear()
        self._master.clear()
        log.info("rws_server_stopped", profile=self.profile)

    # ---- fault knobs --------------------------------------------------------------------------

    def inject_error(
        self, path_prefix: str, status: int = 500, code: int = -1, message: str = "injected fault"
    ) -> None:
        """Answer every request whose path starts with ``path_prefix`` with this error (until cleared)."""
        self._faults[path_prefix] = _Fault(status, code, message)

    def set_delay(self, seconds: float, path_prefix: str = "/") -> None:
        """Delay responses to paths under ``path_prefix`` by ``seconds`` (0 removes the delay)."""
        if seconds <= 0:
            self._delays.pop(path_prefix, None)
        else:
            self._delays[path_prefix] = seconds

    def clear_error(self, path_prefix: str) -> None:
        """Remove the injected error of ``path_prefix`` (if any)."""
        self._faults.pop(path_prefix, None)

    def clear_faults(self) -> None:
        """Remove injected errors and delays."""
        self._faults.clear()
        self._delays.clear()

    def injected_faults(self) -> dict[str, Any]:
        """The fault knobs in force: ``{"errors": {prefix: status}, "delays_s": {prefix: s}, "serving": bool}``."""
        return {
            "errors": {p: f.status for p, f in self._faults.items()},
            "delays_s": dict(self._delays),
            "serving": self._runner is not None,
        }

    def expire_sessions(self) -> None:
        """Forget every session, as the controller does for idle sessions; clients must log in again."""
        self.sessions.clear()
        self._master.clear()

    async def close_subscriptions(self) -> None:
        """Close every subscription websocket and forget the subscriptions (as a controller restart does)."""
        self._subs.clear()
        for ws in list(self._websockets):
            await ws.close(code=1001, message=b"controller restarting")

    # ---- auth and sessions --------------------------------------------------------------------

    def _challenge(self, stale: bool = False) -> str:
        if self.profile == "rws2":
            return f'Basic realm="{REALM}"'
        now = time.monotonic()
        # The controller's nonce is base64 of "<16 hex>:<realm>:<hex time>:0" (the captured challenge).
        raw = f"{secrets.token_hex(8)}:{REALM}:{int(time.time() * 1000):x}:0"
        nonce = base64.b64encode(raw.encode()).decode()
        self._nonces[nonce] = now
        # Forget nonces past their lifetime so the table stays small.
        for n, t in list(self._nonces.items()):
            if now - t > self.nonce_lifetime_s:
                del self._nonces[n]
                self._nonce_nc.pop(n, None)
        return (
            f'Digest realm="{REALM}", domain="/", qop="auth", nonce="{nonce}", opaque="{DIGEST_OPAQUE}", '
            f'algorithm="MD5", stale="{"TRUE" if stale else "FALSE"}"'
        )

    def _check_authorization(self, req: web.Request) -> tuple[str | None, bool]:
        """Return (user or None, stale nonce)."""
        header = req.headers.get("Authorization", "")
        if self.profile == "rws2":
            if not header.lower().startswith("basic "):
                return None, False
            try:
                user, _, password = base64.b64decode(header[6:].strip()).decode().partition(":")
            except (ValueError, UnicodeDecodeError):
                return None, False
            ok = user in self.users and secrets.compare_digest(self.users[user], password)
            return (user if ok else None), False
        if not header.lower().startswith("digest "):
            return None, False
        p = parse_auth_params(header[7:])
        user, nonce = p.get("username", ""), p.get("nonce", "")
        if user not in self.users or p.get("realm") != REALM:
            return None, False
        issued = self._nonces.get(nonce)
        if issued is None or time.monotonic() - issued > self.nonce_lifetime_s:
            return None, True
        if p.get("qop") != "auth" or "cnonce" not in p or "nc" not in p or "response" not in p:
            return None, False
        try:
            nc = int(p["nc"], 16)
        except ValueError:
            return None, False
        if nc <= self._nonce_nc.get(nonce, 0):  # replayed nonce count
            return None, False
        if p.get("uri", "") not in (req.path_qs, req.raw_path):
            return None, False
        expected = digest_response(
            username=user, realm=REALM, password=self.users[user], method=req.method,
            uri=p.get("uri", ""), nonce=nonce, nc=p["nc"], cnonce=p["cnonce"],
        )  # fmt: skip
        if not secrets.compare_digest(expected, p["response"]):
            return None, False
        self._nonce_nc[nonce] = nc
        return user, False

    def _prune_sessions(self) -> None:
        now = time.monotonic()
        for sid, s in list(self.sessions.items()):
            if now - s.last_used_s > self.session_idle_s:
                self._drop_session(sid)

    def _drop_session(self, sid: str) -> None:
        self.sessions.pop(sid, None)
        for dom, holder in list(self._master.items()):
            if holder == sid:
                del self._master[dom]

    def _session_from_cookie(self, req: web.Request) -> Session | None:
        sid = req.cookies.get(SESSION_COOKIE)
        s = self.sessions.get(sid) if sid else None
        if s is not None:
            s.last_used_s = time.monotonic()
        return s

    def _session_by_abbcx(self, req: web.Request, user: str) -> Session | None:
        abbcx = req.cookies.get(ABBCX_COOKIE)
        if not abbcx:
            return None
        s = next((s for s in self.sessions.values() if s.abbcx == abbcx and s.user == user), None)
        if s is not None:
            s.last_used_s = time.monotonic()
        return s

    # ---- dispatch -----------------------------------------------------------------------------

    def _wants_json(self, req: web.Request) -> bool:
        if self.profile == "rws1":
            return req.query.get("json") == "1"
        return "json" in req.headers.get("Accept", "")

    def _error(self, req: web.Request, status: int, message: str, code: int) -> web.Response:
        """The controller's error answer: RWS 1.0 puts ``status`` under ``_embedded`` beside an empty
        ``_state``, RWS 2.0 at the top level; XHTML ``<div class="status">`` when JSON is not asked."""
        as_json = self._wants_json(req)
        base = f"{self.base_url}/"
        if as_json:
            st = {"code": code, "msg": message}
            if self.profile == "rws1":
                body: dict[str, Any] = {
                    "_links": {"base": {"href": base}},
                    "_embedded": {"status": st, "_state": []},
                }
            else:
                body = {"_links": {"base": {"href": base}}, "status": st}
            data = json.dumps(body).encode()
        else:
            title = "<title>rw</title>" if self.profile == "rws1" else ""
            data = (
                f'<?xml version="1.0" encoding="UTF-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>{title}'
                f'<base href="{_x(base)}"/></head><body><div class="status"><span class="code">{code}</span>'
                f'<span class="msg">{_x(message)}</span></div></body></html>'
            ).encode("ascii", "xmlcharrefreplace")
        return web.Response(
            status=status, body=data, headers={"Content-Type": CONTENT_TYPE[(self.profile, as_json)]}
        )

    def _bad_request(self, req: web.Request, err: RwsRequestError) -> web.Response:
        self.stats["bad_requests"] += 1
        now = time.monotonic()
        if now - self._last_bad_log_s > 1.0:  # rate limit: at most one line a second
            self._last_bad_log_s = now
            log.warning(
                "rws_bad_request", method=req.method, path=req.path, status=err.status, error=err.message,
                total=self.stats["bad_requests"],
            )  # fmt: skip
        return self._error(req, err.status, err.message, err.code)

    def _controller_error(self, err: ControllerError) -> RwsRequestError:
        """The HTTP status and return code the controller gives for a refusal of this kind."""
        v2 = self.profile == "rws2"
        if isinstance(err, SignalNotFound):
            return RwsRequestError(404, err.message, RC_SIGNAL_NOT_FOUND)
        if isinstance(err, SymbolNotFound):
            if err.message.startswith("task not found"):
                return RwsRequestError(400, err.message, RC_INVALID_PARAMETER)
            # RW6 answers an unknown symbol with 400 and its generic not-found code; RW7 with 404.
            return (
                RwsRequestError(404, err.message, RC_SYMBOL_NOT_FOUND_V2)
                if v2
                else RwsRequestError(400, err.message, RC_RESOURCE_NOT_FOUND)
            )
        if isinstance(err, StateRefused):
            return RwsRequestError(400, err.message, RC_PGM_STATE)
        if isinstance(err, AccessDenied):
            return RwsRequestError(403, err.message, err.code)
        if isinstance(err, RapidValueError):
            return RwsRequestError(400, err.message, RC_INVALID_PARAMETER)
        return RwsRequestError(err.http_status, err.message, err.code)

    async def _dispatch(self, req: web.Request) -> web.StreamResponse:
        self.stats["requests"] += 1
        path = req.path
        for prefix, delay in self._delays.items():
            if path.startswith(prefix):
                await asyncio.sleep(delay)
                break
        created: list[Session] = []
        resp = await self._handle(req, path, created)
        if created and not resp.prepared:  # a prepared websocket answer has sent its headers already
            # Also on an error answer: the session exists now, and the client must reuse it.
            secure = self.profile == "rws2"
            extra = {"secure": True, "samesite": "None"} if secure else {}
            resp.set_cookie(SESSION_COOKIE, created[0].sid, httponly=True, path="/", **extra)
            resp.set_cookie(ABBCX_COOKIE, created[0].abbcx, httponly=True, path="/", **extra)
        return resp

    async def _handle(self, req: web.Request, path: str, created: list[Session]) -> web.StreamResponse:
        try:
            self._prune_sessions()
            session = self._session_from_cookie(req)
            if session is None:
                user, stale = self._check_authorization(req)
                if user is None:
                    if req.headers.get("Authorization") and not stale:
                        self.stats["auth_failures"] += 1
                    return web.Response(
                        status=401,
                        headers={"WWW-Authenticate": self._challenge(stale)},
                        text="401 Unauthorized",
                    )
                session = self._session_by_abbcx(req, user)
                if session is None:
                    if len(self.sessions) >= self.max_sessions:
                        self.stats["rejected_busy"] += 1
                        return self._error(
                            req, 503, f"too many sessions ({self.max_sessions} active)", RC_BUSY
                        )
                    now = time.monotonic()
                    sid = f"{next(self._session_seq)}::http.session::{secrets.token_hex(16)}"
                    session = Session(sid, user, now, now, abbcx=str(next(self._abbcx_seq)))
                    self.sessions[session.sid] = session
                    self.stats["sessions_created"] += 1
                    created.append(session)
            return await self._route(req, session)
        except RwsRequestError as err:
            return self._bad_request(req, err)
        except ControllerError as err:
            return self._bad_request(req, self._controller_error(err))
        except Exception as err:  # never let one request take the server down
            log.exception("rws_handler_failed", method=req.method, path=path)
            return self._error(req, 500, f"internal error: {type(err).__name__}: {err}", -1)

    async def _route(self, req: web.Request, session: Session) -> web.StreamResponse:
        path = req.path
        for prefix, fault in self._faults.items():
            if path.startswith(prefix):
                return self._error(req, fault.status, fault.message, fault.code)
        if self.profile == "rws2":
            accept = req.headers.get("Accept", "")
            if rw.V2 not in accept.replace(" ", "") and not req.headers.get("Upgrade"):
                raise RwsRequestError(
                    406, f"Accept must name a ;v=2.0 media type, got {accept!r}", RC_NOT_ACCEPTABLE
                )
        # The controller names the same resource with or without a trailing slash.
        norm = path.rstrip("/") or "/"
        method = req.method
        path_known = False
        for m, regex, handler, mutating in self._routes:
            match = regex.fullmatch(norm)
            if match is None:
                continue
            path_known = True
            if m != method:
                continue
            form: dict[str, str] = {}
            multi: list[tuple[str, str]] = []
            if method in ("POST", "PUT"):
                form, multi = await self._read_form(req)
                if mutating and self.profile == "rws2":
                    self._check_mastership_v2(req, form, session)
            return await handler(_Request(req, session, match, form, self._wants_json(req), multi, norm))
        if path_known:
            raise RwsRequestError(405, f"method {method} not allowed on {path}", RC_METHOD_NOT_ALLOWED)
        raise RwsRequestError(404, f"Resource not found: {path}", RC_RESOURCE_NOT_FOUND)

    def _check_mastership_v2(self, req: web.Request, form: dict[str, str], session: Session) -> None:
        holder = self._master.get("edit")
        if holder is not None and holder != session.sid:
            raise RwsRequestError(403, "Requested resource is held by someone else", RC_HELD_BY_OTHER)
        implicit = req.query.get("mastership") == "implicit" or form.get("mastership") == "implicit"
        if not (implicit or "edit" in session.mastership):
            raise RwsRequestError(
                403, "The user does not have required mastership for the operation.", RC_NO_MASTERSHIP
            )

    def _implicit_mastership_v1(self, r: _Request, domain: str = "edit") -> None:
        # RW6 takes mastership implicitly for a write, unless another client holds it.
        holder = self._master.get(domain)
        if holder is not None and holder != r.session.sid:
            raise RwsRequestError(400, "Requested resource is held by someone else", RC_RESOURCE_NOT_FOUND)

    async def _read_form(self, req: web.Request) -> tuple[dict[str, str], list[tuple[str, str]]]:
        ctype = req.headers.get("Content-Type", "")
        raw = await req.read()
        if raw and "x-www-form-urlencoded" not in ctype:
            raise RwsRequestError(415, f"Content-Type must be {rw.FORM}, got {ctype!r}")
        if self.profile == "rws2" and raw and rw.V2 not in ctype.replace(" ", ""):
            raise RwsRequestError(415, f"Content-Type must carry ;v=2.0, got {ctype!r}", RC_NOT_ACCEPTABLE)
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise RwsRequestError(400, f"form body is not UTF-8 at byte {err.start}: {raw[:40]!r}") from err
        form: dict[str, str] = {}
        multi: list[tuple[str, str]] = []
        for part in text.split("&"):
            if not part:
                continue
            key, sep, value = part.partition("=")
            if not sep:
                raise RwsRequestError(400, f"form field without '=': {part[:40]!r}")
            k, v = unquote(key.replace("+", " ")), unquote(value.replace("+", " "))
            form[k] = v
            multi.append((k, v))
        return form, multi

    # ---- body rendering -----------------------------------------------------------------------

    def _respond(
        self,
        r: _Request,
        items: list[dict[str, Any]],
        title: str,
        *,
        listing: bool = False,
        next_href: str | None = None,
        status: bool = True,
    ) -> web.Response:
        """A success answer: ``items`` (``_type``, ``_title``, fields; ``_links`` optional) in the profile's
        envelope. ``_links.base`` is the resource's parent, ``self`` relative to it (query echoed)."""
        base_path, rel = self._base_and_self(r.path)
        base = f"{self.base_url}{base_path}"
        self_href = rel + (f"?{r.req.query_string}" if r.req.query_string else "")
        if not r.json:
            data = self._xhtml(items, title, base, self_href, next_href).encode("ascii", "xmlcharrefreplace")
        else:
            links: dict[str, Any] = {"base": {"href": base}, "self": {"href": self_href}}
            if next_href is not None:
                links["next"] = {"href": next_href}
            if self.profile == "rws1":
                body: dict[str, Any] = {"_links": links, "_embedded": {"_state": items}}
            elif listing:
                body = {"_links": links, "_embedded": {"resources": items}}
            else:
                body = {"_links": links, **({"status": {"code": RC_OK}} if status else {}), "state": items}
            data = json.dumps(body).encode()
        return web.Response(body=data, headers={"Content-Type": CONTENT_TYPE[(self.profile, r.json)]})

    @staticmethod
    def _base_and_self(path: str) -> tuple[str, str]:
        """``_links.base`` and ``self`` as the captured answers have them: the service root
        (``/rw/rapid/`` + ``tasks``), or the resource itself (``/rw/panel/ctrlstate/`` + ``""``) for
        panel, motion-system, system and the event-log root."""
        parts = path.strip("/").split("/")
        if len(parts) < 2 or f"/{parts[0]}" != rw.SERVICES:
            return "/", path.lstrip("/")
        if parts[1] in ("panel", "motionsystem", "system") or path == rw.ELOG:
            return path + "/", ""
        return f"{rw.SERVICES}/{parts[1]}/", "/".join(parts[2:])

    def _xhtml(
        self, items: list[dict[str, Any]], title: str, base: str, self_href: str, next_href: str | None
    ) -> str:
        lis = []
        for it in items:
            inner = []
            link = it.get("_links", {}).get("self", {}).get("href")
            if link is not None:
                inner.append(f'<a href="{_x(link)}" rel="self"/>')
            for k, v in it.items():
                if k.startswith("_"):
                    continue
                if isinstance(v, list):  # elog arguments
                    inner += [
                        f'<span class="arg{i}" type="{_x(a["type"])}">{_x(a["value"])}</span>'
                        for i, a in enumerate(v, start=1)
                    ]
                else:
                    inner.append(f'<span class="{_x(k)}">{_x(v)}</span>')
            lis.append(f'<li class="{_x(it["_type"])}" title="{_x(it["_title"])}">{"".join(inner)}</li>')
        head_title = f"<title>{_x(title)}</title>" if self.profile == "rws1" else ""
        nxt = f'<a href="{_x(next_href)}" rel="next"/>' if next_href is not None else ""
        return (
            f'<?xml version="1.0" encoding="UTF-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>'
            f'{head_title}<base href="{_x(base)}"/></head><body><div class="state">'
            f'<a href="{_x(self_href)}" rel="self"/>{nxt}<ul>{"".join(lis)}</ul></div></body></html>'
        )

    def _page(
        self, r: _Request, items: list[dict[str, Any]], leaf: str
    ) -> tuple[list[dict[str, Any]], str | None]:
        """``start`` / ``limit`` paging (at most 100 items a page); returns the page and the next link."""
        try:
            start = int(r.req.query.get("start", "0"))
            limit = int(r.req.query.get("limit", str(PAGE_LIMIT_MAX)))
        except ValueError as err:
            raise RwsRequestError(400, f"start and limit must be integers: {err}") from err
        if start < 0 or limit <= 0:
            raise RwsRequestError(400, f"start must be >= 0 and limit > 0, got start={start} limit={limit}")
        limit = min(limit, PAGE_LIMIT_MAX)
        page = items[start : start + limit]
        if start + limit >= len(items):
            return page, None
        keep = [
            f"{k}={quote(v, safe='')}" for k, v in r.req.query.items() if k not in ("start", "limit", "json")
        ]
        return page, f"{leaf}?{'&'.join([*keep, f'start={start + limit}', f'limit={limit}'])}"

    @staticmethod
    def _no_content() -> web.Response:
        return web.Response(status=204)

    # ---- routes -------------------------------------------------------------------------------

    def _build_routes(self) -> list[tuple[str, re.Pattern[str], Handler, bool]]:
        """(method, path regex, handler, mutating). RWS 1.0 chooses operations with ``?action=``."""
        v2 = self.profile == "rws2"
        # the vocabulary's paths hold no regular-expression metacharacters: used as they are
        task = rw.RAPID_TASKS + r"/(?P<task>[^/;]+)"
        sig = rw.IOSYSTEM_SIGNALS + r"/(?P<path>[^;]+?)"
        mu = rw.MECHUNITS + r"/(?P<mu>[^/]+)"
        routes: list[tuple[str, str, Handler, bool]] = [
            ("GET", rw.PANEL_OPMODE, self._get_opmode, False),
            ("GET", rw.PANEL_SPEEDRATIO, self._get_speedratio, False),
            ("GET", rw.RAPID_EXECUTION, self._get_execution, False),
            ("GET", rw.RAPID_TASKS, self._get_tasks, False),
            ("GET", task, self._get_task, False),
            ("GET", rw.IOSYSTEM_SIGNALS, self._get_signals, False),
            ("GET", rw.ELOG, self._get_elog_domains, False),
            ("GET", rw.ELOG + r"/(?P<domain>\d+)", self._get_elog, False),
            ("GET", rw.ELOG + r"/(?P<domain>\d+)/(?P<seq>\d+)", self._get_elog_message, False),
            ("GET", mu + r"/jointtarget", self._get_jointtarget, False),
            ("GET", mu + r"/robtarget", self._get_robtarget, False),
            ("GET", rw.SYSTEM, self._get_system, False),
            ("GET", rw.LOGOUT, self._logout, False),
            ("POST", rw.SUBSCRIPTION, self._subscribe, False),
            ("PUT", rw.SUBSCRIPTION + r"/(?P<sub>\d+)", self._subscription_add, False),
            ("DELETE", rw.SUBSCRIPTION + r"/(?P<sub>\d+)", self._unsubscribe_route, False),
            ("GET", rw.POLL + r"/(?P<sub>\d+)", self._poll_ws, False),
        ]
        symbol = r"/(?P<task>[^/]+)(?:/(?P<module>[^/]+))?/(?P<name>[^/;]+)"
        sym_v2 = rw.RAPID_SYMBOL_V2 + symbol + "/data"
        sym_v1 = rw.RAPID_SYMBOL_DATA + symbol
        if v2:
            routes += [
                ("GET", rw.PANEL_CTRL_STATE_V2, self._get_ctrlstate, False),
                ("POST", rw.PANEL_CTRL_STATE_V2, self._set_ctrlstate, True),
                ("POST", rw.PANEL_SPEEDRATIO, self._set_speedratio, True),
                ("POST", rw.execution_action_path("start"), self._start, True),
                ("POST", rw.execution_action_path("stop"), self._stop, True),
                ("POST", rw.execution_action_path("resetpp"), self._resetpp, True),
                ("POST", task + r"/activate", self._activate, True),
                ("POST", task + r"/deactivate", self._deactivate, True),
                ("GET", task + r"/modules", self._get_modules, False),
                ("GET", task + r"/modules/(?P<module>[^/]+)", self._get_module, False),
                ("GET", sym_v2, self._get_var, False),
                ("POST", sym_v2, self._set_var, True),
                ("POST", sig + r"/set-value", self._set_signal, True),
                ("GET", sig, self._get_signal, False),
                ("POST", rw.MASTERSHIP + "/request", self._mastership_request, False),
                ("POST", rw.MASTERSHIP + "/release", self._mastership_release, False),
                (
                    "POST",
                    rw.MASTERSHIP + r"/(?P<domain>edit|motion)/request",
                    self._mastership_request,
                    False,
                ),
                (
                    "POST",
                    rw.MASTERSHIP + r"/(?P<domain>edit|motion)/release",
                    self._mastership_release,
                    False,
                ),
                ("GET", rw.MASTERSHIP + r"/(?P<domain>edit|motion)", self._get_mastership, False),
            ]
        else:
            routes += [
                ("GET", rw.PANEL_CTRLSTATE, self._get_ctrlstate, False),
                ("POST", rw.PANEL_CTRLSTATE, self._rws1_action, True),
                ("POST", rw.PANEL_SPEEDRATIO, self._rws1_action, True),
                ("POST", rw.RAPID_EXECUTION, self._rws1_action, True),
                ("POST", task, self._rws1_action, True),
                ("GET", rw.RAPID_MODULES, self._get_modules, False),
                ("GET", rw.RAPID_MODULES + r"/(?P<module>[^/]+)", self._get_module, False),
                ("GET", sym_v1, self._get_var, False),
                ("POST", sym_v1, self._rws1_action, True),
                ("GET", sig, self._get_signal, False),
                ("POST", sig, self._rws1_action, True),
                ("POST", rw.MASTERSHIP, self._rws1_action, False),
                ("POST", rw.MASTERSHIP + r"/(?P<domain>rapid|motion|cfg)", self._rws1_action, False),
                ("GET", rw.MASTERSHIP + r"/(?P<domain>rapid|motion|cfg)", self._get_mastership, False),
            ]
        return [(m, re.compile(p), h, mut) for m, p, h, mut in routes]

    async def _rws1_action(self, r: _Request) -> web.StreamResponse:
        # RWS 1.0 selects the operation with ?action=...; map it onto the shared handlers.
        action = r.req.query.get("action", "")
        path = r.path
        table: dict[tuple[str, str], Handler] = {
            (rw.PANEL_CTRLSTATE, "setctrlstate"): self._set_ctrlstate,
            (rw.PANEL_SPEEDRATIO, "setspeedratio"): self._set_speedratio,
            (rw.RAPID_EXECUTION, "start"): self._start,
            (rw.RAPID_EXECUTION, "stop"): self._stop,
            (rw.RAPID_EXECUTION, "resetpp"): self._resetpp,
            (rw.MASTERSHIP, "request"): self._mastership_request,
            (rw.MASTERSHIP, "release"): self._mastership_release,
        }
        handler = table.get((path, action))
        if handler is None:
            if path.startswith(rw.RAPID_SYMBOL_DATA + "/") and action == "set":
                handler = self._set_var
            elif path.startswith(rw.IOSYSTEM_SIGNALS + "/") and action == "set":
                handler = self._set_signal
            elif path.startswith(rw.RAPID_TASKS + "/") and action in ("activate", "deactivate"):
                handler = self._activate if action == "activate" else self._deactivate
            elif path.startswith(rw.MASTERSHIP + "/") and action in ("request", "release"):
                handler = self._mastership_request if action == "request" else self._mastership_release
        if handler is None:
            raise RwsRequestError(400, f"Invalid action parameter value: {action!r} for {path}")
        return await handler(r)

    @staticmethod
    def _field(r: _Request, name: str) -> str:
        value = r.form.get(name)
        if value is None:
            raise RwsRequestError(400, f"missing form field {name!r}")
        return value

    @staticmethod
    def _choice(r: _Request, name: str, allowed: tuple[str, ...], default: str | None = None) -> str | None:
        value = r.form.get(name, default)
        if value is not None and value not in allowed:
            raise RwsRequestError(400, f"{name} must be one of {', '.join(allowed)}, got {value!r}")
        return value

    def _task_name(self, name: str) -> str:
        """The model's task of ``name``; RobotWare 7 answers task names in any case, RobotWare 6 exactly."""
        for t in self.model.tasks_active:
            if t == name or (self.profile == "rws2" and t.lower() == name.lower()):
                return t
        raise SymbolNotFound(f"task not found: Task {name} does not exist", code=RC_INVALID_PARAMETER)

    # ---- panel --------------------------------------------------------------------------------

    async def _get_ctrlstate(self, r: _Request) -> web.Response:
        title = "ctrl-state" if self.profile == "rws2" else "ctrlstate"
        item = {"_type": "pnl-ctrlstate", "_title": title, "ctrlstate": self.model.ctrl_state}
        return self._respond(r, [item], "panel")

    async def _set_ctrlstate(self, r: _Request) -> web.Response:
        state = self._field(r, "ctrl-state")
        if state == rw.MOTORON:
            self.model.motors_on()
        elif state == rw.MOTOROFF:
            self.model.motors_off()
        else:
            raise RwsRequestError(400, f"ctrl-state must be {rw.MOTORON} or {rw.MOTOROFF}, got {state!r}")
        return self._no_content()

    async def _get_opmode(self, r: _Request) -> web.Response:
        return self._respond(
            r, [{"_type": "pnl-opmode", "_title": "opmode", "opmode": self.model.opmode}], "panel"
        )

    async def _get_speedratio(self, r: _Request) -> web.Response:
        item = {
            "_type": "pnl-speedratio",
            "_title": "speedratio",
            "speedratio": str(self.model.speed_ratio_pct),
        }
        return self._respond(r, [item], "panel")

    async def _set_speedratio(self, r: _Request) -> web.Response:
        text = self._field(r, "speed-ratio")
        if not text.isdigit() or not 0 <= int(text) <= 100:
            raise RwsRequestError(400, f"speed-ratio must be an integer 0..100, got {text!r}")
        self.model.speed_ratio_pct = int(text)
        return self._no_content()

    # ---- RAPID execution and tasks ------------------------------------------------------------

    async def _get_execution(self, r: _Request) -> web.Response:
        item = {
            "_type": "rap-execution",
            "_title": "execution",
            "ctrlexecstate": self.model.rapid_state,
            "cycle": self._cycle,
        }
        return self._respond(r, [item], "rapid")

    async def _start(self, r: _Request) -> web.Response:
        # The documented start parameters (RWS 1.0 manual, "Start RAPID execution"); all optional here.
        self._choice(r, "regain", ("continue", "regain", "clear", "enterconsume"))
        self._choice(
            r, "execmode", ("continue", "stepin", "stepover", "stepout", "stepback", "steplast", "stepmotion")
        )
        cycle = self._choice(r, "cycle", ("forever", "asis", "once", "oncedone"))
        self._choice(r, "condition", ("none", "callchain"))
        self._choice(r, "stopatbp", ("disabled", "enabled"))
        self._choice(r, "alltaskbytsp", ("true", "false"))
        if self.profile == "rws1":
            self._implicit_mastership_v1(r)
        self.model.start_rapid()
        if cycle not in (None, "asis"):
            self._cycle = cycle
        return self._no_content()

    async def _stop(self, r: _Request) -> web.Response:
        self._choice(r, "stopmode", ("cycle", "instr", "stop", "qstop"))
        self._choice(r, "usetsp", ("normal", "alltask"))
        self.model.stop_rapid()
        return self._no_content()

    async def _resetpp(self, r: _Request) -> web.Response:
        if self.profile == "rws1":
            self._implicit_mastership_v1(r)
        self.model.reset_pp()
        return self._no_content()

    def _task_item(self, name: str, listing: bool) -> dict[str, Any]:
        running = self.model.rapid_state == rw.RUNNING and name == self.model.task
        item: dict[str, Any] = {
            "_type": "rap-task-li" if listing else "rap-task",
            "_title": name,
            "name": name,
            "type": "normal" if self.profile == "rws2" else "norm",
            "taskstate": "linked",
            "excstate": "started" if running else "ready" if name == self.model.task else "stopped",
            "active": "On" if self.model.tasks_active[name] else "Off",
            "motiontask": "TRUE" if name == self.model.task else "FALSE",
        }
        if listing:
            item["_links"] = {"self": {"href": f"tasks/{name}"}}
        else:  # the fields of the manual's task page (values of a normal motion task)
            item.update({"tasktype": "Normal", "trust": "None", "taskID": "1", "execmode": "continous",
                         "exectype": "None", "prodentrypt": "main", "bind_ref": "True",
                         "task_in_forgnd": "True"})  # fmt: skip
        return item

    async def _get_tasks(self, r: _Request) -> web.Response:
        items = [self._task_item(t, True) for t in self.model.tasks_active]
        if self.profile == "rws2":
            items.insert(
                0, {"_links": {"self": {"href": "tasks/spy"}}, "_type": "rap-tasks-spy-li", "_title": "spy"}
            )
        return self._respond(r, items, "rapid", listing=True)

    async def _get_task(self, r: _Request) -> web.Response:
        return self._respond(r, [self._task_item(self._task_name(r.match.group("task")), False)], "rapid")

    async def _activate(self, r: _Request) -> web.Response:
        self.model.set_task_active(self._task_name(r.match.group("task")), True)
        return self._no_content()

    async def _deactivate(self, r: _Request) -> web.Response:
        self.model.set_task_active(self._task_name(r.match.group("task")), False)
        return self._no_content()

    def _modules_task(self, r: _Request) -> str:
        g = r.match.groupdict()
        name = g.get("task") or r.req.query.get("task")
        if not name:
            raise RwsRequestError(400, "the task query parameter is missing (modules?task=T_ROB1)")
        return self._task_name(name)

    async def _get_modules(self, r: _Request) -> web.Response:
        task = self._modules_task(r)
        items = [
            {"_type": "rap-module-info-li", "_title": f"{task}/{name}", "name": name, "type": mtype}
            for name, mtype in self.model.modules(task)
        ]
        # RobotWare 7 answers the module list in "state", not "_embedded" (captured answer).
        return self._respond(r, items, "rapid")

    async def _get_module(self, r: _Request) -> web.Response:
        task = self._modules_task(r)
        name = r.match.group("module")
        found = [(n, t) for n, t in self.model.modules(task) if n == name]
        if not found:
            if self.profile == "rws2":
                raise RwsRequestError(
                    400, f"module name/parameter is invalid or missing: {name}", RC_MODULE_INVALID_V2
                )
            raise RwsRequestError(404, f"Resource not found: module {name}", RC_RESOURCE_NOT_FOUND)
        item = {"_type": "rap-module", "_title": f"{task}/{name}", "modname": name, "type": found[0][1]}
        return self._respond(r, [item], "rapid")

    # ---- RAPID data ---------------------------------------------------------------------------

    async def _get_var(self, r: _Request) -> web.Response:
        g = r.match.groupdict()
        var = self.model.var_info(self._task_name(g["task"]), g["module"], g["name"])
        item = {
            "_type": "rap-data",
            "_title": f"RAPID/{var.task}/{var.module}/{var.name}",
            "value": var.value,
        }
        return self._respond(r, [item], "rapid")

    async def _set_var(self, r: _Request) -> web.Response:
        g = r.match.groupdict()
        if self.profile == "rws1":
            self._implicit_mastership_v1(r)
        self.model.set_var(self._task_name(g["task"]), g["module"], g["name"], self._field(r, "value"))
        return self._no_content()

    # ---- IO -----------------------------------------------------------------------------------

    def _signal_from_path(self, r: _Request) -> str:
        parts = r.match.group("path").split("/")
        if len(parts) not in (1, 3):
            raise RwsRequestError(
                404, f"Invalid IO signal name passed in the uri: {r.req.path}", RC_SIGNAL_NOT_FOUND
            )
        sig = self.model.signal(parts[-1])
        if len(parts) == 3 and (parts[0], parts[1]) != (sig.network, sig.device):
            raise RwsRequestError(404, f"IO signal not found: {'/'.join(parts)}", RC_SIGNAL_NOT_FOUND)
        return sig.name

    def _signal_item(self, name: str, listing: bool) -> dict[str, Any]:
        sig = self.model.signal(name)
        path = f"{sig.network}/{sig.device}/{sig.name}"
        item: dict[str, Any] = {
            "_type": "ios-signal-li" if listing or self.profile == "rws2" else "ios-signal",
            "_title": path,
            "name": sig.name,
            "type": sig.signal_type,
            "category": "",
            "lvalue": format_num(sig.lvalue),
            "lstate": "not simulated",
        }
        if listing:
            item["_links"] = {"self": {"href": f"signals/{path}"}}
        else:
            item.update(
                {
                    "unitnm": sig.device,
                    "phstate": "valid",
                    "pvalue": format_num(sig.lvalue),
                    "ltime-sec": "0",
                    "ltime-microsec": "0",
                    "ptime-sec": "0",
                    "ptime-microsec": "0",
                    "quality": "1",
                }
            )
        return item

    async def _get_signals(self, r: _Request) -> web.Response:
        items = [self._signal_item(s.name, True) for s in self.model.signals]
        page, nxt = self._page(r, items, "signals")
        return self._respond(r, page, "io", listing=True, next_href=nxt)

    async def _get_signal(self, r: _Request) -> web.Response:
        return self._respond(r, [self._signal_item(self._signal_from_path(r), False)], "io")

    async def _set_signal(self, r: _Request) -> web.Response:
        name = self._signal_from_path(r)
        text = self._field(r, "lvalue")
        try:
            value = float(text)
        except ValueError as err:
            raise RwsRequestError(400, f"lvalue must be a number, got {text!r}") from err
        try:
            self.model.set_io(name, value)
        except AccessDenied as err:
            raise RwsRequestError(403, f"Rejected: {err.message}", RC_SIGNAL_REJECTED) from err
        return self._no_content()

    # ---- event log ----------------------------------------------------------------------------

    def _elog_item(self, domain: int, ev: Any, lang: str | None, listing: bool) -> dict[str, Any]:
        item: dict[str, Any] = {
            "_type": "elog-message-li" if listing else "elog-message",
            "_title": rw.elog_path(domain, ev.seqnum),
            "msgtype": str(ev.msgtype),
            "code": str(ev.code),
            "tstamp": ev.tstamp,
        }
        if lang is not None:  # the texts come only in a language that was asked for
            item.update({"title": ev.title, "desc": ev.desc, "conseqs": ev.conseqs, "causes": ev.causes,
                         "actions": ev.actions})  # fmt: skip
        item["argc"] = str(len(ev.args))
        if ev.args:
            item["argv"] = [{"type": "string", "value": a} for a in ev.args]
        if listing:
            q = f"?lang={lang}" if lang is not None else ""
            item["_links"] = {"self": {"href": f"{domain}/{ev.seqnum}{q}"}}
        return item

    def _elog_domain(self, r: _Request) -> int:
        domain = int(r.match.group("domain"))
        if domain not in ELOG_DOMAINS:
            raise RwsRequestError(400, f"Invalid action parameter value: event log domain {domain}")
        return domain

    def _lang(self, r: _Request) -> str | None:
        lang = r.req.query.get("lang")
        if lang is not None and lang not in (
            "en",
            "de",
            "fr",
            "es",
            "it",
            "zh",
            "ja",
            "sv",
            "ko",
            "pt",
            "cs",
        ):
            raise RwsRequestError(400, f"Invalid action parameter value: lang={lang!r}")
        return lang

    async def _get_elog_domains(self, r: _Request) -> web.Response:
        items = [
            {"_links": {"self": {"href": str(d)}}, "_type": "elog-domain-li", "_title": str(d),
             "numevts": str(len(self.model.events) if d == 0 else 0), "buffsize": "1000" if d == 0 else "50"}
            for d in ELOG_DOMAINS
        ]  # fmt: skip
        return self._respond(r, items, "Elog", listing=True)

    async def _get_elog(self, r: _Request) -> web.Response:
        domain = self._elog_domain(r)
        lang = self._lang(r)
        events = self.model.events if domain == 0 else []  # newest first
        items = [self._elog_item(domain, ev, lang, True) for ev in events]
        page, nxt = self._page(r, items, str(domain))
        return self._respond(r, page, "Elog", listing=True, next_href=nxt)

    async def _get_elog_message(self, r: _Request) -> web.Response:
        domain = self._elog_domain(r)
        lang = self._lang(r)
        seq = int(r.match.group("seq"))
        ev = next((e for e in self.model.events if e.seqnum == seq), None) if domain == 0 else None
        if ev is None:
            raise RwsRequestError(
                404, f"Resource not found: event log message {domain}/{seq}", RC_RESOURCE_NOT_FOUND
            )
        return self._respond(r, [self._elog_item(domain, ev, lang, False)], "Elog")

    # ---- motion system, system ----------------------------------------------------------------

    def _check_mechunit(self, r: _Request) -> None:
        if r.match.group("mu") != self.mechunit:
            raise RwsRequestError(
                404, f"Resource not found: mechanical unit {r.match.group('mu')}", RC_RESOURCE_NOT_FOUND
            )

    async def _get_jointtarget(self, r: _Request) -> web.Response:
        self._check_mechunit(r)
        q_deg, _, _ = self.model.position()
        item: dict[str, Any] = {"_type": "ms-jointtarget", "_title": self.mechunit}
        item.update({f"rax_{i + 1}": format_num(round(float(v), 6)) for i, v in enumerate(q_deg)})
        item.update(self._external_axes_items())
        return self._respond(r, [item], "motionsystem")

    async def _get_robtarget(self, r: _Request) -> web.Response:
        self._check_mechunit(r)
        coord = r.req.query.get("coordinate", "Base")
        if coord not in ("Base", "World"):
            raise RwsRequestError(400, f"coordinate {coord!r} not supported by the simulator (Base, World)")
        for key in ("tool", "wobj"):
            val = r.req.query.get(key, "")
            if val not in ("", "tool0" if key == "tool" else "wobj0"):
                raise RwsRequestError(400, f"{key} {val!r} not defined in the simulator (only tool0 / wobj0)")
        _, pos_mm, quat = self.model.position()
        item: dict[str, Any] = {"_type": "ms-robtargets", "_title": self.mechunit}
        item.update({k: format_num(round(float(v), 6)) for k, v in zip("xyz", pos_mm, strict=True)})
        item.update({f"q{i + 1}": format_num(round(float(v), 9)) for i, v in enumerate(quat)})
        item.update({"cf1": "0", "cf4": "0", "cf6": "0", "cfx": "0"})
        item.update(self._external_axes_items())
        return self._respond(r, [item], "motionsystem")

    def _external_axes_items(self) -> dict[str, str]:
        """``eax_a..eax_f`` of a jointtarget / robtarget: an additional axis of the robot's motion group
        (a track, mm) in ``eax_a``, 9E+09 where an axis is unused."""
        return {
            f"eax_{c}": format_extax(v) for c, v in zip("abcdef", self.model.external_axes(), strict=True)
        }

    async def _get_system(self, r: _Request) -> web.Response:
        major, minor = ("7", "16") if self.profile == "rws2" else ("6", "15")
        item = {"_type": "sys-system", "_title": "system", "major": major, "minor": minor, "name": "cellctl-sim",
                "rwversion": f"{major}.{minor}.0", "rwversionname": f"{major}.{minor}.0"}  # fmt: skip
        return self._respond(r, [item], "system")

    async def _logout(self, r: _Request) -> web.Response:
        self._drop_session(r.session.sid)
        for sid, sub in list(self._subs.items()):
            if sub.session_id == r.session.sid:
                del self._subs[sid]
        resp = self._no_content()
        resp.del_cookie(SESSION_COOKIE)
        resp.del_cookie(ABBCX_COOKIE)
        return resp

    # ---- mastership ---------------------------------------------------------------------------

    def _mastership_domains(self, r: _Request) -> tuple[str, ...]:
        dom = r.match.groupdict().get("domain")
        if dom is None:
            return ("edit", "motion")
        return ("edit",) if dom in ("edit", "rapid", "cfg") else ("motion",)

    async def _mastership_request(self, r: _Request) -> web.Response:
        domains = self._mastership_domains(r)
        for dom in domains:
            holder = self._master.get(dom)
            if holder is not None and holder != r.session.sid:
                raise RwsRequestError(403, "Requested resource is held by someone else", RC_HELD_BY_OTHER)
        for dom in domains:
            self._master[dom] = r.session.sid
            r.session.mastership.add(dom)
        return self._no_content()

    async def _mastership_release(self, r: _Request) -> web.Response:
        for dom in self._mastership_domains(r):
            if self._master.get(dom) == r.session.sid:
                del self._master[dom]
            r.session.mastership.discard(dom)
        return self._no_content()

    async def _get_mastership(self, r: _Request) -> web.Response:
        (dom,) = self._mastership_domains(r)
        holder = self._master.get(dom)
        state = "nomaster" if holder is None else "remote"
        item = {"_type": "msh-resource", "_title": r.match.group("domain"), "mastership": state}
        return self._respond(r, [item], "mastership")

    # ---- subscriptions ------------------------------------------------------------------------

    _RESOURCE_RE = re.compile(
        "^("
        + "|".join(
            re.escape(p)
            for p in (rw.PANEL_CTRLSTATE, rw.PANEL_OPMODE, rw.EXECUTION_SUBSCRIPTION, rw.elog_path(0))
        )
        + f"|{re.escape(rw.RAPID_SYMBOL_DATA)}/[^/;]+(/[^/;]+)?/[^/;]+;value"
        + f"|{re.escape(rw.RAPID_SYMBOL_V2)}/[^/;]+(/[^/;]+)?/[^/;]+/data;value"
        + f"|{re.escape(rw.IOSYSTEM_SIGNALS)}/[^;]+;state)$"
    )
    #: a RAPID value's subscription resource in either spelling: task, module (or None), name
    _SYMBOL_RESOURCE_RE = re.compile(
        f"^(?:{re.escape(rw.RAPID_SYMBOL_DATA)}|{re.escape(rw.RAPID_SYMBOL_V2)})"
        r"/([^/;]+)(?:/([^/;]+))?/([^/;]+?)(?:/data)?;value$"
    )

    def _parse_resources(self, r: _Request) -> dict[str, tuple[str, int]]:
        """resource key -> (resource path, priority) of a subscription form."""
        indices = [v for k, v in r.multi if k == "resources"]
        if not indices:
            raise RwsRequestError(400, "subscription needs at least one 'resources' field")
        resources: dict[str, tuple[str, int]] = {}
        for idx in indices:
            res = r.form.get(idx)
            if res is None:
                raise RwsRequestError(400, f"resources={idx} names no field {idx!r}")
            if not self._RESOURCE_RE.match(res):
                raise RwsRequestError(400, f"resource {res!r} cannot be subscribed to")
            prio_text = r.form.get(f"{idx}-p", "1")
            if prio_text not in ("0", "1", "2"):
                raise RwsRequestError(400, f"field {idx}-p must be 0, 1 or 2, got {prio_text!r}")
            prio = int(prio_text)
            if prio == 2 and not (res.endswith(";state") or res.endswith(";value")):
                raise RwsRequestError(400, f"priority 2 is allowed only for IO signals and RAPID data: {res}")
            resources[self._resource_key(res)] = (res, prio)
        return resources

    @staticmethod
    def _resource_key(res: str) -> str:
        # Signals may be named with or without network/device; key them by signal name.
        signals = rw.IOSYSTEM_SIGNALS + "/"
        if res.startswith(signals):
            return "signal:" + res[len(signals) :].split(";")[0].split("/")[-1]
        m = RwsServer._SYMBOL_RESOURCE_RE.match(res)
        if m:
            return f"rapid:{m.group(1)}:{m.group(3)}"
        return res

    def _ws_url(self, sub_id: str) -> str:
        return f"{'wss' if self.profile == 'rws2' else 'ws'}://{self.host}:{self.port}{rw.POLL}/{sub_id}"

    def _event_frame(self, sub_id: str, lis: list[str]) -> str:
        """An event page as the controller sends it, in the 201 answer and on the websocket."""
        title = "<title>Event</title>" if self.profile == "rws1" else ""
        # One line: abb-robot-client finds the websocket URL and the values with line-bound regexes.
        return (
            f'<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>{title}'
            f'<base href="{self.base_url}/"/></head><body><div class="state">'
            f'<a href="subscription/{sub_id}" rel="group"></a><a href="{self._ws_url(sub_id)}" rel="self"></a>'
            f'<a href="subscription/{sub_id}?action=show" rel="action"></a><ul>{"".join(lis)}</ul></div>'
            "</body></html>"
        )

    def _initial_event(self, key: str, res: str) -> str | None:
        """The current value of a subscribed resource, as an event item (sent in the 201 answer)."""
        m = self.model
        if key == rw.PANEL_CTRLSTATE:
            return self._event_li("ctrlstate", {"ctrlstate": m.ctrl_state})
        if key == rw.PANEL_OPMODE:
            return self._event_li("opmode", {"opmode": m.opmode})
        if key == rw.EXECUTION_SUBSCRIPTION:
            return self._event_li("execution", {"ctrlexecstate": m.rapid_state})
        if key.startswith("signal:"):
            try:
                sig = m.signal(key[len("signal:") :])
            except SignalNotFound as err:
                raise RwsRequestError(404, err.message, RC_SIGNAL_NOT_FOUND) from err
            return self._event_li("signal", {"name": sig.name, "lvalue": sig.lvalue})
        if key.startswith("rapid:"):
            _, task, name = key.split(":", 2)
            try:
                var = m.var_info(self._task_name(task), None, name)
            except SymbolNotFound as err:
                raise self._controller_error(err) from err
            return self._event_li(
                "rapid-data", {"task": var.task, "module": var.module, "name": var.name, "value": var.value}
            )
        return None  # the event log: no initial value

    async def _subscribe(self, r: _Request) -> web.Response:
        resources = self._parse_resources(r)
        self._sub_seq += 1
        sub = _Subscription(str(self._sub_seq), r.session.sid, {k: p for k, (_, p) in resources.items()})
        lis = [li for k, (res, _) in resources.items() if (li := self._initial_event(k, res)) is not None]
        self.stats["subscriptions_created"] += 1
        self._subs[sub.sid] = sub
        body = self._event_frame(sub.sid, lis).encode("ascii", "xmlcharrefreplace")
        # 201 with an XHTML body even when JSON was asked for (the controller does; clients regex it).
        return web.Response(
            status=201,
            body=body,
            headers={"Location": self._ws_url(sub.sid), "Content-Type": CONTENT_TYPE[(self.profile, False)]},
        )

    def _own_subscription(self, r: _Request) -> _Subscription:
        sub = self._subs.get(r.match.group("sub"))
        if sub is None or sub.session_id != r.session.sid:
            raise RwsRequestError(
                404, f"Resource not found: subscription {r.match.group('sub')}", RC_RESOURCE_NOT_FOUND
            )
        return sub

    async def _subscription_add(self, r: _Request) -> web.Response:
        sub = self._own_subscription(r)
        sub.resources.update({k: p for k, (_, p) in self._parse_resources(r).items()})
        return self._no_content()

    async def _unsubscribe_route(self, r: _Request) -> web.Response:
        sub = self._own_subscription(r)
        del self._subs[sub.sid]
        await sub.queue.put("")  # wakes the websocket writer so it closes
        return self._no_content()

    async def _poll_ws(self, r: _Request) -> web.StreamResponse:
        sub = self._own_subscription(r)
        proto = rw.WS_PROTOCOL[self.profile]
        ws = web.WebSocketResponse(protocols=(proto,), heartbeat=None)
        if not ws.can_prepare(r.req).ok:
            raise RwsRequestError(400, "GET /poll/{id} needs a websocket upgrade")
        await ws.prepare(r.req)
        if ws.ws_protocol != proto:
            await ws.close(code=1002, message=f"subprotocol {proto} required".encode())
            return ws
        self._websockets.add(ws)

        async def reader() -> None:
            async for msg in ws:  # only close / ping frames are expected from the client
                if msg.type in (WSMsgType.CLOSE, WSMsgType.ERROR):
                    break

        read_task = asyncio.create_task(reader())
        try:
            while not ws.closed and sub.sid in self._subs:
                get = asyncio.create_task(sub.queue.get())
                done, _ = await asyncio.wait({get, read_task}, return_when=asyncio.FIRST_COMPLETED)
                if get not in done:
                    get.cancel()
                    break
                text = get.result()
                if not text:
                    break
                await ws.send_str(self._event_frame(sub.sid, [text]))
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            read_task.cancel()
            self._websockets.discard(ws)
            if not ws.closed:
                await ws.close()
        return ws

    def _on_model_change(self, kind: str, data: dict) -> None:
        if not self._subs:
            return
        event = self._event_for(kind, data)
        if event is None:
            return
        key, fragment = event
        for sub in self._subs.values():
            if key in sub.resources:
                if sub.queue.full():  # a stalled reader must not grow memory without bound
                    sub.queue.get_nowait()
                    sub.dropped += 1
                    self.stats["events_dropped"] += 1
                sub.queue.put_nowait(fragment)

    def _event_for(self, kind: str, data: dict) -> tuple[str, str] | None:
        """(resource key, event item) of a model change, or None if nobody can subscribe to it."""
        keys = {
            "ctrlstate": rw.PANEL_CTRLSTATE,
            "opmode": rw.PANEL_OPMODE,
            "execution": rw.EXECUTION_SUBSCRIPTION,
            "elog": rw.elog_path(0),
        }
        if kind == "rapid-data":
            key = f"rapid:{data['task']}:{data['name']}"
        elif kind == "signal":
            key = f"signal:{data['name']}"
        elif kind in keys:
            key = keys[kind]
        else:
            return None
        li = self._event_li(kind, data)
        return (key, li) if li is not None else None

    def _event_li(self, kind: str, data: dict) -> str | None:
        """The ``<li>`` of one event, shaped as the ABB manual prints it (Subscription Event pages)."""
        if kind == "ctrlstate":
            return (
                f'<li class="pnl-ctrlstate-ev" title="ctrlstate"><a href="{rw.PANEL_CTRLSTATE}" rel="self"/>'
                f'<span class="ctrlstate">{_x(data["ctrlstate"])}</span></li>'
            )
        if kind == "opmode":
            return (
                f'<li class="pnl-opmode-ev" title="opmode"><a href="{rw.PANEL_OPMODE}" rel="self"/>'
                f'<span class="opmode">{_x(data["opmode"])}</span></li>'
            )
        if kind == "execution":
            return (
                '<li class="rap-ctrlexecstate-ev" title="ctrlexecstate">'
                f'<a href="{rw.EXECUTION_SUBSCRIPTION}" rel="self"/>'
                f'<span class="ctrlexecstate">{_x(data["ctrlexecstate"])}</span></li>'
            )
        if kind == "rapid-data":
            sym = f"RAPID/{data['task']}/{data['module']}/{data['name']}"
            href = rw.symbol_subscription(f"{data['task']}/{data['module']}", data["name"])
            return (
                f'<li class="rap-value-ev" title="value"><a href="{_x(href)}" rel="self"/>'
                f'</li><li class="rap-data" title="{_x(sym)}"><span class="value">{_x(data["value"])}</span></li>'
            )
        if kind == "signal":
            sig = self.model.signal(data["name"])
            path = f"{sig.network}/{sig.device}/{sig.name}"
            return (
                f'<li class="ios-signalstate-ev" title="{_x(path)}"><a href="{_x(rw.signal_subscription(path))}"'
                f' rel="self"/><span class="lvalue">{format_num(data["lvalue"])}</span>'
                '<span class="lstate">not simulated</span></li>'
            )
        if kind == "elog":
            seq = int(data["seqnum"])
            return (
                f'<li class="elog-message-ev" title="message"><a href="{rw.elog_path(0, seq)}" rel="self"/>'
                f'<span class="seqnum">{seq}</span></li>'
            )
        return None
