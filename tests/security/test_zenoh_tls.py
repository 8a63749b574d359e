"""Mutual TLS from [zenoh.access] (auth = "tls"): certificates made here with `cryptography`, on loopback.

Roles name certificate common names: the operator's certificate may trigger, a worker's may not,
a certificate from another CA cannot connect at all, and a private key others may read is refused.
"""

from __future__ import annotations

import asyncio
import json

import pytest

from cellctl.api import Keys
from cellctl.api.session import (
    ZenohSetupError,
    async_get,
    build_zenoh_config,
    close_session,
    config_dict,
    declare_async_queryable,
    open_session,
)
from cellctl.config import ZenohAccess, ZenohSection
from tests.support.pki import Pki
from tests.support.ports import free_port

PREFIX = "cell/tls1"
KEYS = Keys(PREFIX)
ROLES = {"operator": ["alice"], "worker": ["w1"]}


def _section(port: int, pki: Pki, cn: str, roles: dict | None = None) -> ZenohSection:
    cert, key = pki.leaf(cn)
    access = ZenohAccess(enabled=True, auth="tls", tls_ca_file=pki.ca_file, tls_cert_file=cert, tls_key_file=key,
                         roles=roles if roles is not None else ROLES)  # fmt: skip
    return ZenohSection(listen=[f"tls/127.0.0.1:{port}"], multicast_scouting=False, access=access)


def test_operator_certificate_triggers_worker_certificate_cannot_and_a_foreign_ca_cannot_connect(tmp_path):
    pki, foreign = Pki(tmp_path / "pki"), Pki(tmp_path / "other", ca_cn="someone-else")
    port = free_port()

    async def main():
        calls = 0

        async def on_trigger(query):
            nonlocal calls
            calls += 1
            query.reply(query.key_expr, b'{"job_id": "j", "state": "queued"}')

        daemon = open_session(
            build_zenoh_config(_section(port, pki, "daemon"), role="serve", key_prefix=PREFIX)
        )
        sessions = []
        try:
            declare_async_queryable(daemon, KEYS.trigger, on_trigger)
            out = {}
            for cn in ("alice", "w1"):
                s = open_session(build_zenoh_config(_section(port, pki, cn), role="connect"))
                sessions.append(s)
                before = calls
                replies = await async_get(s, KEYS.trigger, payload=json.dumps({}), timeout_s=3)
                out[cn] = ([r.ok is not None for r in replies], calls - before)
            with pytest.raises(ZenohSetupError, match="cannot open Zenoh"):
                sessions.append(
                    open_session(build_zenoh_config(_section(port, foreign, "alice"), role="connect"))
                )
            return out
        finally:
            for s in sessions:
                close_session(s)
            close_session(daemon)

    out = asyncio.run(main())
    assert out["alice"] == ([True], 1)
    assert out["w1"] == ([], 0)


def test_tls_config_uses_tls_endpoints_mtls_and_acl_by_certificate_common_name(tmp_path):
    pki = Pki(tmp_path / "pki")
    serve = config_dict(_section(7447, pki, "daemon"), role="serve", key_prefix=PREFIX)
    tls = serve["transport"]["link"]["tls"]
    assert tls["enable_mtls"] and {"listen_certificate", "listen_private_key", "root_ca_certificate"} <= set(
        tls
    )
    assert "auth" not in serve["transport"]  # no password in TLS-only mode
    assert {s["id"]: s["cert_common_names"] for s in serve["access_control"]["subjects"]} == {
        "role_operator": ["alice"],
        "role_worker": ["w1"],
        "worker_w1": ["w1"],  # the worker id w1 bound to the certificate w1
    }
    client = config_dict(_section(7447, pki, "alice"), role="connect", key_prefix=PREFIX)
    assert {"connect_certificate", "connect_private_key"} <= set(client["transport"]["link"]["tls"])
    assert "access_control" not in client


def test_tls_refuses_plain_tcp_endpoints_a_shared_private_key_and_missing_files(tmp_path):
    pki = Pki(tmp_path / "pki")
    section = _section(7447, pki, "daemon")
    plain = section.model_copy(update={"listen": ["tcp/127.0.0.1:7447"]})
    with pytest.raises(ZenohSetupError, match="needs tls/ endpoints"):
        config_dict(plain, key_prefix=PREFIX)
    section.access.tls_key_file.chmod(0o644)
    with pytest.raises(ZenohSetupError, match=r"tls_key_file.*mode 644"):
        config_dict(section, key_prefix=PREFIX)
    with pytest.raises(ValueError, match="needs tls_ca_file, tls_cert_file, tls_key_file"):
        ZenohAccess(enabled=True, auth="tls")
