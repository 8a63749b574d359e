"""Robot Web Services server of the simulated controller (aiohttp), RWS 1.0 and RWS 2.0 profiles.

Serves the endpoints ``rws_client.RwsClient`` uses, on top of a ``ControllerModel``:

- ``rws1`` (IRC5, RobotWare 6): plain HTTP, digest auth (RFC 2617 MD5, qop=auth) written here, session
  cookies ``-http-session-`` / ``ABBCX``, ``json=1`` bodies shaped ``{"_embedded": {"_state": [...]}}``
  (XHTML without it), subscriptions: POST ``/subscription`` -> 201 + websocket ``/poll/{id}`` with the
  ``robapi2_subscription`` subprotocol, XHTML event fragments.
- ``rws2`` (OmniCore, RobotWare 7): HTTPS with a self-signed certificate generated at start, basic
  auth, ``;v=2.0`` media types (406 / 415 without them), RWS2 paths (``/rw/panel/ctrl-state``,
  ``/rw/rapid/execution/start``, ``/rw/rapid/symbol/RAPID/{t}/{v}/data``, ``.../set-value``),
  mutating calls refused with 403 unless ``mastership=implicit`` or mastership was requested.

Sessions are limited (``max_sessions``; 503 beyond) and expire after ``session_idle_s``. Fault knobs
(``inject_error``, ``set_delay``, ``expire_sessions``) act at run time. A bad request never stops the
server: it gets a 4xx naming the offending field, and is counted and logged (rate limited).
"""

from __future__ import annotations

import asyncio
import base64
import html
import os
import re
import secrets
import shutil
import ssl
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal
from urllib.parse import unquote

import structlog
from aiohttp import WSMsgType, web

from drivers.abb_egm.digest import digest_response, md5_hex, parse_auth_params
from drivers.abb_egm.rapid_values import RC_BAD_VALUE, ControllerError, format_num
from drivers.abb_egm.sim.model import ControllerModel

log = structlog.get_logger(__name__)

Profile = Literal["rws1", "rws2"]
REALM = "validusers@robotwebservices.com"
SESSION_COOKIE = "-http-session-"
ABBCX_COOKIE = "ABBCX"
WS_PROTOCOL_RWS1 = "robapi2_subscription"
MEDIA_V2 = "v=2.0"

Handler = Callable[["_Request"], Awaitable[web.StreamResponse]]


class RwsRequestError(Exception):
    """A request the server rejects; carries the HTTP status, the controller return code and a message."""

    def __init__(self, status: int, message: str, code: int = RC_BAD_VALUE) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.code = code


@dataclass
class Session:
    """One authenticated client session (what the cookie points at)."""

    sid: str
    user: str
    created_s: float
    last_used_s: float
    mastership: bool = False


@dataclass
class _Subscription:
    sid: str
    session_id: str
    resources: dict[str, int]  # resource path -> priority
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
            self._tmpdir = tempfile.TemporaryDirectory(prefix="rws-cert-")
            cert, key = await generate_self_signed_cert(self._tmpdir.name, self.host)
            self.cert_path = cert
            ssl_ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ssl_ctx.load_cert_chain(cert, key)
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

    async def close_subscriptions(self) -> None:
        """Close every subscription websocket and forget the subscriptions (as a controller restart does)."""
        self._subs.clear()
        for ws in list(self._websockets):
            await ws.close(code=1001, message=b"controller restarting")

    # ---- auth and sessions --------------------------------------------------------------------

    def _challenge(self, stale: bool = False) -> str:
        if self.profile == "rws2":
            return f'Basic realm="{REALM}"'
        nonce = secrets.token_hex(16)
        now = time.monotonic()
        self._nonces[nonce] = now
        # Forget nonces past their lifetime so the table stays small.
        for n, t in list(self._nonces.items()):
            if now - t > self.nonce_lifetime_s:
                del self._nonces[n]
                self._nonce_nc.pop(n, None)
        stale_s = ', stale="true"' if stale else ""
        return f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", opaque="{md5_hex(REALM)}", algorithm=MD5{stale_s}'

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
                del self.sessions[sid]

    def _session_from_cookie(self, req: web.Request) -> Session | None:
        sid = req.cookies.get(SESSION_COOKIE)
        s = self.sessions.get(sid) if sid else None
        if s is not None:
            s.last_used_s = time.monotonic()
        return s

    # ---- dispatch -----------------------------------------------------------------------------

    def _error(self, status: int, message: str, code: int = RC_BAD_VALUE) -> web.Response:
        body = {"status": {"code": code, "msg": message}, "code": code, "msg": message}
        return web.json_response(body, status=status)

    def _bad_request(self, req: web.Request, err: RwsRequestError) -> web.Response:
        self.stats["bad_requests"] += 1
        now = time.monotonic()
        if now - self._last_bad_log_s > 1.0:  # rate limit: at most one line a second
            self._last_bad_log_s = now
            log.warning(
                "rws_bad_request", method=req.method, path=req.path, status=err.status, error=err.message,
                total=self.stats["bad_requests"],
            )  # fmt: skip
        return self._error(err.status, err.message, err.code)

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
            resp.set_cookie(SESSION_COOKIE, created[0].sid, httponly=True, path="/")
            resp.set_cookie(ABBCX_COOKIE, secrets.token_hex(8), httponly=True, path="/")
        return resp

    async def _handle(self, req: web.Request, path: str, created: list[Session]) -> web.StreamResponse:
        try:
            self._prune_sessions()
            session = self._session_from_cookie(req)
            if session is None:
                user, stale = self._check_authorization(req)
                if user is None:
                    if req.headers.get("Authorization"):
                        self.stats["auth_failures"] += 1
                    return web.Response(
                        status=401,
                        headers={"WWW-Authenticate": self._challenge(stale)},
                        text="401 Unauthorized",
                    )
                if len(self.sessions) >= self.max_sessions:
                    self.stats["rejected_busy"] += 1
                    return self._error(503, f"too many sessions ({self.max_sessions} active)", -7005)
                now = time.monotonic()
                session = Session(secrets.token_hex(12), user, now, now)
                self.sessions[session.sid] = session
                self.stats["sessions_created"] += 1
                created.append(session)
            return await self._route(req, session)
        except RwsRequestError as err:
            return self._bad_request(req, err)
        except ControllerError as err:
            return self._bad_request(req, RwsRequestError(err.http_status, err.message, err.code))
        except Exception as err:  # never let one request take the server down
            log.exception("rws_handler_failed", method=req.method, path=path)
            return self._error(500, f"internal error: {type(err).__name__}: {err}", -1)

    async def _route(self, req: web.Request, session: Session) -> web.StreamResponse:
        path = req.path
        for prefix, fault in self._faults.items():
            if path.startswith(prefix):
                return self._error(fault.status, fault.message, fault.code)
        method = req.method
        for m, regex, handler, mutating in self._routes:
            if m != method:
                continue
            match = regex.match(path)
            if match is None:
                continue
            want_json = self._negotiate(req)
            form: dict[str, str] = {}
            multi: list[tuple[str, str]] = []
            if method in ("POST", "PUT"):
                form, multi = await self._read_form(req)
                if mutating and self.profile == "rws2":
                    implicit = (
                        req.query.get("mastership") == "implicit" or form.get("mastership") == "implicit"
                    )
                    if not (implicit or session.mastership):
                        raise RwsRequestError(403, "mastership required (use mastership=implicit)", -7006)
            return await handler(_Request(req, session, match, form, want_json, multi))
        raise RwsRequestError(404, f"no resource {method} {path}", -7002)

    def _negotiate(self, req: web.Request) -> bool:
        if self.profile == "rws1":
            return req.query.get("json") == "1"
        accept = req.headers.get("Accept", "")
        if MEDIA_V2 not in accept.replace(" ", ""):
            raise RwsRequestError(406, f"Accept must name a ;v=2.0 media type, got {accept!r}", -7007)
        return "json" in accept

    async def _read_form(self, req: web.Request) -> tuple[dict[str, str], list[tuple[str, str]]]:
        ctype = req.headers.get("Content-Type", "")
        raw = await req.read()
        if raw and "x-www-form-urlencoded" not in ctype:
            raise RwsRequestError(
                415, f"Content-Type must be application/x-www-form-urlencoded, got {ctype!r}"
            )
        if self.profile == "rws2" and raw and MEDIA_V2 not in ctype.replace(" ", ""):
            raise RwsRequestError(415, f"Content-Type must carry ;v=2.0, got {ctype!r}", -7007)
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
        self, r: _Request, items: list[dict[str, Any]], title: str, listing: bool = False
    ) -> web.Response:
        if not r.json:
            return web.Response(text=self._xhtml(items, title), content_type="application/xhtml+xml")
        links = {"base": {"href": f"{self.base_url}/"}, "self": {"href": r.req.path}}
        if self.profile == "rws1":
            body: dict[str, Any] = {"_links": links, "_embedded": {"_state": items}}
        elif listing:
            body = {"_links": links, "_embedded": {"resources": items}}
        else:
            body = {"_links": links, "state": items}
        ctype = "application/hal+json" if self.profile == "rws2" else "application/json"
        resp = web.json_response(body)
        resp.content_type = ctype
        return resp

    def _xhtml(self, items: list[dict[str, Any]], title: str) -> str:
        lis = []
        for it in items:
            spans = "".join(
                f'<span class="{html.escape(k)}">{html.escape(str(v))}</span>'
                for k, v in it.items()
                if not k.startswith("_")
            )
            lis.append(
                f'<li class="{html.escape(it["_type"])}" title="{html.escape(it["_title"])}">{spans}</li>'
            )
        return (
            f'<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>'
            f'<title>{html.escape(title)}</title><base href="{self.base_url}/"/></head><body>'
            f'<div class="state"><ul>{"".join(lis)}</ul></div></body></html>'
        )

    @staticmethod
    def _no_content() -> web.Response:
        return web.Response(status=204)

    # ---- routes -------------------------------------------------------------------------------

    def _build_routes(self) -> list[tuple[str, re.Pattern[str], Handler, bool]]:
        v2 = self.profile == "rws2"
        sym = r"/rw/rapid/symbol/RAPID/(?P<task>[^/]+)(?:/(?P<module>[^/]+))?/(?P<name>[^/]+)/data$"
        sym1 = r"/rw/rapid/symbol/data/RAPID/(?P<task>[^/]+)(?:/(?P<module>[^/]+))?/(?P<name>[^/]+)$"
        sig = r"/rw/iosystem/signals/(?P<path>[^?]+?)"
        routes: list[tuple[str, str, Handler, bool]] = [
            ("GET", r"/rw/panel/opmode$", self._get_opmode, False),
            ("GET", r"/rw/panel/speedratio$", self._get_speedratio, False),
            ("GET", r"/rw/rapid/execution$", self._get_execution, False),
            ("GET", r"/rw/elog/(?P<domain>\d+)$", self._get_elog, False),
            ("GET", r"/rw/motionsystem/mechunits/(?P<mu>[^/]+)/jointtarget$", self._get_jointtarget, False),
            ("GET", r"/rw/motionsystem/mechunits/(?P<mu>[^/]+)/robtarget$", self._get_robtarget, False),
            ("GET", r"/rw/system$", self._get_system, False),
            ("GET", r"/logout$", self._logout, False),
        ]
        if v2:
            routes += [
                ("GET", r"/rw/panel/ctrl-state$", self._get_ctrlstate, False),
                ("POST", r"/rw/panel/ctrl-state$", self._set_ctrlstate, True),
                ("POST", r"/rw/rapid/execution/start$", self._start, True),
                ("POST", r"/rw/rapid/execution/stop$", self._stop, True),
                ("POST", r"/rw/rapid/execution/resetpp$", self._resetpp, True),
                ("GET", sym, self._get_var, False),
                ("POST", sym, self._set_var, True),
                ("POST", sig + r"/set-value$", self._set_signal, True),
                ("GET", sig + r"$", self._get_signal, False),
                ("POST", r"/rw/mastership/request$", self._mastership_request, False),
                ("POST", r"/rw/mastership/release$", self._mastership_release, False),
            ]
        else:
            routes += [
                ("GET", r"/rw/panel/ctrlstate$", self._get_ctrlstate, False),
                ("POST", r"/rw/panel/ctrlstate$", self._rws1_action, True),
                ("POST", r"/rw/rapid/execution$", self._rws1_action, True),
                ("GET", sym1, self._get_var, False),
                ("POST", sym1, self._rws1_action, True),
                ("GET", sig + r"$", self._get_signal, False),
                ("POST", sig + r"$", self._rws1_action, True),
                ("POST", r"/subscription$", self._subscribe, False),
                ("DELETE", r"/subscription/(?P<sub>[^/]+)$", self._unsubscribe_route, False),
                ("GET", r"/poll/(?P<sub>[^/]+)$", self._poll_ws, False),
            ]
        return [(m, re.compile(p), h, mut) for m, p, h, mut in routes]

    async def _rws1_action(self, r: _Request) -> web.StreamResponse:
        # RWS 1.0 selects the operation with ?action=...; map it onto the shared handlers.
        action = r.req.query.get("action", "")
        path = r.req.path
        table: dict[tuple[str, str], Handler] = {
            ("/rw/panel/ctrlstate", "setctrlstate"): self._set_ctrlstate,
            ("/rw/rapid/execution", "start"): self._start,
            ("/rw/rapid/execution", "stop"): self._stop,
            ("/rw/rapid/execution", "resetpp"): self._resetpp,
        }
        handler = table.get((path, action))
        if handler is None and action == "set":
            if path.startswith("/rw/rapid/symbol/data/"):
                handler = self._set_var
            elif path.startswith("/rw/iosystem/signals/"):
                handler = self._set_signal
        if handler is None:
            raise RwsRequestError(400, f"unknown action {action!r} for {path}")
        return await handler(r)

    @staticmethod
    def _field(r: _Request, name: str) -> str:
        value = r.form.get(name)
        if value is None:
            raise RwsRequestError(400, f"missing form field {name!r}")
        return value

    async def _get_ctrlstate(self, r: _Request) -> web.Response:
        item = {"_type": "pnl-ctrlstate", "_title": "ctrlstate", "ctrlstate": self.model.ctrl_state}
        return self._respond(r, [item], "panel")

    async def _set_ctrlstate(self, r: _Request) -> web.Response:
        state = self._field(r, "ctrl-state")
        if state == "motoron":
            self.model.motors_on()
        elif state == "motoroff":
            self.model.motors_off()
        else:
            raise RwsRequestError(400, f"ctrl-state must be motoron or motoroff, got {state!r}")
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

    async def _get_execution(self, r: _Request) -> web.Response:
        item = {
            "_type": "rap-execution",
            "_title": "execution",
            "ctrlexecstate": self.model.rapid_state,
            "cycle": "once",
        }
        return self._respond(r, [item], "execution")

    async def _start(self, r: _Request) -> web.Response:
        cycle = r.form.get("cycle", "asis")
        if cycle not in ("once", "forever", "asis", "oncedone"):
            raise RwsRequestError(400, f"cycle must be once, forever or asis, got {cycle!r}")
        self.model.start_rapid()
        return self._no_content()

    async def _stop(self, r: _Request) -> web.Response:
        self.model.stop_rapid()
        return self._no_content()

    async def _resetpp(self, r: _Request) -> web.Response:
        self.model.reset_pp()
        return self._no_content()

    async def _get_var(self, r: _Request) -> web.Response:
        g = r.match.groupdict()
        var = self.model.var_info(g["task"], g["module"], g["name"])
        item = {
            "_type": "rap-data",
            "_title": f"RAPID/{var.task}/{var.module}/{var.name}",
            "value": var.value,
        }
        return self._respond(r, [item], "rapid data")

    async def _set_var(self, r: _Request) -> web.Response:
        g = r.match.groupdict()
        self.model.set_var(g["task"], g["module"], g["name"], self._field(r, "value"))
        return self._no_content()

    def _signal_from_path(self, r: _Request) -> str:
        parts = r.match.group("path").split("/")
        name = parts[-1]
        sig = self.model.signal(name)
        if len(parts) == 3 and (parts[0], parts[1]) != (sig.network, sig.device):
            raise RwsRequestError(404, f"IO signal not found: {'/'.join(parts)}", -7002)
        if len(parts) not in (1, 3):
            raise RwsRequestError(
                404, f"IO signal path must be signal or network/device/signal: {r.req.path}", -7002
            )
        return name

    async def _get_signal(self, r: _Request) -> web.Response:
        sig = self.model.signal(self._signal_from_path(r))
        item = {
            "_type": "ios-signal-li",
            "_title": f"{sig.network}/{sig.device}/{sig.name}",
            "name": sig.name,
            "type": sig.signal_type,
            "lvalue": format_num(sig.lvalue),
            "lstate": "not simulated",
        }
        return self._respond(r, [item], "signal")

    async def _set_signal(self, r: _Request) -> web.Response:
        name = self._signal_from_path(r)
        text = self._field(r, "lvalue")
        try:
            value = float(text)
        except ValueError as err:
            raise RwsRequestError(400, f"lvalue must be a number, got {text!r}") from err
        self.model.set_io(name, value)
        return self._no_content()

    async def _get_elog(self, r: _Request) -> web.Response:
        domain = int(r.match.group("domain"))
        if domain != 0:
            raise RwsRequestError(404, f"event log domain {domain} is empty in the simulator", -7002)
        items = [
            {
                "_type": "elog-message-li",
                "_title": f"/rw/elog/0/{ev.seqnum}",
                "seqnum": str(ev.seqnum),
                "msgtype": str(ev.msgtype),
                "code": str(ev.code),
                "tstamp": ev.tstamp,
                "title": ev.title,
                "desc": ev.desc,
            }
            for ev in self.model.events
        ]
        return self._respond(r, items, "elog", listing=True)

    def _check_mechunit(self, r: _Request) -> None:
        if r.match.group("mu") != self.mechunit:
            raise RwsRequestError(404, f"mechanical unit not found: {r.match.group('mu')}", -7002)

    async def _get_jointtarget(self, r: _Request) -> web.Response:
        self._check_mechunit(r)
        q_deg, _, _ = self.model.position()
        item: dict[str, Any] = {"_type": "ms-jointtarget", "_title": self.mechunit}
        item.update({f"rax_{i + 1}": format_num(round(float(v), 6)) for i, v in enumerate(q_deg)})
        item.update({f"eax_{c}": "9E+09" for c in "abcdef"})
        return self._respond(r, [item], "jointtarget")

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
        return self._respond(r, [item], "robtarget")

    async def _get_system(self, r: _Request) -> web.Response:
        version = "7.16.0" if self.profile == "rws2" else "6.15.0"
        item = {"_type": "sys-system", "_title": "system", "name": "cellctl-sim", "rwversionname": version}
        return self._respond(r, [item], "system")

    async def _logout(self, r: _Request) -> web.Response:
        self.sessions.pop(r.session.sid, None)
        for sid, sub in list(self._subs.items()):
            if sub.session_id == r.session.sid:
                del self._subs[sid]
        resp = self._no_content()
        resp.del_cookie(SESSION_COOKIE)
        resp.del_cookie(ABBCX_COOKIE)
        return resp

    async def _mastership_request(self, r: _Request) -> web.Response:
        r.session.mastership = True
        return self._no_content()

    async def _mastership_release(self, r: _Request) -> web.Response:
        r.session.mastership = False
        return self._no_content()

    # ---- subscriptions (RWS 1.0) --------------------------------------------------------------

    _RESOURCE_RE = re.compile(
        r"^(/rw/panel/ctrlstate|/rw/panel/opmode|/rw/rapid/execution;ctrlexecstate|/rw/elog/0"
        r"|/rw/rapid/symbol/data/RAPID/[^/;]+(/[^/;]+)?/[^/;]+;value|/rw/iosystem/signals/[^;]+;state)$"
    )

    async def _subscribe(self, r: _Request) -> web.Response:
        indices = [v for k, v in r.multi if k == "resources"]
        if not indices:
            raise RwsRequestError(400, "subscription needs at least one 'resources' field")
        resources: dict[str, int] = {}
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
            resources[self._normalise_resource(res)] = prio
        self._sub_seq += 1
        self.stats["subscriptions_created"] += 1
        sub = _Subscription(str(self._sub_seq), r.session.sid, resources)
        self._subs[sub.sid] = sub
        href = f"ws://{self.host}:{self.port}/poll/{sub.sid}"
        body = {"_links": {"self": {"href": href}, "group": {"href": f"subscription/{sub.sid}"}}}
        return web.json_response(body, status=201, headers={"Location": href})

    def _normalise_resource(self, res: str) -> str:
        # Signals may be named with or without network/device; key them by signal name.
        if res.startswith("/rw/iosystem/signals/"):
            return "signal:" + res[len("/rw/iosystem/signals/") :].split(";")[0].split("/")[-1]
        m = re.match(r"^/rw/rapid/symbol/data/RAPID/([^/;]+)(?:/([^/;]+))?/([^/;]+);value$", res)
        if m:
            return f"rapid:{m.group(1)}:{m.group(3)}"
        return res

    async def _unsubscribe_route(self, r: _Request) -> web.Response:
        sub = self._subs.get(r.match.group("sub"))
        if sub is None or sub.session_id != r.session.sid:
            raise RwsRequestError(404, f"no subscription {r.match.group('sub')}", -7002)
        del self._subs[sub.sid]
        await sub.queue.put("")  # wakes the websocket writer so it closes
        return self._no_content()

    async def _poll_ws(self, r: _Request) -> web.StreamResponse:
        sub = self._subs.get(r.match.group("sub"))
        if sub is None or sub.session_id != r.session.sid:
            raise RwsRequestError(404, f"no subscription {r.match.group('sub')}", -7002)
        ws = web.WebSocketResponse(protocols=(WS_PROTOCOL_RWS1,), heartbeat=None)
        if not ws.can_prepare(r.req).ok:
            raise RwsRequestError(400, "GET /poll/{id} needs a websocket upgrade")
        await ws.prepare(r.req)
        if ws.ws_protocol != WS_PROTOCOL_RWS1:
            await ws.close(code=1002, message=b"subprotocol robapi2_subscription required")
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
                await ws.send_str(text)
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
        if kind == "ctrlstate":
            return "/rw/panel/ctrlstate", self._ev_xhtml(
                "pnl-ctrlstate-ev", "/rw/panel/ctrlstate", {"ctrlstate": data["ctrlstate"]}
            )
        if kind == "opmode":
            return "/rw/panel/opmode", self._ev_xhtml(
                "pnl-opmode-ev", "/rw/panel/opmode", {"opmode": data["opmode"]}
            )
        if kind == "execution":
            return "/rw/rapid/execution;ctrlexecstate", self._ev_xhtml(
                "rap-ctrlexecstate-ev", "/rw/rapid/execution", {"ctrlexecstate": data["ctrlexecstate"]}
            )
        if kind == "rapid-data":
            href = f"/rw/rapid/symbol/data/RAPID/{data['task']}/{data['module']}/{data['name']}"
            return f"rapid:{data['task']}:{data['name']}", self._ev_xhtml(
                "rap-data", href, {"name": data["name"], "value": data["value"]}
            )
        if kind == "signal":
            href = f"/rw/iosystem/signals/{data['name']}"
            return f"signal:{data['name']}", self._ev_xhtml(
                "ios-signalstate-ev", href, {"name": data["name"], "lvalue": format_num(data["lvalue"])}
            )
        if kind == "elog":
            spans = {
                "seqnum": str(data["seqnum"]),
                "code": str(data["code"]),
                "msgtype": str(data["msgtype"]),
            }
            return "/rw/elog/0", self._ev_xhtml("elog-message-ev", f"/rw/elog/0/{data['seqnum']}", spans)
        return None

    def _ev_xhtml(self, cls: str, href: str, spans: dict[str, str]) -> str:
        inner = "".join(f'<span class="{k}">{html.escape(v)}</span>' for k, v in spans.items())
        return (
            f'<html xmlns="http://www.w3.org/1999/xhtml"><head><base href="{self.base_url}/"/></head><body>'
            f'<div class="state"><ul><li class="{cls}" title="{html.escape(href)}">'
            f'<a href="{html.escape(href)}" rel="self"></a>{inner}</li></ul></div></body></html>'
        )
