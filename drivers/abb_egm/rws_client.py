"""Asyncio Robot Web Services client, one interface for RWS 1.0 (RobotWare 6) and RWS 2.0 (RobotWare 7).

- ``rws1``: HTTP, digest auth (RFC 2617 MD5, qop=auth, computed here: aiohttp has no digest client),
  the controller's session cookies reused for every request (a new session per request exhausts the
  controller's session limit and gives 503), ``json=1``, logout on close, state changes through a
  websocket subscription (``robapi2_subscription``).
- ``rws2``: HTTPS (the controller's self-signed certificate: not verified unless a CA file is given),
  basic auth, ``;v=2.0`` media types, ``mastership=implicit`` on mutating calls, state changes by
  polling (the RWS 2.0 websocket subprotocol is not verified on hardware).

One ``aiohttp.ClientSession`` with a cookie jar holds the controller session. A 401 on a request made
with a session cookie means the controller dropped the session (idle timeout, restart): the client
logs in again once and repeats the request. Every request has a bounded timeout. A non-2xx answer
raises ``RwsError`` carrying the HTTP status and the controller's return code and message, read from
either profile's error body (RWS 1.0: ``status`` under ``_embedded``; RWS 2.0: at the top level;
XHTML ``<div class="status">``). XHTML answers are read into the same shape as JSON ones, and list
resources are read page by page along ``_links.next``. Only endpoints of ABB's RWS documentation
are used; ``docs/robot-setup.md`` lists which were checked against captured controller answers.

Usage::

    async with RwsClient(RwsClientConfig(base_url="http://192.168.125.1", profile="rws1")) as rws:
        await rws.motors_on()
        await rws.set_rapid_bool("T_ROB1", "egm_end", False)
        await rws.start_rapid()
        async for change in rws.changes(execution=True):
            ...
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import html
import json
import re
import secrets
import ssl
from collections.abc import AsyncIterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple
from urllib.parse import parse_qsl, quote, urljoin, urlsplit

import aiohttp
import numpy as np
import structlog

from drivers.abb_egm import rapid_values as _prog
from drivers.abb_egm import rws_protocol as rw
from drivers.abb_egm.digest import digest_response, parse_auth_params
from drivers.abb_egm.rapid_values import (
    ElogEntry,
    JointTarget,
    format_bool,
    format_jointtarget,
    format_num,
    format_string,
    parse_bool,
    parse_jointtarget,
    parse_num,
    parse_string,
)
from drivers.abb_egm.rws_protocol import Profile

log = structlog.get_logger(__name__)


class RwsError(Exception):
    """The controller (or the transport) refused a request.

    ``status``: HTTP status (0 when no answer came); ``code``: the controller's return code from the
    error body, when it gave one; ``method`` / ``path``: the request.
    """

    def __init__(
        self, message: str, *, status: int = 0, code: int | None = None, method: str = "", path: str = ""
    ) -> None:
        super().__init__(f"{method} {path}: {message} (HTTP {status}, code {code})" if method else message)
        self.message = message
        self.status = status
        self.code = code
        self.method = method
        self.path = path


class RwsAuthError(RwsError):
    """Login failed: wrong user name or password (the controller answered 401 to our credentials)."""


class RwsBusyError(RwsError):
    """The controller has no free session (503)."""


class RwsTimeoutError(RwsError):
    """No answer within the configured timeout."""


class RwsProtocolError(RwsError):
    """An answer that does not have the shape RWS gives it: a missing field, an unparsable value or
    body. The message names the request and what was wrong."""


def _parses_answer(fn):
    """Turn a lookup or conversion failure while reading an answer into :class:`RwsProtocolError`.

    A controller (or something pretending to be one) may answer anything: callers must see one
    error type, never a KeyError or a ValueError from deep inside the parsing.
    """

    @functools.wraps(fn)
    async def wrapper(self, *args, **kwargs):
        try:
            return await fn(self, *args, **kwargs)
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
            what = f"missing field {exc}" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
            raise RwsProtocolError(f"{fn.__name__}: unexpected answer ({what})"[:300]) from exc

    return wrapper


@dataclass(frozen=True)
class RwsClientConfig:
    """Connection settings (these become the ``[robot.rws]`` table of ``cell.toml``).

    ``base_url``: ``http://host[:port]`` (rws1) or ``https://host[:port]`` (rws2).
    ``tls_ca_file``: a PEM file to verify the controller certificate against; None skips verification
    (the controller's certificate is self-signed). ``timeout_s``: per request. ``poll_interval_s``: for
    state-change polling (rws2).
    """

    base_url: str = "http://127.0.0.1:80"
    profile: Profile = "rws1"
    username: str = "Default User"
    password: str = "robotics"
    timeout_s: float = 5.0
    tls_ca_file: str | None = None
    poll_interval_s: float = 0.2
    mechunit: str = "ROB_1"


@dataclass(frozen=True)
class ExecutionState:
    """RAPID execution state: ``ctrlexecstate`` is ``running`` or ``stopped``."""

    ctrlexecstate: str
    cycle: str


@dataclass(frozen=True)
class TaskState:
    """One RAPID task as ``/rw/rapid/tasks`` lists it (``excstate``: ready, started, stopped, ...)."""

    name: str
    type: str
    taskstate: str
    excstate: str
    active: bool
    motiontask: bool


@dataclass(frozen=True)
class SignalState:
    """One IO signal as ``/rw/iosystem/signals`` lists it; ``path`` is ``network/device/name``."""

    name: str
    path: str
    type: str
    lvalue: float


#: ``eax_a..eax_f``: six values, None for an unused axis
ExternalAxes = tuple[float | None, ...]
_NO_EXTERNAL_AXES: ExternalAxes = (None, None, None, None, None, None)


@dataclass(frozen=True)
class CartesianPose:
    """Flange pose in the base frame: ``pos_mm`` (3,), ``quat_wxyz`` (4,) scalar first (RAPID q1..q4).

    ``external_axes_mm``: the robtarget's ``eax_a..eax_f``, None where the controller reports 9E9 (axis
    unused); a linear track in the robot's motion group is in mm (a rotational axis would be in deg).
    """

    pos_mm: np.ndarray
    quat_wxyz: np.ndarray
    external_axes_mm: ExternalAxes = _NO_EXTERNAL_AXES


@dataclass(frozen=True)
class MechunitJoints:
    """The mechanical unit's jointtarget: ``q_deg`` (6,) the arm's joints (``rax_1..rax_6``) and
    ``external_axes_mm`` its ``eax_a..eax_f`` (a linear track in mm, a rotational axis in deg), None
    where the controller reports 9E9 (axis unused). Some controllers report 0, not 9E9, for an axis
    they do not have (ABB's RWS 1.0 example, an RWS 2.0 answer): whether a track is present is the
    cell's configuration, not this answer."""

    q_deg: np.ndarray
    external_axes_mm: ExternalAxes


def _external_axes(item: Mapping[str, Any]) -> ExternalAxes:
    """``eax_a..eax_f`` of a jointtarget / robtarget item (None for 9E9; absent fields are unused)."""
    return tuple(
        _prog.extax_or_none(float(item[f"eax_{c}"])) if f"eax_{c}" in item else None for c in "abcdef"
    )


@dataclass(frozen=True)
class StateChange:
    """One state-change notification.

    ``kind``: ``ctrlstate`` | ``opmode`` | ``execution`` | ``rapid-data`` | ``signal`` | ``elog``;
    ``name``: the variable / signal name (or the kind); ``value``: the new value as text (for ``elog``
    the event code).
    """

    kind: str
    name: str
    value: str


class _DigestState:
    """One digest challenge and its nonce counter (RFC 2617, MD5, qop=auth)."""

    def __init__(self, challenge: dict[str, str]) -> None:
        qops = [q.strip() for q in challenge.get("qop", "auth").split(",")]
        if "auth" not in qops:
            raise RwsError(f"digest challenge offers no qop=auth: {challenge.get('qop')!r}")
        algo = challenge.get("algorithm", "MD5").upper()
        if algo != "MD5":
            raise RwsError(f"digest algorithm {algo!r} not supported (only MD5)")
        self.realm = challenge.get("realm", "")
        self.nonce = challenge.get("nonce", "")
        self.opaque = challenge.get("opaque")
        self.nc = 0

    def header(self, method: str, uri: str, username: str, password: str, cnonce: str | None = None) -> str:
        """The ``Authorization`` value for one request; ``cnonce`` is random unless given (tests)."""
        self.nc += 1
        nc = f"{self.nc:08x}"
        cnonce = cnonce or secrets.token_hex(8)
        response = digest_response(
            username=username, realm=self.realm, password=password, method=method, uri=uri,
            nonce=self.nonce, nc=nc, cnonce=cnonce,
        )  # fmt: skip
        parts = [
            f'username="{username}"',
            f'realm="{self.realm}"',
            f'nonce="{self.nonce}"',
            f'uri="{uri}"',
            "algorithm=MD5",
            "qop=auth",
            f"nc={nc}",
            f'cnonce="{cnonce}"',
            f'response="{response}"',
        ]
        if self.opaque is not None:
            parts.append(f'opaque="{self.opaque}"')
        return "Digest " + ", ".join(parts)


def _states(body: Any) -> list[dict[str, Any]]:
    """The state items of a JSON body, whichever profile shaped it."""
    if not isinstance(body, dict):
        return []
    emb = body.get("_embedded") or {}
    for key in ("_state", "resources"):
        if isinstance(emb.get(key), list):
            return emb[key]
    if isinstance(body.get("state"), list):
        return body["state"]
    return []


_LI_RE = re.compile(r"<li\b([^>]*)>(.*?)</li>", re.S)
_ATTR_RE = re.compile(r'([\w:-]+)\s*=\s*"([^"]*)"')
_SPAN_RE = re.compile(r"<span\b([^>]*?)(?:/>|>(.*?)</span>)", re.S)
_A_RE = re.compile(r"<a\b([^>]*?)/?>", re.S)
_BASE_RE = re.compile(r'<base\s+href\s*=\s*"([^"]*)"', re.S)
_STATUS_RE = re.compile(r'<div class="status">(.*?)</div>', re.S)
_WS_HREF_RE = re.compile(r'<a\s+href\s*=\s*"(wss?://[^"]+/poll/[^"/]+)"\s+rel="(?:self|events)"')


def _attrs(text: str) -> dict[str, str]:
    return {k: html.unescape(v) for k, v in _ATTR_RE.findall(text)}


def parse_xhtml(text: str) -> dict[str, Any]:
    """An RWS XHTML answer as the JSON envelope of RWS 1.0: ``{"_links": {...}, "_embedded": {"_state": [...]}}``.

    Each ``<li class=.. title=..>`` becomes an item with ``_type`` / ``_title``, one field per
    ``<span class=..>`` (``<span class="x"/>`` is ``""``), ``argN`` spans collected in ``argv`` and its
    ``rel="self"`` link in ``_links``; the page's ``self`` / ``next`` links and ``<base href>`` go to
    ``_links``. An error page (``<div class="status">``) gives ``{"_embedded": {"status": {code, msg}}}``.
    """
    links: dict[str, Any] = {}
    if m := _BASE_RE.search(text):
        links["base"] = {"href": html.unescape(m.group(1))}
    if m := _STATUS_RE.search(text):
        spans = {
            _attrs(a).get("class", ""): html.unescape(v or "").strip()
            for a, v in _SPAN_RE.findall(m.group(1))
        }
        status: dict[str, Any] = {"msg": spans.get("msg", "")}
        if "code" in spans:
            status["code"] = spans["code"]
        return {"_links": links, "_embedded": {"status": status, "_state": []}}
    outside = _LI_RE.sub("", text)
    for a in _A_RE.findall(outside):
        at = _attrs(a)
        if at.get("rel") in ("self", "next") and "href" in at:
            links.setdefault(at["rel"], {"href": at["href"]})
    items: list[dict[str, Any]] = []
    for li_attrs, inner in _LI_RE.findall(text):
        at = _attrs(li_attrs)
        item: dict[str, Any] = {"_type": at.get("class", ""), "_title": at.get("title", "")}
        for a in _A_RE.findall(inner):
            a_at = _attrs(a)
            if a_at.get("rel") == "self" and "href" in a_at:
                item["_links"] = {"self": {"href": a_at["href"]}}
        argv = []
        for span_attrs, value in _SPAN_RE.findall(inner):
            sp = _attrs(span_attrs)
            name, val = sp.get("class", ""), html.unescape(value or "")
            if re.fullmatch(r"arg\d+", name):
                argv.append({"type": sp.get("type", ""), "value": val})
            elif name:
                item[name] = val
        if argv:
            item["argv"] = argv
        items.append(item)
    return {"_links": links, "_embedded": {"_state": items}}


def _self_href(item: dict[str, Any]) -> str:
    link = item.get("_links")
    return str(link.get("self", {}).get("href", "")) if isinstance(link, dict) else ""


def parse_event_xhtml(text: str) -> list[StateChange]:
    """Parse a subscription event page (XHTML, both profiles; also the 201 answer) into state changes.

    ``elog`` changes carry the event code when the page names it; the controller's event pages name
    only the sequence number (``value`` is then ``""``).
    """
    out: list[StateChange] = []
    items = _states(parse_xhtml(text))
    pending_var = ""  # RWS 1.0 sends the variable's path in a rap-value-ev item before its rap-data
    for it in items:
        cls, href = it["_type"], _self_href(it)
        if cls == "pnl-ctrlstate-ev" and "ctrlstate" in it:
            out.append(StateChange("ctrlstate", "ctrlstate", it["ctrlstate"]))
        elif cls == "pnl-opmode-ev" and "opmode" in it:
            out.append(StateChange("opmode", "opmode", it["opmode"]))
        elif cls == "rap-ctrlexecstate-ev" and "ctrlexecstate" in it:
            out.append(StateChange("execution", "ctrlexecstate", it["ctrlexecstate"]))
        elif cls == "rap-value-ev":
            pending_var = href
        elif cls == "rap-data" and "value" in it:
            where = it.get("name") or it["_title"] or href or pending_var
            name = where.split(";")[0].rstrip("/").removesuffix("/data").split("/")[-1]
            out.append(StateChange("rapid-data", name, it["value"]))
            pending_var = ""
        elif cls == "ios-signalstate-ev" and "lvalue" in it:
            where = it.get("name") or href or it["_title"]
            out.append(StateChange("signal", where.split(";")[0].split("/")[-1], it["lvalue"]))
        elif cls == "elog-message-ev":
            seq = it.get("seqnum") or href.rstrip("/").split("/")[-1]
            out.append(StateChange("elog", seq, it.get("code", "")))
    return out


def subscription_ws_url(headers: Mapping[str, str], body: str) -> str:
    """The websocket URL of a new subscription: the ``Location`` header, else the body's
    ``<a href="ws://.../poll/N" rel="self">`` (some RobotWare 6 controllers send only that)."""
    location = headers.get("Location", "")
    if location:
        return location
    m = _WS_HREF_RE.search(body)
    if m is None:
        raise RwsProtocolError("subscription answer names no websocket (no Location, no ws:// link)")
    return html.unescape(m.group(1))


def error_status(text: str, parsed: Any) -> tuple[int | None, str]:
    """The controller's return code and message of an error body, whichever shape it has: RWS 1.0
    JSON (``status`` under ``_embedded``), RWS 2.0 JSON (``status`` at the top level), XHTML
    (``<div class="status">``); JSON is recognised also under a wrong Content-Type."""
    if parsed is None and text.lstrip().startswith("{"):
        with contextlib.suppress(ValueError):
            parsed = json.loads(text)
    if parsed is None and "<" in text:
        parsed = parse_xhtml(text)
    code: Any = None
    msg = text[:200]
    if isinstance(parsed, dict):
        emb = parsed.get("_embedded")
        st = parsed.get("status")
        if not (isinstance(st, dict) and "code" in st) and isinstance(emb, dict):
            st = emb.get("status")
        if isinstance(st, dict):
            code, msg = st.get("code"), str(st.get("msg", msg))
        else:
            items = _states(parsed)
            if items and isinstance(items[0], dict) and "code" in items[0]:
                code, msg = items[0].get("code"), str(items[0].get("msg", msg))
    if isinstance(code, str):
        try:
            code = int(code)
        except ValueError:
            code = None
    if isinstance(code, bool) or not isinstance(code, int):
        code = None
    return code, msg


class _Answer(NamedTuple):
    """One answer: HTTP status, the body as JSON (XHTML parsed into the same shape), headers, raw text."""

    status: int
    body: Any
    headers: Mapping[str, str]
    text: str


class RwsClient:
    """Robot Web Services client; use as ``async with RwsClient(cfg) as rws:`` (logs out on exit)."""

    def __init__(self, config: RwsClientConfig) -> None:
        if config.profile not in ("rws1", "rws2"):
            raise ValueError(f"unknown RWS profile {config.profile!r} (use 'rws1' or 'rws2')")
        if config.timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {config.timeout_s}")
        self.config = config
        self._base = config.base_url.rstrip("/")
        self._http: aiohttp.ClientSession | None = None
        self._digest: _DigestState | None = None
        self._logged_in = False
        self._login_lock = asyncio.Lock()
        self.logins = 0  # how many times credentials were sent to create a session

    # ---- lifecycle ----------------------------------------------------------------------------

    async def __aenter__(self) -> RwsClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _session(self) -> aiohttp.ClientSession:
        if self._http is None or self._http.closed:
            ssl_arg: ssl.SSLContext | bool = True
            if self.config.profile == "rws2" or self._base.startswith("https"):
                if self.config.tls_ca_file:
                    ssl_arg = ssl.create_default_context(cafile=self.config.tls_ca_file)
                else:
                    ssl_arg = False  # the controller's certificate is self-signed
            # unsafe=True: the controller is addressed by IP, and aiohttp's default jar drops cookies
            # set by IP hosts, which would open a new session per request.
            self._http = aiohttp.ClientSession(
                cookie_jar=aiohttp.CookieJar(unsafe=True),
                timeout=aiohttp.ClientTimeout(total=self.config.timeout_s),
                connector=aiohttp.TCPConnector(ssl=ssl_arg, limit=4),
            )
        return self._http

    async def close(self) -> None:
        """Log out (frees the controller session) and close the connection pool."""
        if self._http is None or self._http.closed:
            return
        if self._logged_in:
            try:
                await self._request("GET", rw.LOGOUT, relogin=False)
            except RwsError as err:
                log.warning("rws_logout_failed", error=str(err))
        self._logged_in = False
        await self._http.close()
        self._http = None

    # ---- transport ----------------------------------------------------------------------------

    def _headers(self, method: str, has_body: bool) -> dict[str, str]:
        if self.config.profile == "rws2":
            h = {"Accept": rw.HAL_JSON_V2}
            if has_body:
                h["Content-Type"] = rw.FORM_V2
            return h
        return {"Content-Type": rw.FORM} if has_body else {}

    def _auth_header(self, method: str, path_qs: str) -> str | None:
        if self.config.profile == "rws2":
            token = base64.b64encode(f"{self.config.username}:{self.config.password}".encode()).decode()
            return f"Basic {token}"
        if self._digest is None:
            return None
        return self._digest.header(method, path_qs, self.config.username, self.config.password)

    @staticmethod
    def _encode_form(form: Sequence[tuple[str, str]] | dict[str, str] | None) -> str | None:
        if form is None:
            return None
        items = form.items() if isinstance(form, dict) else form
        return "&".join(f"{quote(k, safe='')}={quote(v, safe='')}" for k, v in items)

    def _path_qs(self, path: str, query: dict[str, str] | None) -> str:
        # A path may carry its own query (a controller's _links.next); the arguments' query adds to it.
        path, _, own = path.partition("?")
        q = dict(parse_qsl(own, keep_blank_values=True))
        q.update(query or {})
        if self.config.profile == "rws1":
            q.setdefault("json", "1")
        if not q:
            return path
        return path + "?" + "&".join(f"{quote(k, safe='')}={quote(v, safe='')}" for k, v in q.items())

    async def _request(
        self,
        method: str,
        path: str,
        *,
        query: dict[str, str] | None = None,
        form: Sequence[tuple[str, str]] | dict[str, str] | None = None,
        relogin: bool = True,
    ) -> _Answer:
        """Send one request; handles the 401 challenge, stale sessions and errors."""
        if not self._logged_in:
            # One login at a time: concurrent first requests would otherwise each open a session.
            async with self._login_lock:
                return await self._send(method, path, query, form, relogin)
        return await self._send(method, path, query, form, relogin)

    async def _send(
        self,
        method: str,
        path: str,
        query: dict[str, str] | None,
        form: Sequence[tuple[str, str]] | dict[str, str] | None,
        relogin: bool,
    ) -> _Answer:
        http = self._session()
        path_qs = self._path_qs(path, query)
        body = self._encode_form(form)
        url = self._base + path_qs
        sent_credentials = False
        for _attempt in range(3):
            headers = self._headers(method, body is not None)
            auth = None
            if not self._logged_in or sent_credentials:
                auth = self._auth_header(method, path_qs)
            if auth is not None:
                headers["Authorization"] = auth
                sent_credentials = True
            try:
                async with http.request(method, url, data=body, headers=headers) as resp:
                    status = resp.status
                    try:
                        text = await resp.text()
                    except (UnicodeDecodeError, LookupError) as err:  # bad bytes or an unknown charset
                        raise RwsProtocolError(
                            f"undecodable body: {err}"[:200], status=status, method=method, path=path
                        ) from err
                    if status == 401:
                        challenge = resp.headers.get("WWW-Authenticate", "")
                        # RFC 2617 says "true"; the controller writes stale="FALSE" / "TRUE".
                        stale = parse_auth_params(challenge).get("stale", "").lower() == "true"
                        if auth is not None and not stale:
                            self._logged_in = False
                            raise RwsAuthError(
                                f"login as {self.config.username!r} refused (wrong user name or password?)",
                                status=401, method=method, path=path,
                            )  # fmt: skip
                        if self._logged_in and not relogin:
                            raise RwsError("session expired", status=401, method=method, path=path)
                        if self._logged_in:
                            log.info("rws_session_stale_relogin", path=path)
                        self._logged_in = False
                        if challenge.lower().startswith("digest "):
                            self._digest = _DigestState(parse_auth_params(challenge[7:]))
                        elif self.config.profile == "rws1":
                            raise RwsError(
                                f"expected a digest challenge, got {challenge!r}",
                                status=401,
                                method=method,
                                path=path,
                            )
                        sent_credentials = True
                        continue
                    # Credentials were accepted unless the controller had no session to give (503).
                    if sent_credentials and status != 503:
                        self._logged_in = True
                        self.logins += 1
                        sent_credentials = False
                    parsed: Any = None
                    ctype = resp.headers.get("Content-Type", "")
                    if text and "json" in ctype:
                        try:
                            parsed = json.loads(text)
                        except ValueError as err:
                            if status < 400:
                                raise RwsError(
                                    f"malformed JSON body: {text[:80]!r}",
                                    status=status,
                                    method=method,
                                    path=path,
                                ) from err
                    elif text and "xml" in ctype:
                        parsed = parse_xhtml(text)
                    if status >= 400:
                        code, msg = error_status(text, parsed)
                        cls = RwsBusyError if status == 503 else RwsError
                        raise cls(msg, status=status, code=code, method=method, path=path)
                    return _Answer(status, parsed, resp.headers, text)
            except TimeoutError as err:
                raise RwsTimeoutError(
                    f"no answer within {self.config.timeout_s} s", method=method, path=path
                ) from err
            except aiohttp.ClientError as err:
                raise RwsError(f"transport error: {err}", method=method, path=path) from err
        raise RwsAuthError(
            "login did not complete after repeated challenges", status=401, method=method, path=path
        )

    async def _get_all(self, path: str, query: dict[str, str] | None = None) -> list[dict[str, Any]]:
        """The items of a list resource, following ``_links.next`` page by page (at most 1000 pages)."""
        items: list[dict[str, Any]] = []
        next_path: str | None = path
        seen: set[str] = set()
        while next_path is not None and len(seen) < 1000:
            seen.add(next_path)
            body = (await self._request("GET", next_path, query=query)).body
            items += [it for it in _states(body) if isinstance(it, dict)]
            next_path = None
            links = body.get("_links") if isinstance(body, dict) else None
            nxt = links.get("next") if isinstance(links, dict) else None
            if isinstance(nxt, dict) and nxt.get("href"):
                base = links.get("base", {}).get("href") if isinstance(links.get("base"), dict) else None
                # "signals?start=3&amp;limit=3": RobotWare 7 XML-escapes the & inside its JSON links
                href = html.unescape(str(nxt["href"]))
                target = urlsplit(urljoin(str(base or self._base + path), href))
                candidate = target.path + (f"?{target.query}" if target.query else "")
                next_path = candidate if candidate not in seen else None
                query = None  # the next link carries the query of the page it names
        return items

    async def _get_state(self, path: str, query: dict[str, str] | None = None) -> dict[str, Any]:
        body = (await self._request("GET", path, query=query)).body
        items = _states(body)
        if not items or not isinstance(items[0], dict):
            raise RwsProtocolError("answer holds no state item", method="GET", path=path)
        return items[0]

    def _mutating_query(self) -> dict[str, str]:
        return {"mastership": "implicit"} if self.config.profile == "rws2" else {}

    async def _action(self, path1: str, action: str, path2: str, form: dict[str, str] | None = None) -> None:
        if self.config.profile == "rws1":
            await self._request("POST", path1, query={"action": action}, form=form or {})
        else:
            await self._request("POST", path2, query=self._mutating_query(), form=form or {})

    # ---- panel --------------------------------------------------------------------------------

    @_parses_answer
    async def get_ctrl_state(self) -> str:
        """Controller state: ``motoron``, ``motoroff``, ``guardstop``, ``emergencystop``, ..."""
        return str((await self._get_state(rw.ctrl_state_path(self.config.profile)))["ctrlstate"])

    async def set_motors(self, on: bool) -> None:
        """Motors on / off (the controller must be in AUTO)."""
        form = {"ctrl-state": rw.MOTORON if on else rw.MOTOROFF}
        await self._action(rw.PANEL_CTRLSTATE, "setctrlstate", rw.PANEL_CTRL_STATE_V2, form)

    async def motors_on(self) -> None:
        """Switch the motors on."""
        await self.set_motors(True)

    async def motors_off(self) -> None:
        """Switch the motors off."""
        await self.set_motors(False)

    @_parses_answer
    async def get_opmode(self) -> str:
        """Operating mode: ``AUTO``, ``MANR``, ``MANF``, ..."""
        return str((await self._get_state(rw.PANEL_OPMODE))["opmode"])

    # ---- RAPID execution ----------------------------------------------------------------------

    @_parses_answer
    async def get_execution_state(self) -> ExecutionState:
        """RAPID execution state."""
        item = await self._get_state(rw.RAPID_EXECUTION)
        return ExecutionState(str(item["ctrlexecstate"]), str(item.get("cycle", "")))

    async def start_rapid(self, cycle: Literal["once", "forever", "asis"] = "once") -> None:
        """Start RAPID execution from the program pointer."""
        form = {
            "regain": "continue",
            "execmode": "continue",
            "cycle": cycle,
            "condition": "none",
            "stopatbp": "disabled",
            "alltaskbytsp": "false",
        }
        await self._action(rw.RAPID_EXECUTION, "start", rw.execution_action_path("start"), form)

    async def stop_rapid(self) -> None:
        """Stop RAPID execution."""
        await self._action(rw.RAPID_EXECUTION, "stop", rw.execution_action_path("stop"), {"stopmode": "stop"})

    async def reset_pp(self) -> None:
        """Program pointer to main (program must be stopped)."""
        await self._action(rw.RAPID_EXECUTION, "resetpp", rw.execution_action_path("resetpp"))

    # ---- RAPID variables ----------------------------------------------------------------------

    def _symbol_path(self, task: str, name: str, module: str | None) -> str:
        return rw.symbol_path(self.config.profile, task, name, module)

    @_parses_answer
    async def get_rapid_var(self, task: str, name: str, module: str | None = None) -> str:
        """Read a RAPID variable as its literal string (e.g. ``"[[0,0,0,0,30,0],[9E+09,...]]"``)."""
        return str((await self._get_state(self._symbol_path(task, name, module)))["value"])

    async def set_rapid_var(self, task: str, name: str, literal: str, module: str | None = None) -> None:
        """Write a RAPID variable from a literal string."""
        path = self._symbol_path(task, name, module)
        if self.config.profile == "rws1":
            await self._request("POST", path, query={"action": "set"}, form={"value": literal})
        else:
            await self._request("POST", path, query=self._mutating_query(), form={"value": literal})

    @_parses_answer
    async def get_rapid_num(self, task: str, name: str, module: str | None = None) -> float:
        """Read a ``num``."""
        return parse_num(await self.get_rapid_var(task, name, module))

    async def set_rapid_num(self, task: str, name: str, value: float, module: str | None = None) -> None:
        """Write a ``num``."""
        await self.set_rapid_var(task, name, format_num(value), module)

    @_parses_answer
    async def get_rapid_bool(self, task: str, name: str, module: str | None = None) -> bool:
        """Read a ``bool``."""
        return parse_bool(await self.get_rapid_var(task, name, module))

    async def set_rapid_bool(self, task: str, name: str, value: bool, module: str | None = None) -> None:
        """Write a ``bool``."""
        await self.set_rapid_var(task, name, format_bool(value), module)

    @_parses_answer
    async def get_rapid_string(self, task: str, name: str, module: str | None = None) -> str:
        """Read a ``string``."""
        return parse_string(await self.get_rapid_var(task, name, module))

    async def set_rapid_string(self, task: str, name: str, value: str, module: str | None = None) -> None:
        """Write a ``string``."""
        await self.set_rapid_var(task, name, format_string(value), module)

    @_parses_answer
    async def get_rapid_jointtarget(self, task: str, name: str, module: str | None = None) -> JointTarget:
        """Read a ``jointtarget`` (degrees)."""
        return parse_jointtarget(await self.get_rapid_var(task, name, module))

    async def set_rapid_jointtarget(
        self, task: str, name: str, value: JointTarget | np.ndarray, module: str | None = None
    ) -> None:
        """Write a ``jointtarget`` from a JointTarget or a (6,) array of degrees."""
        await self.set_rapid_var(task, name, format_jointtarget(value), module)

    # ---- IO -----------------------------------------------------------------------------------

    @_parses_answer
    async def get_io(self, signal: str, network: str | None = None, device: str | None = None) -> float:
        """Read an IO signal's value (0/1 for digital signals)."""
        item = await self._get_state(rw.signal_path(signal, network, device))
        return float(item["lvalue"])

    async def set_io(
        self, signal: str, value: float, network: str | None = None, device: str | None = None
    ) -> None:
        """Write an IO signal (fails with the controller's code if the access level forbids it)."""
        path = rw.signal_path(signal, network, device)
        form = {"lvalue": format_num(value)}
        if self.config.profile == "rws1":
            await self._request("POST", path, query={"action": "set"}, form=form)
        else:
            await self._request("POST", path + "/set-value", query=self._mutating_query(), form=form)

    # ---- event log, position ------------------------------------------------------------------

    @staticmethod
    def _elog_entry(it: dict[str, Any]) -> ElogEntry:
        seq = it.get("seqnum") or str(it.get("_title", "")).rsplit("/", 1)[-1]
        argv = it.get("argv") or []
        return ElogEntry(
            seqnum=int(seq),
            msgtype=int(it.get("msgtype", 0)),
            code=int(it.get("code", 0)),
            title=str(it.get("title", "")),
            desc=str(it.get("desc", "")),
            tstamp=str(it.get("tstamp", "")),
            conseqs=str(it.get("conseqs", "")),
            causes=str(it.get("causes", "")),
            actions=str(it.get("actions", "")),
            args=tuple(str(a["value"]) for a in argv if isinstance(a, dict)),
        )

    @_parses_answer
    async def read_event_log(self, domain: int = 0) -> list[ElogEntry]:
        """Event-log messages of ``domain``, newest first (every page, following ``_links.next``)."""
        items = await self._get_all(rw.elog_path(domain), {"lang": "en"})
        return [self._elog_entry(it) for it in items]

    @_parses_answer
    async def read_event(self, domain: int, seqnum: int) -> ElogEntry:
        """One event-log message with its English texts."""
        return self._elog_entry(await self._get_state(rw.elog_path(domain, seqnum), {"lang": "en"}))

    @_parses_answer
    async def read_event_log_domains(self) -> dict[int, int]:
        """Event-log domain number -> number of messages in it."""
        items = await self._get_all(rw.ELOG)
        return {
            int(it["_title"]): int(it.get("numevts", 0))
            for it in items
            if it.get("_type") == "elog-domain-li"
        }

    # ---- tasks, modules, signal list ----------------------------------------------------------

    @staticmethod
    def _task_state(it: dict[str, Any]) -> TaskState:
        return TaskState(
            name=str(it["name"]),
            type=str(it.get("type", "")),
            taskstate=str(it.get("taskstate", "")),
            excstate=str(it.get("excstate", "")),
            active=str(it.get("active", "")).lower() == "on",
            motiontask=str(it.get("motiontask", "")).lower() == "true",
        )

    @_parses_answer
    async def get_tasks(self) -> list[TaskState]:
        """The RAPID tasks of the system (RobotWare 7's ``spy`` entry left out)."""
        items = await self._get_all(rw.RAPID_TASKS)
        return [self._task_state(it) for it in items if it.get("_type") == "rap-task-li"]

    @_parses_answer
    async def get_task(self, task: str) -> TaskState:
        """One RAPID task."""
        return self._task_state(await self._get_state(rw.task_path(task)))

    @_parses_answer
    async def get_modules(self, task: str) -> list[tuple[str, str]]:
        """``(name, type)`` of the modules loaded in ``task`` (``SysMod`` / ``ProgMod``)."""
        if self.config.profile == "rws1":
            items = await self._get_all(rw.RAPID_MODULES, {"task": task})
        else:
            items = await self._get_all(rw.task_path(task) + "/modules")
        return [(str(it["name"]), str(it.get("type", ""))) for it in items if "name" in it]

    @_parses_answer
    async def list_signals(self) -> list[SignalState]:
        """Every IO signal (all pages)."""
        items = await self._get_all(rw.IOSYSTEM_SIGNALS)
        return [
            SignalState(
                str(it["name"]), str(it.get("_title", "")), str(it.get("type", "")), float(it["lvalue"])
            )
            for it in items
            if "name" in it
        ]

    @_parses_answer
    async def get_joint_position(self) -> np.ndarray:
        """Robot joints, (6,) float, degrees."""
        return (await self.get_mechunit_joints()).q_deg

    @_parses_answer
    async def get_mechunit_joints(self) -> MechunitJoints:
        """The jointtarget: the arm's joints (deg) and the external axes (a track in mm)."""
        item = await self._get_state(rw.mechunit_path(self.config.mechunit, "jointtarget"))
        q = np.array([float(item[f"rax_{i}"]) for i in range(1, 7)])
        return MechunitJoints(q, _external_axes(item))

    @_parses_answer
    async def get_cartesian(self) -> CartesianPose:
        """Flange pose (tool0) in the base frame."""
        item = await self._get_state(
            rw.mechunit_path(self.config.mechunit, "robtarget"),
            {"tool": "tool0", "wobj": "wobj0", "coordinate": "Base"},
        )
        pos = np.array([float(item[k]) for k in ("x", "y", "z")])
        quat = np.array([float(item[f"q{i}"]) for i in range(1, 5)])
        return CartesianPose(pos, quat, _external_axes(item))

    # ---- state changes ------------------------------------------------------------------------

    async def changes(
        self,
        *,
        ctrl_state: bool = True,
        opmode: bool = False,
        execution: bool = True,
        rapid_vars: Sequence[tuple[str, str]] = (),
        signals: Sequence[str] = (),
        elog: bool = False,
    ) -> AsyncIterator[StateChange]:
        """Yield state changes as they happen: websocket subscription (rws1) or polling (rws2).

        ``rapid_vars``: ``(task, name)`` pairs. ``signals``: signal names. Only changes after the
        subscription is in place are reported. The iterator runs until the consumer stops it; close it
        to end the subscription at once (``async with contextlib.aclosing(rws.changes()) as it:``).
        A websocket the controller closes (restart) is subscribed again, with backoff.
        """
        if self.config.profile == "rws1":
            gen = self._ws_changes(ctrl_state, opmode, execution, rapid_vars, signals, elog)
        else:
            gen = self._poll_changes(ctrl_state, opmode, execution, rapid_vars, signals, elog)
        try:
            async for change in gen:
                yield change
        finally:
            await gen.aclose()

    async def _ws_changes(
        self,
        ctrl_state: bool,
        opmode: bool,
        execution: bool,
        rapid_vars: Sequence[tuple[str, str]],
        signals: Sequence[str],
        elog: bool,
    ) -> AsyncIterator[StateChange]:
        resources = []
        if ctrl_state:
            resources.append(rw.PANEL_CTRLSTATE)
        if opmode:
            resources.append(rw.PANEL_OPMODE)
        if execution:
            resources.append(rw.EXECUTION_SUBSCRIPTION)
        resources += [rw.symbol_subscription(t, n) for t, n in rapid_vars]
        resources += [rw.signal_subscription(s) for s in signals]
        if elog:
            resources.append(rw.elog_path(0))
        if not resources:
            raise ValueError("changes(): nothing to subscribe to")
        form: list[tuple[str, str]] = []
        for i, res in enumerate(resources, start=1):
            prio = "2" if res.endswith(";state") else "1"
            form += [("resources", str(i)), (str(i), res), (f"{i}-p", prio)]
        failures = 0
        while True:
            answer = await self._request("POST", rw.SUBSCRIPTION, form=form)
            ws_path = urlsplit(subscription_ws_url(answer.headers, answer.text)).path
            ws_url = self._base.replace("http", "ws", 1) + ws_path
            try:
                async with self._session().ws_connect(
                    ws_url,
                    protocols=(rw.WS_PROTOCOL["rws1"],),
                    # Pings find a dead controller (cable pulled) that would never close the socket.
                    heartbeat=10.0,
                    timeout=aiohttp.ClientWSTimeout(ws_close=2.0),
                ) as ws:
                    failures = 0
                    async for msg in ws:
                        if msg.type == aiohttp.WSMsgType.TEXT:
                            for change in parse_event_xhtml(msg.data):
                                if change.kind == "elog" and not change.value:
                                    # The event names only the sequence number; the code is in the message.
                                    entry = await self.read_event(0, int(change.name))
                                    change = StateChange("elog", change.name, str(entry.code))
                                yield change
                        elif msg.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
                            break
            except aiohttp.ClientError as err:
                log.warning("rws_subscription_ws_failed", error=str(err))
            finally:
                with contextlib.suppress(RwsError, TimeoutError):
                    await asyncio.wait_for(
                        self._request(
                            "DELETE", f"{rw.SUBSCRIPTION}/{ws_path.rsplit('/', 1)[-1]}", relogin=False
                        ),
                        self.config.timeout_s,
                    )
            # The controller closed the socket (restart, session drop): subscribe again, with backoff.
            failures += 1
            if failures > 5:
                raise RwsError("subscription websocket keeps closing", method="GET", path=ws_path)
            await asyncio.sleep(min(0.1 * 2**failures, 2.0))

    async def _poll_changes(
        self,
        ctrl_state: bool,
        opmode: bool,
        execution: bool,
        rapid_vars: Sequence[tuple[str, str]],
        signals: Sequence[str],
        elog: bool,
    ) -> AsyncIterator[StateChange]:
        last: dict[tuple[str, str], str] = {}
        last_seq: int | None = None
        first = True
        while True:
            current: list[StateChange] = []
            if ctrl_state:
                current.append(StateChange("ctrlstate", "ctrlstate", await self.get_ctrl_state()))
            if opmode:
                current.append(StateChange("opmode", "opmode", await self.get_opmode()))
            if execution:
                ex = await self.get_execution_state()
                current.append(StateChange("execution", "ctrlexecstate", ex.ctrlexecstate))
            for task, name in rapid_vars:
                current.append(StateChange("rapid-data", name, await self.get_rapid_var(task, name)))
            for sig in signals:
                current.append(StateChange("signal", sig, format_num(await self.get_io(sig))))
            for ch in current:
                key = (ch.kind, ch.name)
                if not first and last.get(key) != ch.value:
                    yield ch
                last[key] = ch.value
            if elog:
                entries = await self.read_event_log()
                if last_seq is not None:
                    for e in reversed([e for e in entries if e.seqnum > last_seq]):
                        yield StateChange("elog", str(e.seqnum), str(e.code))
                last_seq = max([e.seqnum for e in entries], default=last_seq or 0)
            first = False
            await asyncio.sleep(self.config.poll_interval_s)
