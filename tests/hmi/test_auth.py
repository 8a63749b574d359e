"""HMI users, password hashes, roles and the log-in limiter (no network)."""

from __future__ import annotations

import gc
import os
import tracemalloc
from pathlib import Path

import pytest

from cellctl.hmi.auth import (
    Attempt,
    Authenticator,
    AuthError,
    LoginLimiter,
    add_user,
    allowed,
    hash_password,
    load_users,
    role_cap,
    valid_name,
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


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_the_limiter_counts_an_attempt_before_its_check_and_uncounts_a_right_one() -> None:
    lim = LoginLimiter(max_failures=5, max_failures_ip=20, window_s=60.0, clock=Clock())
    # five attempts in flight at once (none checked yet) use up the user's five
    held = [lim.reserve("10.0.0.1", "olga") for _ in range(5)]
    assert all(isinstance(a, Attempt) for a in held)
    assert not isinstance(lim.reserve("10.0.0.1", "olga"), Attempt)
    lim.settle(held[0], ok=True)  # a right password gives its slot back
    again = lim.reserve("10.0.0.1", "olga")
    assert isinstance(again, Attempt)
    lim.settle(again, ok=False)
    assert 59.0 < lim.blocked("10.0.0.1", "olga") <= 60.0


def test_a_refused_attempt_stores_nothing() -> None:
    lim = LoginLimiter(max_failures_ip=2, clock=Clock())
    for name in ("a", "b"):
        assert isinstance(lim.reserve("10.0.0.9", name), Attempt)
    before = lim.entries()
    for k in range(100):
        assert not isinstance(lim.reserve("10.0.0.9", f"new-{k}"), Attempt)
    assert lim.entries() == before == 3  # one address, two names


def test_a_user_name_locked_from_elsewhere_still_logs_in_from_an_address_without_failures() -> None:
    lim = LoginLimiter(max_failures=5, max_failures_ip=20, window_s=60.0, clock=Clock())
    for _ in range(5):
        a = lim.reserve("10.6.6.6", "olga")
        assert isinstance(a, Attempt)
        lim.settle(a, ok=False)
    assert lim.blocked("10.6.6.6", "olga") > 0  # the attacker's address: locked for olga
    assert lim.blocked("10.6.6.6", "vic") == 0  # ... not for another name (up to 20 in all)
    crew = lim.reserve("10.0.0.1", "olga")  # the panel, no failures of its own: olga's password is checked
    assert isinstance(crew, Attempt)
    # a wrong one from the panel too: now the panel waits as the attacker does
    lim.settle(crew, ok=False)
    assert lim.blocked("10.0.0.1", "olga") > 0
    # the address limit holds whatever the names
    for k in range(19):
        lim.settle(lim.reserve("10.7.7.7", f"u{k}"), ok=False)  # type: ignore[arg-type]
    last = lim.reserve("10.7.7.7", "u19")
    assert isinstance(last, Attempt)
    lim.settle(last, ok=False)
    assert lim.blocked("10.7.7.7", "anyone") > 0


def test_the_limiters_entries_expire_after_the_window_and_never_exceed_max_keys() -> None:
    clock = Clock()
    lim = LoginLimiter(max_failures_ip=3, window_s=60.0, max_keys=100, clock=clock)
    for k in range(10_000):  # 10 000 junk attempts from 10 000 addresses, each a new name
        a = lim.reserve(f"10.{k // 256 % 256}.{k % 256}.{k // 65536}", f"junk{k}")
        assert isinstance(a, Attempt)
        lim.settle(a, ok=False)
        assert lim.entries() <= 200
    clock.t += 61.0
    a = lim.reserve("10.0.0.1", "olga")
    assert isinstance(a, Attempt)
    assert lim.entries() == 2  # the expired ones went when a new key came


def test_the_limiters_memory_stays_flat_under_junk() -> None:
    lim = LoginLimiter(max_keys=1000, clock=Clock())

    def junk(n: int, tag: str) -> None:
        for k in range(n):
            a = lim.reserve(f"{tag}-{k}", f"{tag}{k}" + "x" * 50)
            if isinstance(a, Attempt):
                lim.settle(a, ok=False)

    tracemalloc.start()
    try:
        junk(2_000, "a")  # fills the tables
        gc.collect()
        full = tracemalloc.get_traced_memory()[0]
        junk(10_000, "b")
        gc.collect()
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert lim.entries() <= 2000
    assert after - full < 64 * 1024, (full, after)  # entries replaced, not added


def test_user_names_the_users_file_could_not_hold_are_invalid() -> None:
    assert valid_name("olga") and valid_name("a" * 64) and valid_name("j.doe-2_x")
    assert not valid_name("") and not valid_name("a" * 65) and not valid_name("olga ") and not valid_name("ö")


def test_the_hmis_zenoh_identity_caps_what_its_users_may_do() -> None:
    roles = {"operator": ["hmi"], "viewer": ["qa-screen"], "worker": ["w1"]}
    assert role_cap(True, "hmi", roles) == "engineer"
    assert role_cap(True, "qa-screen", roles) == "viewer"
    assert role_cap(False, "qa-screen", roles) == "engineer" and role_cap(True, "x", {}) == "engineer"
    assert not allowed("engineer", "reset", cap="viewer") and not allowed("operator", "trigger", cap="viewer")
    assert allowed("engineer", "reset", cap="engineer")


def test_an_ipv6_client_is_limited_by_its_64_prefix() -> None:
    from cellctl.hmi.server import client_key

    assert client_key("2001:db8:1:2:aaaa::1") == client_key("2001:db8:1:2:bbbb::9") == "2001:db8:1:2::/64"
    assert client_key("2001:db8:1:3::1") != client_key("2001:db8:1:2::1")
    assert client_key("::ffff:10.0.0.7") == "10.0.0.7" == client_key("10.0.0.7")
    assert client_key(None) == "?" and client_key("unix-socket") == "unix-socket"
