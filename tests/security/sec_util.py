"""Helpers for the security tests (a uniquely named module: `conftest` is ambiguous to import)."""

from __future__ import annotations

from pathlib import Path

from cellctl.config import ZenohAccess, ZenohSection

#: user -> password of the test cell's dictionary; "eve" is known to Zenoh but has no role
PASSWORDS = {
    "daemon": "dmn-7f3a-secret",
    "alice": "alc-91c2-secret",
    "w1": "wrk-55d0-secret",
    "bob": "bob-0e4b-secret",
    "eve": "eve-a3a1-secret",
}
ROLES = {"operator": ["alice"], "worker": ["w1"], "viewer": ["bob"]}


def write_dictionary(path: Path, passwords: dict[str, str] = PASSWORDS) -> Path:
    """The serving side's user:password file, owner-only as required."""
    path.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
    path.chmod(0o600)
    return path


def env_name(user: str) -> str:
    return f"TEST_SEC_ZENOH_PW_{user.upper()}"


def section(port: int, user: str, dictionary: Path | None = None, roles: dict | None = None) -> ZenohSection:
    """A [zenoh] section on loopback for ``user`` (its password from the environment, see env_name)."""
    access = ZenohAccess(
        enabled=True,
        user=user,
        password_env=env_name(user),
        dictionary_file=dictionary,
        roles=roles if roles is not None else ROLES,
    )
    return ZenohSection(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False, access=access)
