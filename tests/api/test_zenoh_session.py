"""Zenoh configuration from [zenoh] and the asyncio bridge, checked on loopback."""

from __future__ import annotations

import asyncio
import threading

import pytest
import zenoh

from cellctl.api.session import (
    ZenohSetupError,
    async_get,
    build_zenoh_config,
    close_session,
    config_dict,
    declare_async_queryable,
    open_session,
    subscribe,
)
from cellctl.config import ZenohAccess, ZenohSection
from tests.support.ports import free_port


def test_daemon_config_listens_only_where_configured_with_scouting_off():
    cfg = config_dict(ZenohSection(listen=["tcp/127.0.0.1:7447"]), role="serve")
    assert cfg["mode"] == "peer"
    assert cfg["listen"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    assert cfg["connect"]["endpoints"] == []
    assert cfg["scouting"] == {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    assert "transport" not in cfg


def test_worker_config_is_a_client_of_the_daemon_listen_endpoint_via_loopback():
    cfg = config_dict(ZenohSection(listen=["tcp/0.0.0.0:7450", "tcp/[::]:7451"]), role="connect")
    assert cfg["mode"] == "client" and cfg["listen"]["endpoints"] == []
    assert cfg["connect"]["endpoints"] == ["tcp/127.0.0.1:7450", "tcp/[::1]:7451"]
    routed = config_dict(ZenohSection(connect=["tcp/10.0.0.5:7447"]), role="connect")
    assert routed["connect"]["endpoints"] == ["tcp/10.0.0.5:7447"]


def test_peer_connected_to_a_hub_gossips_and_multicast_follows_the_setting():
    cfg = config_dict(
        ZenohSection(mode="peer", listen=[], connect=["tcp/10.0.0.5:7447"], multicast_scouting=True),
        role="serve",
    )
    assert cfg["scouting"] == {"multicast": {"enabled": True}, "gossip": {"enabled": True}}
    router = config_dict(ZenohSection(mode="router", listen=["tcp/127.0.0.1:7447"]), role="serve")
    assert router["scouting"]["gossip"] == {"enabled": False}


def test_access_settings_give_usrpwd_and_an_acl_confined_to_the_cell_prefix(tmp_path, monkeypatch):
    monkeypatch.setenv("TEST_ZENOH_PW", "s3cret")
    users = tmp_path / "users.txt"
    users.write_text("# users\ncellctl:s3cret\nmes:other\n")
    users.chmod(0o600)  # a dictionary readable by others is refused
    access = ZenohAccess(enabled=True, password_env="TEST_ZENOH_PW", dictionary_file=users)
    cfg = config_dict(ZenohSection(access=access), role="serve", key_prefix="cell/c1")
    assert cfg["transport"]["auth"]["usrpwd"] == {
        "user": "cellctl",
        "password": "s3cret",
        "dictionary_file": str(users),
    }
    acl = cfg["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert acl["rules"][0]["key_exprs"] == ["cell/c1", "cell/c1/**"]
    assert acl["subjects"][0]["usernames"] == ["cellctl", "mes"]
    client = config_dict(ZenohSection(access=access), role="connect", key_prefix="cell/c1")
    assert client["transport"]["auth"]["usrpwd"] == {"user": "cellctl", "password": "s3cret"}
    assert "access_control" not in client
    build_zenoh_config(ZenohSection(access=access), role="serve", key_prefix="cell/c1")  # zenoh accepts it


def test_missing_password_is_a_setup_error_naming_the_variable(monkeypatch):
    monkeypatch.delenv("NO_SUCH_PW_VAR", raising=False)
    with pytest.raises(ZenohSetupError, match="NO_SUCH_PW_VAR"):
        config_dict(ZenohSection(access=ZenohAccess(enabled=True, password_env="NO_SUCH_PW_VAR")))


async def _put_until_received(session, key: str, payload: bytes, queue: asyncio.Queue, timeout_s: float = 15):
    """Put until the subscriber has it: a new subscription takes a moment to reach the publisher."""
    t_end = asyncio.get_running_loop().time() + timeout_s
    while True:
        session.put(key, payload)
        try:
            return await asyncio.wait_for(queue.get(), 0.5)
        except TimeoutError:
            if asyncio.get_running_loop().time() > t_end:
                raise


def test_callbacks_run_on_the_event_loop_thread_and_queryable_survives_a_failing_handler(hub):
    async def main():
        loop_thread = threading.get_ident()
        seen_threads: list[int] = []
        got: asyncio.Queue = asyncio.Queue()
        calls = 0

        async def handler(query: zenoh.Query) -> None:
            nonlocal calls
            calls += 1
            seen_threads.append(threading.get_ident())
            if calls == 1:
                raise RuntimeError("first request breaks the handler")
            query.reply(query.key_expr, b"pong")

        daemon = open_session(build_zenoh_config(hub.section, role="serve"))
        a = b = None
        try:
            declare_async_queryable(daemon, f"{hub.prefix}/ping", handler)
            subscribe(
                daemon,
                f"{hub.prefix}/data",
                lambda s: (seen_threads.append(threading.get_ident()), got.put_nowait(s)),
            )
            a = open_session(build_zenoh_config(hub.section, role="connect"))
            b = open_session(build_zenoh_config(hub.section, role="connect"))
            first = await async_get(a, f"{hub.prefix}/ping", timeout_s=5)
            second = await async_get(a, f"{hub.prefix}/ping", timeout_s=5)
            nothing = await async_get(a, f"{hub.prefix}/nobody", timeout_s=5)
            sample = await _put_until_received(a, f"{hub.prefix}/data", b"x", got)
            # one client to another through the daemon (a CLI watching what a worker publishes)
            relayed: asyncio.Queue = asyncio.Queue()
            subscribe(b, f"{hub.prefix}/reports/*", relayed.put_nowait)
            via_daemon = await _put_until_received(a, f"{hub.prefix}/reports/j1", b"report", relayed)
            return loop_thread, seen_threads, first, second, nothing, sample, via_daemon
        finally:
            close_session(a)
            close_session(b)
            close_session(daemon)

    loop_thread, seen_threads, first, second, nothing, sample, via_daemon = asyncio.run(main())
    assert set(seen_threads) == {loop_thread}
    assert first[0].err is not None and b"first request breaks the handler" in first[0].err.payload.to_bytes()
    assert second[0].ok.payload.to_bytes() == b"pong"
    assert nothing == []
    assert sample.payload.to_bytes() == b"x"
    assert via_daemon.payload.to_bytes() == b"report"


def test_usrpwd_auth_admits_the_right_password_and_refuses_a_wrong_one(tmp_path, monkeypatch):
    port = free_port()
    users = tmp_path / "users.txt"
    users.write_text("cellctl:right-pw\n")
    users.chmod(0o600)
    monkeypatch.setenv("PW_RIGHT", "right-pw")
    monkeypatch.setenv("PW_WRONG", "wrong-pw")

    def section(env: str) -> ZenohSection:
        return ZenohSection(
            listen=[f"tcp/127.0.0.1:{port}"],
            access=ZenohAccess(enabled=True, password_env=env, dictionary_file=users),
        )

    daemon = open_session(build_zenoh_config(section("PW_RIGHT"), role="serve", key_prefix="cell/a"))
    good = None
    try:
        good = open_session(build_zenoh_config(section("PW_RIGHT"), role="connect"))
        assert good.info.routers_zid() or good.info.peers_zid()
        with pytest.raises(ZenohSetupError, match="cannot open Zenoh"):
            close_session(open_session(build_zenoh_config(section("PW_WRONG"), role="connect")))
    finally:
        close_session(good)
        close_session(daemon)
