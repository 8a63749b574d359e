"""The log-in under attack, over HTTP: parallel guesses, junk names, and the crew locked out.

One HMI server in this process (tests/support/hmi_server.py, no cell); clients from different
loopback addresses (127.0.0.x) stand for the attacker's machine and the crew's panel.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import pytest

from cellctl.hmi import auth as auth_mod
from cellctl.hmi.auth import LoginLimiter
from tests.support.hmi_server import USERS, LocalHmi
from tests.support.waits import wait_until

ATTACKER, PANEL, OTHER = "127.0.0.1", "127.0.0.2", "127.0.0.3"


@pytest.fixture
def hmi(tmp_path: Path) -> Iterator[LocalHmi]:
    with LocalHmi(tmp_path) as h:
        yield h
    assert "hmi_request_error" not in h.log.getvalue()  # no request ended in an exception


def _count_checks(hmi: LocalHmi) -> list[str]:
    """The user names whose password the server checked (calls of Authenticator.login)."""
    checked: list[str] = []
    lock = threading.Lock()
    real = hmi.auth.login

    def login(name: str, password: str) -> auth_mod.Session | None:
        with lock:
            checked.append(name)
        return real(name, password)

    hmi.auth.login = login  # type: ignore[method-assign]
    return checked


async def _logins(url: str, bodies: list[object], *, source: str, parallel: bool = True) -> list[int]:
    conn = aiohttp.TCPConnector(local_addr=(source, 0), limit=0)
    async with aiohttp.ClientSession(connector=conn) as c:

        async def one(body: object) -> int:
            async with c.post(url + "/api/login", json=body) as r:
                await r.read()
                return r.status

        if parallel:
            return list(await asyncio.gather(*(one(b) for b in bodies)))
        return [await one(b) for b in bodies]


def test_thirty_parallel_wrong_passwords_for_one_user_check_at_most_five(hmi: LocalHmi) -> None:
    checked = _count_checks(hmi)
    body = {"user": "olga", "password": "wrong-password"}
    codes = asyncio.run(_logins(hmi.url, [body] * 30, source=ATTACKER))
    assert len(checked) == hmi.auth.limiter.max_failures == 5, checked
    assert sorted(codes) == [401] * 5 + [429] * 25, codes
    # and many users at once from one address: at most the address's 20
    checked.clear()
    bodies = [{"user": f"user{k}", "password": "x"} for k in range(60)]
    codes = asyncio.run(_logins(hmi.url, bodies, source=OTHER))
    assert len(checked) == hmi.auth.limiter.max_failures_ip == 20
    assert codes.count(401) == 20 and codes.count(429) == 40


def test_the_crew_logs_in_from_its_panel_while_an_attacker_guesses_its_password(hmi: LocalHmi) -> None:
    wrong = {"user": "olga", "password": "guess"}
    right = {"user": "olga", "password": USERS["olga"][1]}

    checked = _count_checks(hmi)

    async def attack_and_log_in() -> tuple[list[int], list[int]]:
        attack = asyncio.ensure_future(_logins(hmi.url, [wrong] * 40, source=ATTACKER))
        await wait_until(lambda: checked, 0.05, "the attack under way (a password checked)")
        crew = await _logins(hmi.url, [right], source=PANEL)
        return await attack, crew

    attack, crew = asyncio.run(attack_and_log_in())
    assert 429 in attack
    assert crew == [200]
    # olga's name is now over its count: the attacker's address is refused even the right password,
    # the panel (no failures of its own) is let in again
    assert asyncio.run(_logins(hmi.url, [right], source=ATTACKER)) == [429]
    assert asyncio.run(_logins(hmi.url, [right], source=PANEL)) == [200]
    # the attacker's address flooding every user name leaves the other crew members' log-ins alone
    names = [{"user": n, "password": "guess"} for n in ("vic", "erin", "nobody")] * 10
    asyncio.run(_logins(hmi.url, names, source=ATTACKER))
    vic = {"user": "vic", "password": USERS["vic"][1]}
    assert asyncio.run(_logins(hmi.url, [vic], source=PANEL)) == [200]


@pytest.mark.slow  # 10 000 requests: about 10 s
def test_ten_thousand_junk_logins_leave_the_limiter_bounded(tmp_path: Path) -> None:
    # the limiter's memory per entry is tests/hmi/test_auth.py's (tracemalloc); here: what is stored
    lim = LoginLimiter(max_keys=256)
    with LocalHmi(tmp_path, limiter=lim) as hmi:
        checked = _count_checks(hmi)
        long_names = [{"user": f"{k}-" + "n" * 4000, "password": "x"} for k in range(5_000)]
        short_names = [{"user": f"junk{k}", "password": "x"} for k in range(5_000)]
        codes = asyncio.run(_run_batches(hmi.url, long_names))
        # names the users file cannot hold: 400 before anything is stored or checked
        assert codes == [400] * 5000 and lim.entries() == 0 and not checked
        codes = asyncio.run(_run_batches(hmi.url, short_names))
        # distinct short names from one address: its 20 checked, every other one 429, nothing stored
        assert codes.count(401) == 20 and codes.count(429) == 4980
        assert len(checked) == 20
        assert lim.entries() == 21  # one address, 20 names
        assert not hmi.server.sockets and len(hmi.auth.sessions) == 0
    assert "hmi_request_error" not in hmi.log.getvalue()


async def _run_batches(url: str, bodies: list[object]) -> list[int]:
    codes: list[int] = []
    for k in range(0, len(bodies), 200):
        codes += await _logins(url, bodies[k : k + 200], source=ATTACKER, parallel=False)
    return codes


def test_malformed_and_oversized_log_in_bodies_are_refused_with_4xx(hmi: LocalHmi) -> None:
    async def post(data: bytes) -> int:
        async with aiohttp.ClientSession() as c, c.post(hmi.url + "/api/login", data=data) as r:
            return r.status

    cases = {
        b"[" * 3000: 400,  # nested deeper than the parser's recursion
        b'{"user": "olga", "password": "\xff\xfe"}': 400,  # not UTF-8
        b'{"user": ["olga"], "password": "x"}': 400,
        b'{"user": "olga"}': 400,
        b'{"user": "ol ga", "password": "x"}': 400,
        b'{"user": "olga", "password": "' + b"p" * 5000 + b'"}': 413,
        b"": 400,
    }
    assert {k[:20]: asyncio.run(post(k)) for k in cases} == {k[:20]: v for k, v in cases.items()}
    assert hmi.auth.limiter.entries() == 0
