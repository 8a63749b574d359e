"""Zenoh access control from [zenoh.access] roles, on loopback: who may trigger, control, publish, read.

The serving session is built exactly as the daemon builds it (``build_zenoh_config(role="serve")``)
and declares the daemon's trigger queryable through the real handler (``cellctl.api.handle_trigger``)
with a real job store behind it, so "no job" means no job directory was created.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
import structlog
import zenoh
from sec_util import PASSWORDS, env_name, section, write_dictionary

from cellctl.api import Keys, TriggerAccepted, handle_trigger, new_job_id
from cellctl.api.session import (
    ZenohSetupError,
    access_control_dict,
    async_get,
    build_zenoh_config,
    close_session,
    config_dict,
    declare_async_queryable,
    open_session,
    subscribe,
)
from cellctl.config import ZenohAccess, ZenohSection
from cellctl.jobstore.jobs import JobRecord, JobStore
from tests.support.ports import free_port

PREFIX = "cell/sec1"
KEYS = Keys(PREFIX)
TRIGGER = {"plate_id": "P-1", "design": "plate.stl", "placement": {"pos_mm": [1500.0, 0.0, 300.0]}}


@pytest.fixture(autouse=True)
def _passwords(monkeypatch):
    for user, pw in PASSWORDS.items():
        monkeypatch.setenv(env_name(user), pw)
    structlog.reset_defaults()


class FakeDaemonSide:
    """The daemon's Zenoh surface: trigger (real handler + job store), abort, state, report subscriber."""

    def __init__(self, tmp: Path, port: int) -> None:
        self.designs = tmp / "designs"
        self.designs.mkdir()
        (self.designs / "plate.stl").write_bytes(b"solid x\nendsolid x\n")
        self.store = JobStore(tmp / "data")
        self.dictionary = write_dictionary(tmp / "users.txt")
        self.port = port
        self.aborts = 0
        self.reports: list[bytes] = []
        self.session: zenoh.Session | None = None
        self.publisher = None

    async def start(self) -> None:
        cfg = build_zenoh_config(
            section(self.port, "daemon", self.dictionary), role="serve", key_prefix=PREFIX
        )
        self.session = open_session(cfg, what="test daemon")

        async def accept(req, design_path):
            rec = self.store.create(
                JobRecord(
                    new_job_id(), req.plate_id, req.design, str(design_path), req.placement.model_dump()
                )
            )
            return TriggerAccepted(job_id=rec.job_id, state="queued")

        async def on_trigger(query):
            await handle_trigger(query, self.designs, accept)

        async def on_abort(query):
            self.aborts += 1
            query.reply(query.key_expr, b'{"action": "abort", "job_id": null, "state": "idle"}')

        declare_async_queryable(self.session, KEYS.trigger, on_trigger)
        declare_async_queryable(self.session, KEYS.control("abort"), on_abort)
        subscribe(self.session, KEYS.report("*"), lambda s: self.reports.append(s.payload.to_bytes()))
        self.publisher = self.session.declare_publisher(KEYS.state)

    def close(self) -> None:
        close_session(self.session)


def _client(port: int, user: str) -> zenoh.Session:
    return open_session(build_zenoh_config(section(port, user), role="connect"), what=f"client {user}")


async def _until(pred, timeout_s: float = 10.0, step_s: float = 0.05) -> bool:
    loop = asyncio.get_running_loop()
    t_end = loop.time() + timeout_s
    while not pred():
        if loop.time() > t_end:
            return False
        await asyncio.sleep(step_s)
    return True


def test_only_the_operator_can_trigger_or_abort_and_nobody_else_creates_a_job(tmp_path):
    async def main():
        daemon = FakeDaemonSide(tmp_path, free_port())
        await daemon.start()
        sessions = {}
        try:
            for user in ("alice", "w1", "bob", "eve"):
                sessions[user] = _client(daemon.port, user)
            outcome = {}
            for user, s in sessions.items():
                before = len(daemon.store.list())
                replies = await async_get(s, KEYS.trigger, payload=json.dumps(TRIGGER), timeout_s=3)
                aborts = daemon.aborts
                abort_replies = await async_get(s, KEYS.control("abort"), timeout_s=3)
                outcome[user] = (
                    [r.ok is not None for r in replies],
                    len(daemon.store.list()) - before,
                    [r.ok is not None for r in abort_replies],
                    daemon.aborts - aborts,
                )
            return outcome
        finally:
            for s in sessions.values():
                close_session(s)
            daemon.close()

    outcome = asyncio.run(main())
    assert outcome["alice"] == ([True], 1, [True], 1)
    for refused in ("w1", "bob", "eve"):
        assert outcome[refused] == ([], 0, [], 0), refused


def test_an_operator_trigger_outside_the_designs_dir_is_refused_with_a_reason_and_no_job(tmp_path):
    async def main():
        daemon = FakeDaemonSide(tmp_path, free_port())
        await daemon.start()
        alice = None
        try:
            alice = _client(daemon.port, "alice")
            bad = dict(TRIGGER, design="../users.stl")
            replies = await async_get(alice, KEYS.trigger, payload=json.dumps(bad), timeout_s=5)
            return replies, daemon.store.list()
        finally:
            close_session(alice)
            daemon.close()

    replies, jobs = asyncio.run(main())
    assert len(replies) == 1 and replies[0].ok is None
    err = json.loads(replies[0].err.payload.to_bytes())
    assert err["code"] == "invalid" and err["field"] == "design"
    assert jobs == []


def test_viewer_reads_state_but_its_forged_report_never_reaches_the_daemon_while_a_worker_report_does(
    tmp_path,
):
    async def main():
        daemon = FakeDaemonSide(tmp_path, free_port())
        await daemon.start()
        bob = w1 = None
        try:
            bob, w1 = _client(daemon.port, "bob"), _client(daemon.port, "w1")
            seen: list[bytes] = []
            subscribe(bob, KEYS.state, lambda s: seen.append(s.payload.to_bytes()))
            worker_saw_state: list[bytes] = []
            subscribe(w1, KEYS.state, lambda s: worker_saw_state.append(s.payload.to_bytes()))

            def publish_state() -> bool:
                daemon.publisher.put(b'{"state": "idle"}')
                return bool(seen)

            got_state = await _until(publish_state, 10, 0.2)

            async def probe(query):
                query.reply(query.key_expr, b"{}")

            # A query the viewer may make, sent after its forged put on the same link: its reply
            # comes once the daemon side handled everything bob sent before it, the put included.
            declare_async_queryable(daemon.session, f"{PREFIX}/workers/probe/info", probe)
            bob.put(KEYS.report("job-forged"), b'{"forged": true}')
            probed = await async_get(bob, f"{PREFIX}/workers/probe/info", timeout_s=10.0)
            forged_seen = list(daemon.reports)
            delivered = await _until(
                lambda: (w1.put(KEYS.report("job-real"), b'{"real": true}'), bool(daemon.reports))[1], 10, 0.2
            )
            return got_state, delivered, list(daemon.reports), worker_saw_state, probed, forged_seen
        finally:
            close_session(bob)
            close_session(w1)
            daemon.close()

    got_state, delivered, reports, worker_saw_state, probed, forged_seen = asyncio.run(main())
    assert got_state, "the viewer never received the state publication"
    assert probed and probed[0].ok is not None, "the viewer's probe query after its put got no reply"
    assert forged_seen == [], forged_seen
    assert delivered and all(r == b'{"real": true}' for r in reports)
    assert worker_saw_state == []  # workers have no read role


def test_wrong_or_missing_credentials_cannot_connect(tmp_path, monkeypatch):
    port = free_port()
    dictionary = write_dictionary(tmp_path / "users.txt")
    daemon = open_session(
        build_zenoh_config(section(port, "daemon", dictionary), role="serve", key_prefix=PREFIX)
    )
    try:
        monkeypatch.setenv(env_name("alice"), "not-alices-password")
        with pytest.raises(ZenohSetupError, match="cannot open Zenoh"):
            close_session(_client(port, "alice"))
        anonymous = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        with pytest.raises(ZenohSetupError, match="cannot open Zenoh"):
            close_session(open_session(build_zenoh_config(anonymous, role="connect")))
    finally:
        close_session(daemon)


def test_access_control_names_only_the_configured_users_and_denies_by_default(tmp_path):
    acl = config_dict(section(7447, "daemon", write_dictionary(tmp_path / "u.txt")), key_prefix=PREFIX)[
        "access_control"
    ]
    assert acl["default_permission"] == "deny"
    subjects = {s["id"]: s["usernames"] for s in acl["subjects"]}
    assert subjects == {
        "role_operator": ["alice"], "role_viewer": ["bob"], "role_worker": ["w1"], "worker_w1": ["w1"]
    }  # fmt: skip
    rules = {r["id"]: r for r in acl["rules"]}
    policy = {p["subjects"][0]: set(p["rules"]) for p in acl["policies"]}
    assert "operate_query" in policy["role_operator"]
    assert "operate_query" not in policy["role_worker"] | policy["role_viewer"]
    assert rules["operate_query"]["key_exprs"] == [f"{PREFIX}/scan/trigger", f"{PREFIX}/control/*"]
    assert all(k.startswith(PREFIX) for r in acl["rules"] for k in r["key_exprs"])


def test_a_role_naming_a_user_missing_from_the_dictionary_is_a_setup_error():
    with pytest.raises(ZenohSetupError, match="missing from the dictionary file: mallory"):
        access_control_dict({"operator": ["alice", "mallory"]}, ["alice"], PREFIX)


def test_a_dictionary_readable_by_others_is_refused_naming_its_mode(tmp_path):
    dictionary = write_dictionary(tmp_path / "users.txt")
    dictionary.chmod(0o644)
    with pytest.raises(ZenohSetupError, match=r"mode 644.*chmod 600"):
        config_dict(section(7447, "daemon", dictionary), key_prefix=PREFIX)


def test_roles_refuse_unknown_role_names_and_odd_user_names():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="roles"):
        ZenohAccess(roles={"admin": ["alice"]})
    with pytest.raises(ValidationError, match="not a user name"):
        ZenohAccess(roles={"operator": ["alice:pw"]})


@pytest.mark.e2e
def test_a_worker_user_takes_jobs_through_the_acl_and_a_viewer_lists_it(tmp_path):
    """The worker role is complete: liveliness, job delivery, events and report pass; a viewer sees the worker."""
    import os
    import signal
    import subprocess
    import sys

    import numpy as np

    from analysis.contracts.job import AnalysisJob
    from cellctl.api import list_workers
    from cellctl.api.cloud_codec import Cloud, encode_cloud
    from cellctl.daemon.dispatch import Dispatcher, DispatchSettings

    port = free_port()
    dictionary = write_dictionary(tmp_path / "users.txt")
    toml = tmp_path / "worker.toml"
    toml.write_text(
        f'[cell]\nid = "sec1"\n\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n\n'
        f'[zenoh.access]\nenabled = true\nuser = "w1"\npassword_env = "{env_name("w1")}"\n'
    )
    here = Path(__file__).resolve().parent
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(here.parent.parent), str(here)]))
    log_path = tmp_path / "worker.log"
    xyz = np.random.default_rng(3).normal(0, 50, (500, 3)).astype(np.float32)
    payload = encode_cloud(Cloud(xyz_mm=xyz, job_id="jobS", plate_id="P1"))

    async def main():
        cfg = build_zenoh_config(section(port, "daemon", dictionary), role="serve", key_prefix=PREFIX)
        session = open_session(cfg, what="test daemon")
        settings = DispatchSettings(
            ack_timeout_s=10.0, heartbeat_timeout_s=10.0, job_timeout_s=60.0, max_attempts=2
        )
        disp = Dispatcher(session, KEYS, settings)
        bob = None
        try:
            await disp.start()
            assert await _until(lambda: disp.workers == ["w1"], 60), log_path.read_text()
            envelope = await asyncio.wait_for(
                disp.submit(AnalysisJob(job_id="jobS", plate_id="P1", design="p.stl"), payload), 60
            )
            # a streamed job (issue 22): the chunks' keys and the whole cloud's query are the role's too
            fut = disp.submit_stream(AnalysisJob(job_id="jobT", plate_id="P1", design="p.stl"))
            disp.stream_chunk("jobT", 0, payload, 500)
            disp.stream_chunk("jobT", 1, payload, 500)
            disp.end_stream("jobT")
            streamed = await asyncio.wait_for(fut, 60)
            bob = _client(port, "bob")
            announced = await list_workers(bob, KEYS, timeout_s=5)
            return envelope, streamed, announced
        finally:
            close_session(bob)
            await disp.close()
            close_session(session)

    # the worker retries its connection until the daemon listens, so it may start first
    with log_path.open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cellctl", "--log-format", "json", "worker", "--config", str(toml),
             "--worker-id", "w1", "--analysis", "sec_fns:point_count"],
            stdout=out, stderr=subprocess.STDOUT, env=env, cwd=tmp_path,
        )  # fmt: skip
    try:
        envelope, streamed, announced = asyncio.run(main())
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    assert envelope.ok and envelope.worker_id == "w1" and envelope.report.inputs.points == 500
    assert streamed.ok and streamed.report.inputs.points == 1000, streamed.error
    assert streamed.timings_s["stream_chunks"] == 2 and streamed.timings_s["stream_fallback"] == 0
    assert [a.worker_id for a in announced] == ["w1"]


def test_without_roles_every_dictionary_user_gets_the_whole_cell_both_ways_and_rule_ids_are_unique():
    acl = access_control_dict({}, ["cellctl", "mes"], PREFIX)
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids))  # zenoh keeps one rule per id: a duplicate silently drops a flow
    flows = {f for r in acl["rules"] for f in r["flows"]}
    assert flows == {"ingress", "egress"}
    assert acl["subjects"] == [{"id": "role_daemon", "usernames": ["cellctl", "mes"]}]
    every_role = access_control_dict(
        {"operator": ["a"], "worker": ["w"], "viewer": ["v"], "daemon": ["d"]}, ["a", "w", "v", "d"], PREFIX
    )
    ids = [r["id"] for r in every_role["rules"]]
    assert len(ids) == len(set(ids))


def test_a_viewer_receives_the_live_cloud_and_a_worker_does_not(tmp_path):
    """The HMI follows a scan's thinned cloud (``jobs/<id>/live``) with no more than the viewer role."""

    async def main():
        daemon = FakeDaemonSide(tmp_path, free_port())
        await daemon.start()
        bob = w1 = None
        try:
            bob, w1 = _client(daemon.port, "bob"), _client(daemon.port, "w1")
            viewer_saw: list[bytes] = []
            worker_saw: list[bytes] = []
            subscribe(bob, KEYS.live_cloud("*"), lambda s: viewer_saw.append(s.payload.to_bytes()))
            subscribe(w1, KEYS.live_cloud("*"), lambda s: worker_saw.append(s.payload.to_bytes()))
            chunk = b'{"job_id": "j1", "seq": 0, "xyz_mm": [[1.0, 2.0, 3.0]]}'
            got = await _until(
                lambda: (daemon.session.put(KEYS.live_cloud("j1"), chunk), bool(viewer_saw))[1], 10, 0.2
            )
            return got, viewer_saw, worker_saw
        finally:
            close_session(bob)
            close_session(w1)
            daemon.close()

    got, viewer_saw, worker_saw = asyncio.run(main())
    assert got and viewer_saw[0].startswith(b'{"job_id": "j1"')
    assert worker_saw == []
