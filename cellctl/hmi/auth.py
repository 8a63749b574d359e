"""The HMI's users, roles and sessions.

Users live in a secrets file (``chmod 600``), one per line: ``name:role:scrypt$n$r$p$salt$hash``
(``hashlib.scrypt``, salt and hash in hex); ``cellctl hmi adduser`` writes it. Passwords are never
stored or logged in clear.

Roles, each including the ones before it: ``viewer`` (sees), ``operator`` (start, pause, resume,
abort), ``engineer`` (reset, re-analyse). They map onto the Zenoh roles of ``[zenoh.access]``
(:data:`ZENOH_ROLE`): a viewer's requests are those a Zenoh ``viewer`` may make, an operator's and an
engineer's those of a Zenoh ``operator``. The server checks every request against the session's role
(:func:`allowed`) whatever the page shows.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import secrets
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from cellctl.config import ConfigError, check_secret_file_mode

ROLES = ("viewer", "operator", "engineer")
#: which Zenoh role of [zenoh.access] each HMI role acts as
ZENOH_ROLE = {"viewer": "viewer", "operator": "operator", "engineer": "operator"}
#: the least role each action needs
ACTION_ROLE = {
    "trigger": "operator",
    "pause": "operator",
    "resume": "operator",
    "abort": "operator",
    "reset": "engineer",
    "reanalyse": "engineer",
}
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_SCRYPT = {"n": 2**14, "r": 8, "p": 1}
SESSION_TTL_S = 12 * 3600.0


class AuthError(Exception):
    """A users file or an entry that cannot be used (names the file and line)."""


def allowed(role: str, action: str, *, cap: str = "engineer") -> bool:
    """Whether ``role`` may do ``action`` (an :data:`ACTION_ROLE` key); ``cap``: the most the HMI's
    own Zenoh identity allows (:func:`role_cap`)."""
    need = ACTION_ROLE.get(action)
    if need is None or role not in ROLES or cap not in ROLES:
        return False
    return min(ROLES.index(role), ROLES.index(cap)) >= ROLES.index(need)


def role_cap(access_enabled: bool, zenoh_user: str, zenoh_roles: dict[str, list[str]]) -> str:
    """The most an HMI user may do, given the Zenoh roles of the HMI's own identity: with access
    control and roles, a Zenoh user without ``operator`` (or ``daemon``) caps every HMI user at
    ``viewer`` (its queries would get no reply); otherwise ``engineer``."""
    if not access_enabled or not zenoh_roles:
        return "engineer"
    mine = {role for role, users in zenoh_roles.items() if zenoh_user in users}
    return "engineer" if mine & {"operator", "daemon"} else "viewer"


def hash_password(
    password: str, *, salt: bytes | None = None, n: int = _SCRYPT["n"], r: int = 8, p: int = 1
) -> str:
    salt = salt or secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=32)
    return f"scrypt${n}${r}${p}${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    try:
        kind, n, r, p, salt, digest = stored.split("$")
        if kind != "scrypt":
            return False
        got = hashlib.scrypt(
            password.encode(), salt=bytes.fromhex(salt), n=int(n), r=int(r), p=int(p), dklen=len(digest) // 2
        )
    except (ValueError, MemoryError):
        return False
    return hmac.compare_digest(got.hex(), digest)


@dataclass(frozen=True)
class User:
    name: str
    role: str
    password_hash: str


def load_users(path: str | Path) -> dict[str, User]:
    """The users of a secrets file (mode checked: group/others may not read it)."""
    path = Path(path)
    try:
        check_secret_file_mode(path, what="hmi users file")
    except ConfigError as exc:
        raise AuthError("; ".join(exc.problems)) from None
    users: dict[str, User] = {}
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(":")
        if len(parts) != 3 or not _NAME.match(parts[0]) or parts[1] not in ROLES:
            raise AuthError(f"{path}:{no}: expected name:role:hash with role one of {', '.join(ROLES)}")
        users[parts[0]] = User(*parts)
    return users


def add_user(path: str | Path, name: str, role: str, password: str) -> None:
    """Add or replace a user in the secrets file (created with mode 600)."""
    if not _NAME.match(name):
        raise AuthError(f"user name {name!r}: 1 to 64 letters, digits, _ . -")
    if role not in ROLES:
        raise AuthError(f"role {role!r}: one of {', '.join(ROLES)}")
    if len(password) < 8:
        raise AuthError("password: at least 8 characters")
    path = Path(path)
    lines = []
    if path.exists():
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith(f"{name}:")]
    lines.append(f"{name}:{role}:{hash_password(password)}")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")
    os.chmod(path, 0o600)


@dataclass
class Session:
    token: str
    user: str
    role: str
    csrf: str
    expires: float


@dataclass
class LoginLimiter:
    """At most ``max_failures`` failed log-ins per key (``user:<name>``) in ``window_s``; keys
    starting ``ip:`` (a client address, which several users may share) allow ``max_failures_ip``."""

    max_failures: int = 5
    max_failures_ip: int = 20
    window_s: float = 60.0
    _fails: dict[str, deque[float]] = field(default_factory=dict)

    def _recent(self, key: str, now: float) -> deque[float]:
        q = self._fails.setdefault(key, deque())
        while q and now - q[0] > self.window_s:
            q.popleft()
        return q

    def blocked(self, *keys: str) -> float:
        """Seconds until a log-in from these keys is accepted again (0: now)."""
        now = time.monotonic()
        waits = []
        for k in keys:
            q = self._recent(k, now)
            if len(q) >= (self.max_failures_ip if k.startswith("ip:") else self.max_failures):
                waits.append(self.window_s - (now - q[0]))
        return max(waits, default=0.0)

    def failed(self, *keys: str) -> None:
        now = time.monotonic()
        for k in keys:
            self._recent(k, now).append(now)


class Authenticator:
    """Users from the secrets file, sessions in memory (a restart logs everybody out)."""

    def __init__(self, users: dict[str, User], *, ttl_s: float = SESSION_TTL_S) -> None:
        self.users = users
        self.ttl_s = ttl_s
        self.sessions: dict[str, Session] = {}
        self.limiter = LoginLimiter()
        # a hash to check against when the user is unknown: the same time either way
        self._dummy = hash_password(secrets.token_hex(8))

    def login(self, name: str, password: str) -> Session | None:
        user = self.users.get(name)
        ok = verify_password(password, user.password_hash if user else self._dummy)
        if not (ok and user):
            return None
        s = Session(
            secrets.token_urlsafe(32),
            user.name,
            user.role,
            secrets.token_urlsafe(32),
            time.time() + self.ttl_s,
        )
        self.sessions[s.token] = s
        return s

    def session(self, token: str | None) -> Session | None:
        s = self.sessions.get(token or "")
        if s is None:
            return None
        if s.expires < time.time():
            self.sessions.pop(s.token, None)
            return None
        return s

    def logout(self, token: str | None) -> None:
        self.sessions.pop(token or "", None)
