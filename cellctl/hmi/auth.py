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

import contextlib
import hashlib
import hmac
import os
import re
import secrets
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
NAME_MAX = 64
_NAME = re.compile(rf"^[A-Za-z0-9_.-]{{1,{NAME_MAX}}}$")
_SCRYPT = {"n": 2**14, "r": 8, "p": 1}
SESSION_TTL_S = 12 * 3600.0


def valid_name(name: str) -> bool:
    """Whether ``name`` is a user name the users file could hold (1 to 64 letters, digits, _ . -)."""
    return bool(_NAME.match(name))


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


class _Window:
    """Times of recent attempts per key, within ``window_s``, for at most ``max_keys`` keys.

    Keys are dropped when their last attempt leaves the window and, when the table is full, the key
    used longest ago is dropped first (LRU), so the table's size is bounded whatever the clients send.
    Reading (:meth:`count`) never creates a key."""

    def __init__(self, window_s: float, max_keys: int) -> None:
        self.window_s = window_s
        self.max_keys = max_keys
        self._t: OrderedDict[str, deque[float]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._t)

    def _trim(self, key: str, now: float) -> deque[float] | None:
        q = self._t.get(key)
        if q is None:
            return None
        while q and now - q[0] > self.window_s:
            q.popleft()
        if not q:
            del self._t[key]
            return None
        return q

    def count(self, key: str, now: float) -> int:
        q = self._trim(key, now)
        return len(q) if q else 0

    def oldest(self, key: str, now: float) -> float:
        q = self._trim(key, now)
        return q[0] if q else now

    def add(self, key: str, now: float) -> None:
        q = self._trim(key, now)
        if q is None:
            # the table is in order of last attempt: drop the keys whose last one left the window
            while self._t:
                head, hq = next(iter(self._t.items()))
                if hq and now - hq[-1] <= self.window_s:
                    break
                del self._t[head]
            while len(self._t) >= self.max_keys:
                self._t.popitem(last=False)  # the key used longest ago
            q = self._t[key] = deque()
        self._t.move_to_end(key)
        q.append(now)

    def remove(self, key: str, t: float) -> None:
        q = self._t.get(key)
        if q is None:
            return
        with contextlib.suppress(ValueError):
            q.remove(t)
        if not q:
            del self._t[key]


@dataclass(frozen=True)
class Attempt:
    """A log-in attempt counted before its password is checked (:meth:`LoginLimiter.reserve`)."""

    address: str
    user: str
    t: float


@dataclass
class LoginLimiter:
    """Failed log-ins, counted per client address and per user name (docs/hmi.md, "Log-in limits").

    An attempt is counted *before* its password is checked (:meth:`reserve`) and only uncounted when
    the password was right (:meth:`settle`), so parallel attempts are limited exactly like
    sequential ones. Per address: at most ``max_failures_ip`` in ``window_s``, whatever the user
    names. Per user name: at most ``max_failures`` in ``window_s``, enforced only against addresses
    with failures of their own in the window, so an outsider who exhausts a crew member's count does
    not lock that crew member out of a panel that has not failed. Each table holds at most
    ``max_keys`` keys (expired first, then least recently used); a refused attempt stores nothing.
    """

    max_failures: int = 5
    max_failures_ip: int = 20
    window_s: float = 60.0
    max_keys: int = 4096
    clock: Any = time.monotonic
    _ips: _Window = field(init=False)
    _users: _Window = field(init=False)

    def __post_init__(self) -> None:
        self._ips = _Window(self.window_s, self.max_keys)
        self._users = _Window(self.window_s, self.max_keys)

    def entries(self) -> int:
        """Keys held (both tables): bounded by ``2 * max_keys``."""
        return len(self._ips) + len(self._users)

    def blocked(self, address: str, user: str) -> float:
        """Seconds until an attempt for ``user`` from ``address`` is accepted again (0: now)."""
        now = self.clock()
        waits = []
        n_ip = self._ips.count(address, now)
        if n_ip >= self.max_failures_ip:
            waits.append(self.window_s - (now - self._ips.oldest(address, now)))
        if n_ip > 0 and self._users.count(user, now) >= self.max_failures:
            waits.append(self.window_s - (now - self._users.oldest(user, now)))
        return max(waits, default=0.0)

    def reserve(self, address: str, user: str) -> Attempt | float:
        """Count an attempt as failed before its password is checked: the :class:`Attempt`, or the
        seconds to wait (> 0) when it is refused (then nothing is stored)."""
        wait = self.blocked(address, user)
        if wait > 0:
            return max(wait, 1e-3)
        now = self.clock()
        self._ips.add(address, now)
        self._users.add(user, now)
        return Attempt(address, user, now)

    def settle(self, attempt: Attempt, ok: bool) -> None:
        """The password was checked: a right one is uncounted, a wrong one stays counted."""
        if ok:
            self._ips.remove(attempt.address, attempt.t)
            self._users.remove(attempt.user, attempt.t)


class Authenticator:
    """Users from the secrets file, sessions in memory (a restart logs everybody out)."""

    def __init__(self, users: dict[str, User], *, ttl_s: float = SESSION_TTL_S) -> None:
        self.users = users
        self.ttl_s = ttl_s
        self.sessions: dict[str, Session] = {}
        self.limiter = LoginLimiter()
        # a hash to check against when the user is unknown: the same time either way
        self._dummy = hash_password(secrets.token_hex(8))

    def verify(self, name: str, password: str) -> User | None:
        """The user when ``password`` is theirs, else None; an unknown name costs the same hash
        (no timing oracle). The HMI's log-in and the OPC UA server's both check here."""
        user = self.users.get(name)
        ok = verify_password(password, user.password_hash if user else self._dummy)
        return user if ok and user else None

    def login(self, name: str, password: str) -> Session | None:
        user = self.verify(name, password)
        if user is None:
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
