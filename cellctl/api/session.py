"""Zenoh sessions for the cell: configuration from ``[zenoh]``, safe open/close, an asyncio bridge.

Measured pitfalls this module exists for (docs/reference libraries.md, section 1):

* A peer listens on every interface by default and scouts by multicast: we always set ``listen``
  and ``connect`` explicitly and turn multicast scouting off unless the configuration asks for it.
* A star of peers with gossip off does not relay: the daemon serves (peer or router) and workers
  and command-line tools connect to it as *clients*; gossip is on only for peers that connect to a
  hub, where it is what makes them see each other.
* Zenoh callbacks run on Zenoh's own threads and hold the GIL: they only hand the sample over to
  the event loop with ``loop.call_soon_threadsafe``.
* A process with callback subscribers hangs at exit unless the session is closed: every session is
  closed in ``finally`` (:func:`session_scope`).
* Never fork after opening a session: analysis runs in *spawned* processes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import structlog
import zenoh
from pydantic import ValidationError

from cellctl.api.keys import Keys
from cellctl.api.models import ApiError, M, WorkerAnnouncement
from cellctl.config import ConfigError, ZenohSection, check_secret_file_mode, resolve_secret

log = structlog.get_logger(__name__)

Role = Literal["serve", "connect"]
_ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


class ZenohSetupError(Exception):
    """A Zenoh session that cannot be configured or opened; says which setting or endpoint."""


def _loopback_of(endpoint: str) -> str:
    # A daemon listening on every interface is reached locally through loopback.
    proto, rest = endpoint.split("/", 1)
    host, port = rest.rsplit(":", 1)
    if host in ("0.0.0.0", "[::]"):
        host = "127.0.0.1" if host == "0.0.0.0" else "[::1]"
    return f"{proto}/{host}:{port}"


def _dictionary_users(path: Path) -> list[str]:
    # The dictionary holds every user's password: refuse it when others may read it, like a secrets file.
    try:
        check_secret_file_mode(path, what="zenoh.access.dictionary_file")
    except ConfigError as exc:
        raise ZenohSetupError(str(exc)) from None
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
        raise ZenohSetupError(f"zenoh.access.dictionary_file {path}: cannot read: {why}") from None
    users = [ln.split(":", 1)[0].strip() for ln in lines if ":" in ln and not ln.lstrip().startswith("#")]
    if not users:
        raise ZenohSetupError(f"zenoh.access.dictionary_file {path}: no 'user:password' lines")
    return users


def _rule(rule_id: str, flow: str, messages: list[str], prefix: str, keys: list[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": [f"{prefix}/{k}" if k else prefix for k in keys],
    }


# What each role may do, seen from the serving node (the daemon or the router): "ingress" is what the
# user's session sends in, "egress" what is forwarded to it. Keys are relative to the cell's prefix
# (cellctl.api.Keys). Declarations flowing out reveal key names only, so every role receives them.
_READ_KEYS = ["state", "reports/*", "jobs/*/event", "jobs/*/live"]
_DECLARATIONS = [
    "declare_subscriber",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
]


def _role_rules(prefix: str) -> dict[str, list[dict[str, Any]]]:
    """The ACL rules of each role (see :class:`cellctl.config.ZenohAccess`)."""
    common = [_rule("declarations_out", "egress", _DECLARATIONS, prefix, ["", "**"])]
    read = [
        _rule("read_subscribe", "ingress", ["declare_subscriber"], prefix, _READ_KEYS),
        _rule("read_receive", "egress", ["put"], prefix, _READ_KEYS),
        _rule(
            "read_liveliness",
            "ingress",
            ["declare_liveliness_subscriber", "liveliness_query"],
            prefix,
            ["alive/**"],
        ),
        _rule("read_liveliness_replies", "egress", ["reply"], prefix, ["alive/**"]),
        _rule("read_worker_info", "ingress", ["query"], prefix, ["workers/*/info"]),
        _rule("read_worker_info_replies", "egress", ["reply"], prefix, ["workers/*/info"]),
    ]
    control_keys = ["scan/trigger", "control/*"]
    operate = [
        _rule("operate_query", "ingress", ["query"], prefix, control_keys),
        _rule("operate_replies", "egress", ["reply"], prefix, control_keys),
    ]
    # what names one worker (its jobs, cancels, stream, token, announcement) is bound to the
    # identity of that name: _own_worker_rules, one subject per worker
    work = [
        _rule("work_publish", "ingress", ["put"], prefix, ["jobs/*/event", "reports/*", "results/**"]),
        _rule("work_designs", "ingress", ["query"], prefix, ["designs/*"]),
        _rule("work_designs_replies", "egress", ["reply"], prefix, ["designs/*"]),
        # a streamed job's whole cloud, when a chunk is missing after its end
        _rule("work_cloud", "ingress", ["query"], prefix, ["jobs/*/cloud"]),
        _rule("work_cloud_replies", "egress", ["reply"], prefix, ["jobs/*/cloud"]),
        # the daemon's token: a stream from a daemon that is gone is given up (cellctl.worker.service)
        _rule("work_daemon_alive", "ingress", ["declare_liveliness_subscriber"], prefix, ["alive/daemon"]),
    ]
    everything = [
        _rule(f"whole_cell_{d}", d, _ALL_MESSAGES, prefix, ["", "**"]) for d in ("ingress", "egress")
    ]
    return {
        "viewer": common + read,
        "operator": common + read + operate,
        "worker": common + work,
        "daemon": everything,
    }


def _own_worker_rules(prefix: str, name: str) -> list[dict[str, Any]]:
    """The rules of the worker whose id is ``name``, for the identity ``name`` only: it receives
    only its own jobs, cancels and stream, declares only its own token and announcement. So no
    other worker-role identity can take its offers, read its offer keys or pose as it."""
    own = [f"workers/{name}/jobs/*", f"workers/{name}/cancel/*", f"workers/{name}/stream/**"]
    info = [f"workers/{name}/info"]
    return [
        _rule(f"worker_{name}_declare", "ingress", ["declare_subscriber"], prefix, own),
        _rule(f"worker_{name}_receive", "egress", ["put"], prefix, own),
        _rule(f"worker_{name}_alive", "ingress", ["liveliness_token"], prefix, [f"alive/workers/{name}"]),
        _rule(f"worker_{name}_info", "ingress", ["declare_queryable", "reply"], prefix, info),
        # a viewer's list_workers asks workers/*/info: a query names no worker, receiving it is harmless
        _rule(f"worker_{name}_info_queries", "egress", ["query"], prefix, ["workers/*/info"]),
    ]


def access_control_dict(
    roles: dict[str, list[str]],
    users: list[str] | None,
    key_prefix: str,
    *,
    subject_key: Literal["usernames", "cert_common_names"] = "usernames",
) -> dict[str, Any]:
    """The zenoh ``access_control`` section: default deny, each role's users allowed its rules only.

    ``roles`` maps a role (operator, worker, viewer, daemon) to user names (``subject_key``
    "usernames", from the dictionary ``users``) or certificate common names ("cert_common_names",
    ``users`` None: any certificate the cell's CA signed). Empty ``roles`` gives every user of
    ``users`` the whole cell key space. A role naming a user that is not in the dictionary is a
    ZenohSetupError (a typo would silently lock that user out).
    """
    if not roles:
        roles = {"daemon": list(users or [])}
    unknown = sorted({u for names in roles.values() for u in names} - set(users)) if users is not None else []
    if unknown:
        raise ZenohSetupError(
            f"zenoh.access.roles names users missing from the dictionary file: {', '.join(unknown)}"
        )
    role_rules = _role_rules(key_prefix)
    rules: dict[str, dict[str, Any]] = {}
    subjects, policies = [], []
    for role, names in sorted(roles.items()):
        if not names:
            continue
        role_rule_ids = []
        for rule in role_rules[role]:
            rules[rule["id"]] = rule  # shared rules (read, declarations) are defined once
            role_rule_ids.append(rule["id"])
        subjects.append({"id": f"role_{role}", subject_key: list(names)})
        policies.append({"id": f"policy_{role}", "rules": role_rule_ids, "subjects": [f"role_{role}"]})
        if role != "worker":
            continue
        for name in names:  # each worker identity bound to the worker id of its name
            own = _own_worker_rules(key_prefix, name)
            rules.update({r["id"]: r for r in own})
            subjects.append({"id": f"worker_{name}", subject_key: [name]})
            policies.append(
                {
                    "id": f"policy_worker_{name}",
                    "rules": [r["id"] for r in own],
                    "subjects": [f"worker_{name}"],
                }
            )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": list(rules.values()),
        "subjects": subjects,
        "policies": policies,
    }


def _tls_dict(section: ZenohSection, *, role: Role, mode: str) -> dict[str, Any]:
    """``transport/link/tls`` for mutual TLS: this process's certificate, and the CA that must have
    signed the peer's. Every endpoint has to be ``tls/...``."""
    access = section.access
    plain = [ep for ep in (*section.listen, *section.connect) if not ep.startswith("tls/")]
    if plain:
        raise ZenohSetupError(
            f"zenoh.access.auth {access.auth!r} needs tls/ endpoints, got {', '.join(plain)}"
        )
    try:
        check_secret_file_mode(access.tls_key_file, what="zenoh.access.tls_key_file")
    except ConfigError as exc:
        raise ZenohSetupError(str(exc)) from None
    for name in ("tls_ca_file", "tls_cert_file", "tls_key_file"):
        if not Path(getattr(access, name)).is_file():
            raise ZenohSetupError(f"zenoh.access.{name} {getattr(access, name)}: no such file")
    out: dict[str, Any] = {"root_ca_certificate": str(access.tls_ca_file), "enable_mtls": True}
    sides = (
        ["connect"]
        if role == "connect" or mode == "client"
        else ["listen"] + (["connect"] if section.connect else [])
    )
    for side in sides:
        out[f"{side}_certificate"] = str(access.tls_cert_file)
        out[f"{side}_private_key"] = str(access.tls_key_file)
    return out


def config_dict(
    section: ZenohSection, *, role: Role = "serve", key_prefix: str | None = None
) -> dict[str, Any]:
    """The Zenoh configuration as a plain dict (secrets included; never log it).

    role "serve": the daemon (or a router) as configured. role "connect": a worker or a command-line
    tool reaching that daemon: mode client, connecting to ``connect`` if set, else to the
    daemon's ``listen`` endpoints.
    """
    if role == "serve" or section.mode == "client":
        mode, listen, connect = section.mode, list(section.listen), list(section.connect)
    else:
        mode, listen = "client", []
        connect = list(section.connect) or [_loopback_of(ep) for ep in section.listen]
        if not connect:
            raise ZenohSetupError("zenoh: nothing to connect to (both 'connect' and 'listen' are empty)")
    if mode == "client":
        listen = []
    cfg: dict[str, Any] = {
        "mode": mode,
        "listen": {"endpoints": listen},
        "connect": {"endpoints": connect},
        "scouting": {
            "multicast": {"enabled": bool(section.multicast_scouting)},
            # Peers meshed through a hub only learn about each other by gossip over their links.
            "gossip": {"enabled": mode == "peer" and bool(connect)},
        },
    }
    access = section.access
    if access.enabled:
        uses_password = access.auth in ("password", "both")
        transport: dict[str, Any] = {}
        if access.auth != "password":
            transport["link"] = {"tls": _tls_dict(section, role=role, mode=mode)}
        if uses_password:
            try:
                password = resolve_secret(
                    access.password_env, access.password_file, what="zenoh.access password"
                )
            except ConfigError as exc:
                raise ZenohSetupError(str(exc)) from None
            usrpwd: dict[str, Any] = {"user": access.user, "password": password.get_secret_value()}
            if access.dictionary_file is not None and mode != "client":
                usrpwd["dictionary_file"] = str(access.dictionary_file)
                if key_prefix:
                    users = _dictionary_users(access.dictionary_file)
                    cfg["access_control"] = access_control_dict(dict(access.roles), users, key_prefix)
            transport["auth"] = {"usrpwd": usrpwd}
        elif access.roles and key_prefix and mode != "client":
            # TLS only: the roles name the common names of the certificates the cell's CA signed
            cfg["access_control"] = access_control_dict(
                dict(access.roles), None, key_prefix, subject_key="cert_common_names"
            )
        cfg["transport"] = transport
    return cfg


def router_config_dict(section: ZenohSection, listen: list[str], prefixes: list[str]) -> dict[str, Any]:
    """The Zenoh configuration of ``cellctl router``: the ``[zenoh]`` section's TLS and access
    settings (as the daemon serves them) in router mode on ``listen``, the access rules covering
    every cell of ``prefixes`` (each role's rules once per cell)."""
    routed = section.model_copy(update={"mode": "router", "listen": list(listen), "connect": []})
    cfg = config_dict(routed, role="serve", key_prefix=prefixes[0])
    cfg["scouting"]["gossip"] = {"enabled": True}
    acl = cfg.get("access_control")
    if acl is not None and len(prefixes) > 1:
        subject_key = next(k for k in acl["subjects"][0] if k != "id") if acl["subjects"] else "usernames"
        users = (
            None if subject_key == "cert_common_names" else _dictionary_users(section.access.dictionary_file)
        )
        rules, policies = [], []
        for i, prefix in enumerate(prefixes):
            one = access_control_dict(dict(section.access.roles), users, prefix, subject_key=subject_key)
            rules += [{**r, "id": f"{r['id']}_{i}"} for r in one["rules"]]
            policies += [
                {**p, "id": f"{p['id']}_{i}", "rules": [f"{r}_{i}" for r in p["rules"]]}
                for p in one["policies"]
            ]
        acl.update(rules=rules, policies=policies)
    return cfg


def build_zenoh_config(
    section: ZenohSection, *, role: Role = "serve", key_prefix: str | None = None
) -> zenoh.Config:
    """A ``zenoh.Config`` for this role from the ``[zenoh]`` section (see :func:`config_dict`)."""
    cfg = zenoh.Config()
    for key, value in config_dict(section, role=role, key_prefix=key_prefix).items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh raises ZError, which names the key
            raise ZenohSetupError(f"zenoh config key {key!r} refused: {exc}") from None
    return cfg


def open_session(cfg: zenoh.Config, *, what: str = "session") -> zenoh.Session:
    """Open a session; a failure becomes ZenohSetupError naming what was being opened."""
    try:
        return zenoh.open(cfg)
    except Exception as exc:
        raise ZenohSetupError(f"cannot open Zenoh {what}: {exc}") from None


def close_session(session: zenoh.Session | None) -> None:
    """Close a session, never raising (it is called from ``finally``)."""
    if session is None:
        return
    try:
        if not session.is_closed():
            session.close()
    except Exception as exc:
        log.warning("zenoh_close_failed", error=str(exc))


@contextlib.contextmanager
def session_scope(cfg: zenoh.Config, *, what: str = "session") -> Iterator[zenoh.Session]:
    """``with session_scope(cfg) as s:``; the session is closed however the block ends."""
    session = open_session(cfg, what=what)
    try:
        yield session
    finally:
        close_session(session)


# ----------------------------------------------------------------------------------------- asyncio bridge


def _hand_over(loop: asyncio.AbstractEventLoop, fn: Callable[..., Any], *args: Any) -> None:
    # Runs on a Zenoh thread: never touch asyncio objects here, only schedule onto the loop.
    with contextlib.suppress(RuntimeError):  # the loop is closed: the process is shutting down
        loop.call_soon_threadsafe(fn, *args)


def subscribe(
    session: zenoh.Session,
    key_expr: str,
    on_sample: Callable[[zenoh.Sample], Any],
    *,
    liveliness: bool = False,
) -> Any:
    """Declare a (liveliness) subscriber whose samples are handed to ``on_sample`` on the running loop.

    ``on_sample`` runs on the event loop thread, never on a Zenoh thread. For liveliness,
    history is requested, so tokens alive before the subscriber appear as PUTs.
    """
    loop = asyncio.get_running_loop()

    def cb(sample: zenoh.Sample) -> None:
        _hand_over(loop, on_sample, sample)

    if liveliness:
        return session.liveliness().declare_subscriber(key_expr, cb, history=True)
    return session.declare_subscriber(key_expr, cb)


def declare_async_queryable(
    session: zenoh.Session,
    key_expr: str,
    handler: Callable[[zenoh.Query], Awaitable[None]],
    *,
    on_error: Callable[[BaseException], None] | None = None,
) -> Any:
    """A queryable whose handler is a coroutine run on the loop; the query is finalised after it.

    A handler exception is logged and answered with an internal error, never propagated, so one
    bad request cannot stop the endpoint.
    """
    loop = asyncio.get_running_loop()

    async def run(query: zenoh.Query) -> None:
        try:
            await handler(query)
        except Exception as exc:
            # Answer first: the caller must hear about it even if logging itself fails.
            with contextlib.suppress(Exception):
                query.reply_err(json.dumps({"code": "internal", "field": "", "message": str(exc)}))
            with contextlib.suppress(Exception):
                log.exception("queryable_handler_failed", key=key_expr)
            if on_error is not None:
                on_error(exc)
        finally:
            with contextlib.suppress(Exception):
                query.drop()

    def start(query: zenoh.Query) -> None:
        task = loop.create_task(run(query))
        _TASKS.add(task)
        task.add_done_callback(_TASKS.discard)

    def cb(query: zenoh.Query) -> None:
        _hand_over(loop, start, query)

    return session.declare_queryable(key_expr, cb)


_TASKS: set[asyncio.Task[Any]] = set()


async def async_get(
    session: zenoh.Session,
    selector: str,
    *,
    payload: bytes | str | None = None,
    timeout_s: float = 10.0,
    attachment: bytes | None = None,
    encoding: str | None = None,
    congestion_control: zenoh.CongestionControl | None = None,
    target: zenoh.QueryTarget | None = None,
) -> list[zenoh.Reply]:
    """Awaitable ``session.get``: every reply, collected when Zenoh finalises the query.

    An empty list means no queryable answered within ``timeout_s``.
    """
    loop = asyncio.get_running_loop()
    done: asyncio.Future[list[zenoh.Reply]] = loop.create_future()
    replies: list[zenoh.Reply] = []

    def on_reply(reply: zenoh.Reply) -> None:
        replies.append(reply)  # list.append is atomic; the loop reads it only after on_done

    def finish() -> None:
        if not done.done():
            done.set_result(list(replies))

    def on_done() -> None:
        _hand_over(loop, finish)

    kwargs: dict[str, Any] = {"timeout": timeout_s}
    if payload is not None:
        kwargs["payload"] = payload
    if attachment is not None:
        kwargs["attachment"] = attachment
    if encoding is not None:
        kwargs["encoding"] = encoding
    if congestion_control is not None:
        kwargs["congestion_control"] = congestion_control
    if target is not None:
        kwargs["target"] = target
    session.get(selector, zenoh.handlers.Callback(on_reply, on_done), **kwargs)
    return await done


# ------------------------------------------------------------------------------- client calls


class ApiCallError(Exception):
    """A query that got an error reply (``error`` holds the ApiError) or no reply at all."""

    def __init__(self, key: str, error: ApiError | None, message: str) -> None:
        self.key = key
        self.error = error
        super().__init__(f"{key}: {message}")


async def call(
    session: Any, key: str, payload: bytes | str | None, reply_model: type[M], *, timeout_s: float = 10.0
) -> M:
    """Query one of the cell's queryables and parse the reply (what `cellctl scan` and friends use).

    Raises ApiCallError on an error reply (with the parsed ApiError), on no reply within
    ``timeout_s`` (daemon not running or too slow), or on a reply that does not parse.
    """
    replies = await async_get(session, key, payload=payload, timeout_s=timeout_s)
    if not replies:
        raise ApiCallError(key, None, f"no reply within {timeout_s} s (is the daemon running?)")
    reply = replies[0]
    if reply.ok is None:
        raw = reply.err.payload.to_bytes()
        try:
            err = ApiError.model_validate_json(raw)
        except ValidationError:
            raise ApiCallError(key, None, f"error reply: {raw[:200]!r}") from None
        where = f"{err.field}: " if err.field else ""
        raise ApiCallError(key, err, f"{err.code}: {where}{err.message}")
    try:
        return reply_model.model_validate_json(reply.ok.payload.to_bytes())
    except ValidationError as exc:
        raise ApiCallError(key, None, f"reply is not a {reply_model.__name__}: {exc}") from None


async def list_workers(session: Any, keys: Keys, *, timeout_s: float = 2.0) -> list[WorkerAnnouncement]:
    """Every worker's announcement (for `cellctl status`), sorted by id; unreadable replies skipped."""
    replies = await async_get(
        session, keys.worker_info("*"), timeout_s=timeout_s, target=zenoh.QueryTarget.ALL
    )
    out = []
    for r in replies:
        if r.ok is None:
            continue
        try:
            out.append(WorkerAnnouncement.model_validate_json(r.ok.payload.to_bytes()))
        except ValidationError:
            log.warning("worker_announcement_malformed", key=str(r.ok.key_expr))
    return sorted(out, key=lambda a: a.worker_id)
