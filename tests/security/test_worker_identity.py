"""Access control on: a worker's reports, events and result chunks count only from the identity
it announced with (issue 43, item 2; docs/safety.md 1.7 and the threat table).

Two worker-role identities: ``w1`` runs the real worker, ``eve`` (worker and viewer roles) reads
the job's events and copies their ids. The ACL binds the worker id ``w1`` to the identity ``w1``
(only it receives ``workers/w1/**``, so only it holds the offer's key); eve's report (plate
FORGED, no results, verdict pass), her "failed" event and her result chunk are refused and
logged, and w1's report is the job's."""

from __future__ import annotations

import asyncio
import hashlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import structlog
from sec_util import PASSWORDS, env_name, section, write_dictionary

from analysis.contracts.job import AnalysisJob
from cellctl.api import JobEvent, Keys, ReportEnvelope
from cellctl.api.cloud_codec import Cloud, encode_cloud
from cellctl.api.session import build_zenoh_config, close_session, open_session, subscribe
from cellctl.api.transfer import ResultChunk, TransferSpec
from cellctl.daemon.dispatch import Dispatcher, DispatchSettings
from tests.support.ports import free_port
from tests.support.zworker_fns import minimal_report

PREFIX = "cell/sec2"
KEYS = Keys(PREFIX)
ROLES = {"operator": ["alice"], "worker": ["w1", "eve"], "viewer": ["bob", "eve"]}


@pytest.fixture(autouse=True)
def _passwords(monkeypatch):
    for user, pw in PASSWORDS.items():
        monkeypatch.setenv(env_name(user), pw)
    structlog.reset_defaults()


async def _until(pred, timeout_s: float = 10.0) -> bool:
    t_end = asyncio.get_running_loop().time() + timeout_s
    while not pred():
        if asyncio.get_running_loop().time() > t_end:
            return False
        await asyncio.sleep(0.05)
    return True


@pytest.mark.e2e
def test_another_worker_identity_copying_the_ids_is_refused_and_logged_and_cannot_read_the_offer(tmp_path):
    port = free_port()
    dictionary = write_dictionary(tmp_path / "users.txt")
    toml = tmp_path / "worker.toml"
    toml.write_text(
        f'[cell]\nid = "sec2"\n\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n\n'
        f'[zenoh.access]\nenabled = true\nuser = "w1"\npassword_env = "{env_name("w1")}"\n'
    )
    gate = tmp_path / "gate"
    design = tmp_path / "todo.json"
    design.write_text(f'{{"gate_path": "{gate}"}}')
    repo = Path(__file__).resolve().parent.parent.parent
    env = dict(os.environ, PYTHONPATH=str(repo))
    log_path = tmp_path / "worker.log"
    payload = encode_cloud(
        Cloud(xyz_mm=__import__("numpy").ones((50, 3), "float32"), job_id="jobI", plate_id="P1")
    )

    async def main():
        cfg = build_zenoh_config(section(port, "daemon", dictionary, ROLES), role="serve", key_prefix=PREFIX)
        session = open_session(cfg, what="test daemon")
        disp = Dispatcher(session, KEYS, DispatchSettings(ack_timeout_s=30, heartbeat_timeout_s=30))
        eve = None
        try:
            await disp.start()
            assert await _until(lambda: disp.workers == ["w1"], 60), log_path.read_text()
            eve = open_session(
                build_zenoh_config(section(port, "eve", None, ROLES), role="connect"), what="eve"
            )
            stolen: list[str] = []
            events: list[JobEvent] = []
            subscribe(eve, KEYS.worker_job("w1"), lambda s: stolen.append(str(s.key_expr)))
            subscribe(eve, KEYS.worker_job("*"), lambda s: stolen.append(str(s.key_expr)))
            subscribe(eve, KEYS.job_event("jobI"), lambda s: events.append(JobEvent.model_validate_json(s.payload.to_bytes())))  # fmt: skip
            # declared last: once eve receives the state, her earlier (denied) declarations have
            # reached the daemon too
            seen_state: list[bytes] = []
            subscribe(eve, KEYS.state, lambda s: seen_state.append(b""))
            while not seen_state:
                session.put(KEYS.state, b"{}")
                await _until(lambda: seen_state, 0.2)
            job = AnalysisJob(job_id="jobI", plate_id="P1", design=str(design))
            fut = disp.submit(job, payload, transfer=TransferSpec())
            assert await _until(lambda: events, 30), "eve, a viewer too, sees the job's events"
            ids = {k: getattr(events[0], k) for k in ("job_id", "worker_id", "attempt", "offer_id")}
            rep = minimal_report(job.model_copy(update={"plate_id": "FORGED"}), 1).model_copy(
                update={"verdict": "pass"}
            )
            eve.put(
                KEYS.report("jobI"), ReportEnvelope(plate_id="FORGED", ok=True, report=rep, **ids).to_json()
            )
            eve.put(KEYS.job_event("jobI"), JobEvent(event="failed", message="forged", **ids).to_json())
            data = b"forged bytes"
            head = ResultChunk(job_id="jobI", worker_id="w1", attempt=ids["attempt"], index=0, chunks=1,
                               sha256=hashlib.sha256(data).hexdigest(), mac="1" * 64)  # fmt: skip
            eve.put(KEYS.result_chunk("jobI", ids["attempt"], 0), data, attachment=head.to_json())
            refused = lambda: (disp.refused_reports, disp.refused_events, disp.refused_chunks) == (1, 1, 1)  # noqa: E731
            assert await _until(refused, 10), (disp.refused_reports, disp.refused_events, disp.refused_chunks)
            assert not fut.done()
            gate.write_text("go")
            return await asyncio.wait_for(fut, 60), stolen
        finally:
            close_session(eve)
            await disp.close()
            close_session(session)

    with log_path.open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cellctl", "--log-format", "json", "worker", "--config", str(toml),
             "--worker-id", "w1", "--analysis", "tests.support.zworker_fns:centroid_after_sleep"],
            stdout=out, stderr=subprocess.STDOUT, env=env, cwd=tmp_path,
        )  # fmt: skip
    try:
        with structlog.testing.capture_logs() as logs:
            env_, stolen = asyncio.run(main())
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    assert stolen == []  # the ACL never forwards w1's offers (and their keys) to eve
    assert env_.ok and env_.worker_id == "w1" and env_.plate_id == "P1" and env_.report.verdict == "fail"
    assert {e["event"] for e in logs if e.get("reason") == "not signed with the offer's key"} == {
        "report_refused", "event_refused", "chunk_refused"
    }  # fmt: skip


def test_the_acl_binds_each_worker_id_to_its_own_identity():
    from cellctl.api.session import access_control_dict

    acl = access_control_dict(ROLES, list(PASSWORDS), PREFIX)
    rules = {r["id"]: r for r in acl["rules"]}
    policy = {p["subjects"][0]: set(p["rules"]) for p in acl["policies"]}
    subjects = {s["id"]: s["usernames"] for s in acl["subjects"]}
    assert subjects["worker_w1"] == ["w1"] and subjects["worker_eve"] == ["eve"]
    assert rules["worker_w1_receive"]["key_exprs"] == [
        f"{PREFIX}/workers/w1/{k}" for k in ("jobs/*", "cancel/*", "stream/**")
    ]
    assert rules["worker_w1_alive"]["key_exprs"] == [f"{PREFIX}/alive/workers/w1"]
    assert not any("workers/w1" in k for r in policy["worker_eve"] for k in rules[r]["key_exprs"])
    # the shared worker role reaches no worker's own keys
    assert not any(k.startswith(f"{PREFIX}/workers/*/") and "info" not in k
                   for r in policy["role_worker"] for k in rules[r]["key_exprs"])  # fmt: skip
