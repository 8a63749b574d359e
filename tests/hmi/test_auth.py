"""HMI users, password hashes, roles and the log-in limiter (no network)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cellctl.hmi.auth import (
    Authenticator,
    AuthError,
    LoginLimiter,
    add_user,
    allowed,
    hash_password,
    load_users,
    role_cap,
    verify_password,
)


def test_a_hash_verifies_its_password_only_and_is_salted() -> None:
    h = hash_password("correct horse")
    assert verify_password("correct horse", h)
    assert not verify_password("correct horsE", h)
    assert hash_password("correct horse") != h  # a fresh salt each time
    assert "correct" not in h
    assert not verify_password("x", "plain:text") and not verify_password("x", "scrypt$1$2$3$zz$yy")


def test_the_users_file_is_written_private_and_refused_when_readable_by_others(tmp_path: Path) -> None:
    f = tmp_path / "users"
    add_user(f, "olga", "operator", "operator-pw")
    add_user(f, "vic", "viewer", "viewer-pw1")
    add_user(f, "olga", "engineer", "new-password")  # replaces
    assert os.stat(f).st_mode & 0o777 == 0o600
    users = load_users(f)
    assert {u.name: u.role for u in users.values()} == {"olga": "engineer", "vic": "viewer"}
    assert "new-password" not in f.read_text()
    os.chmod(f, 0o644)
    with pytest.raises(AuthError, match="chmod 600"):
        load_users(f)


@pytest.mark.parametrize(
    ("name", "role", "pw", "msg"),
    [
        ("bad name", "viewer", "password1", "user name"),
        ("a", "admin", "password1", "role"),
        ("a", "viewer", "short", "8"),
    ],
)
def test_bad_users_are_refused_in_words(tmp_path: Path, name: str, role: str, pw: str, msg: str) -> None:
    with pytest.raises(AuthError, match=msg):
        add_user(tmp_path / "u", name, role, pw)


def test_a_malformed_line_names_the_file_and_line(tmp_path: Path) -> None:
    f = tmp_path / "u"
    f.write_text("# users\nolga:superuser:scrypt$1\n")
    os.chmod(f, 0o600)
    with pytest.raises(AuthError, match=r"u:2: expected name:role:hash"):
        load_users(f)


def test_roles_include_the_ones_below_and_nothing_else() -> None:
    assert not allowed("viewer", "trigger") and not allowed("viewer", "abort")
    assert (
        allowed("operator", "trigger") and allowed("operator", "pause") and not allowed("operator", "reset")
    )
    assert allowed("engineer", "reset") and allowed("engineer", "reanalyse") and allowed("engineer", "abort")
    assert not allowed("engineer", "shutdown") and not allowed("root", "trigger")


def test_sessions_and_wrong_passwords(tmp_path: Path) -> None:
    f = tmp_path / "u"
    add_user(f, "olga", "operator", "operator-pw")
    auth = Authenticator(load_users(f), ttl_s=60)
    assert auth.login("olga", "nope") is None and auth.login("nobody", "operator-pw") is None
    s = auth.login("olga", "operator-pw")
    assert s is not None and s.role == "operator" and s.csrf != s.token
    assert auth.session(s.token) is s
    auth.logout(s.token)
    assert auth.session(s.token) is None and auth.session(None) is None


def test_the_limiter_blocks_after_five_failures_per_key_for_the_window() -> None:
    lim = LoginLimiter(max_failures=5, window_s=60.0)
    for _ in range(4):
        lim.failed("ip:1", "user:olga")
    assert lim.blocked("ip:1", "user:olga") == 0.0
    lim.failed("ip:1", "user:olga")
    assert 59.0 < lim.blocked("ip:2", "user:olga") <= 60.0  # the user name is blocked from any address
    assert lim.blocked("ip:2", "user:vic") == 0.0
    assert lim.blocked("ip:1", "user:vic") == 0.0  # an address shared by several users allows more
    for _ in range(15):
        lim.failed("ip:1")
    assert lim.blocked("ip:1", "user:vic") > 0


def test_the_hmis_zenoh_identity_caps_what_its_users_may_do() -> None:
    roles = {"operator": ["hmi"], "viewer": ["qa-screen"], "worker": ["w1"]}
    assert role_cap(True, "hmi", roles) == "engineer"
    assert role_cap(True, "qa-screen", roles) == "viewer"
    assert role_cap(False, "qa-screen", roles) == "engineer" and role_cap(True, "x", {}) == "engineer"
    assert not allowed("engineer", "reset", cap="viewer") and not allowed("operator", "trigger", cap="viewer")
    assert allowed("engineer", "reset", cap="engineer")
