"""A report is the worker's only when it proves it and says the job's content (issue 43, item 2),
and a worker gets jobs only in a version the daemon speaks (item 4). Zenoh on loopback, access
control off: what a peer on the link can and cannot do (docs/safety.md, the threat table)."""

from __future__ import annotations

import asyncio
import json

import pytest
import structlog

from analysis.contracts.job import AnalysisJob
from analysis.contracts.placement import Placement
from cellctl.api import API_VERSION, STREAM_FORMAT, JobEvent, ReportEnvelope
from cellctl.api.session import build_zenoh_config, close_session, open_session, subscribe
from cellctl.api.transfer import TransferSpec, pack_results
from cellctl.daemon.dispatch import Dispatcher, DispatchSettings, _version_verdict
from tests.support.zworker_fns import minimal_report
from tests.zenoh.fake_worker import FakeWorker
from tests.zenoh.test_dispatch_workers import _cloud_bytes, _job, _run, _wait_for

pytestmark = pytest.mark.e2e


def _forged(env_ids: dict, job: AnalysisJob) -> bytes:
    """The issue's forgery: the ids copied from the job's event, no results, another plate, pass."""
    rep = minimal_report(job.model_copy(update={"plate_id": "FORGED"}), 1).model_copy(
        update={"verdict": "pass"}
    )
    return ReportEnvelope(plate_id="FORGED", ok=True, report=rep, results=None, **env_ids).to_json()


def test_a_peer_copying_the_ids_of_the_event_publication_is_refused_and_the_real_report_counts(
    hub, start_worker
):
    """Access control off. ``worker_id``, ``attempt`` and ``offer_id`` are public on the job's
    events; a peer that copies them and publishes ``results: null``, plate FORGED, verdict pass
    (with no MAC, and with a made-up one) while the job is analysed does not become the verdict;
    nor does its "failed" event take the job back. The worker's own report does."""
    start_worker("w1")
    gate = hub.tmp / "gate"

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "the worker")
        events: list[JobEvent] = []
        sub = subscribe(disp.session, disp.keys.job_event("jobF"),
                        lambda s: events.append(JobEvent.model_validate_json(s.payload.to_bytes())))  # fmt: skip
        peer = open_session(
            build_zenoh_config(hub.section, role="connect", key_prefix=hub.prefix), what="peer"
        )
        try:
            job = _job(hub, "jobF", "P1", gate_path=str(gate))
            fut = disp.submit(job, _cloud_bytes("jobF")[0], transfer=TransferSpec())
            await _wait_for(lambda: events, 20, "the job's first event")
            ids = {k: getattr(events[0], k) for k in ("job_id", "worker_id", "attempt", "offer_id")}
            peer.put(disp.keys.report("jobF"), _forged(ids, job))
            peer.put(disp.keys.report("jobF"), _forged(ids, job), attachment="0" * 64)
            fake_fail = JobEvent(event="failed", message="forged", **ids).to_json()
            peer.put(disp.keys.job_event("jobF"), fake_fail)
            await _wait_for(
                lambda: disp.refused_reports == 2 and disp.refused_events == 1, 10, "the forgeries refused"
            )
            assert not fut.done() and disp.assignment("jobF") == ("w1", 1)
            gate.write_text("go")
            return await asyncio.wait_for(fut, 60), disp.take_results("jobF")
        finally:
            sub.undeclare()
            close_session(peer)

    with structlog.testing.capture_logs() as logs:
        env, files = _run(hub, scenario)
    assert env.ok and env.worker_id == "w1" and env.attempt == 1 and env.plate_id == "P1"
    assert env.report.plate_id == "P1" and env.report.verdict == "fail" and "observed.json" in files
    refused = [e for e in logs if e["event"] in ("report_refused", "event_refused")]
    assert len(refused) == 3 and all(e["reason"] == "not signed with the offer's key" for e in refused)


def test_a_signed_report_not_about_the_job_or_without_its_bundle_is_refused_and_the_job_retried(
    hub, tmp_path
):
    """Access control off, a peer that holds the offer's key (the assigned worker, or anyone who
    read its job key): its report must still be the job's. No result bundle, another plate, another
    design, another placement: each refused, logged and the attempt retried; the fifth is kept."""
    out = tmp_path / "res"
    out.mkdir()
    (out / "report.json").write_text("{}")
    manifest, chunks = pack_results(out)
    placement = Placement(pos_mm=(1500.0, 0.0, 300.0))
    bad = [
        {"results": None},
        {"plate_id": "FORGED"},
        {"design": "other.stl"},
        {"placement": Placement(pos_mm=(1500.0, 10.0, 300.0))},
        {},
    ]
    attempts: list[int] = []

    async def scenario(disp: Dispatcher):
        s = open_session(build_zenoh_config(hub.section, role="connect", key_prefix=hub.prefix), what="fake")

        def answer(spec):
            attempts.append(spec.attempt)
            what = bad[spec.attempt - 1]
            fw.event(spec, "accepted")
            fw.chunks(spec, chunks)
            job = spec.job.model_copy(update={k: v for k, v in what.items() if k in ("design", "placement")})
            fields = {"report": minimal_report(job, 1), "results": manifest}
            if "plate_id" in what:
                fields["plate_id"] = what["plate_id"]
            if "results" in what:
                fields["results"] = None
            fw.report(spec, **fields)

        fw = FakeWorker(s, disp.keys, "fw", answer)
        try:
            await _wait_for(lambda: disp.workers == ["fw"], 30, "the fake worker")
            job = AnalysisJob(job_id="jobC", plate_id="P1", design="p.stl", placement=placement)
            env = await asyncio.wait_for(
                disp.submit(job, _cloud_bytes("jobC")[0], transfer=TransferSpec()), 60
            )
            return env, disp.refused_reports
        finally:
            fw.close()
            close_session(s)

    settings = DispatchSettings(ack_timeout_s=60, heartbeat_timeout_s=60, max_attempts=5, busy_backoff_s=0.05)
    with structlog.testing.capture_logs() as logs:
        env, refused = _run(hub, scenario, settings=settings)
    assert attempts == [1, 2, 3, 4, 5] and env.attempt == 5 and refused == 4
    reasons = [e["reason"] for e in logs if e["event"] == "report_refused"]
    assert reasons[0] == "no result bundle" and "FORGED" in reasons[1]
    assert "other.stl" in reasons[2] and reasons[3] == "placement is not the job's"


def test_a_worker_of_another_version_gets_no_job_and_a_rolling_upgrade_loses_none(hub):
    """Two workers, one still announcing the previous API version (and no stream format): every job
    goes to the current one, the old one is listed as refused with the reason. The old one is
    then upgraded (gone, back with the current version) while jobs keep coming: each job is
    reported once, none lost."""
    done: list[tuple[str, str]] = []

    async def scenario(disp: Dispatcher):
        s = open_session(build_zenoh_config(hub.section, role="connect", key_prefix=hub.prefix), what="fleet")

        def answering(name):
            def answer(spec):
                fw = workers[name]
                fw.event(spec, "accepted")
                fw.report(spec, report=minimal_report(spec.job, 1))
                done.append((spec.job_id, name))

            return answer

        workers = {"old": FakeWorker(s, disp.keys, "old", answering("old"), api_version=1, stream_format=None),
                   "new": FakeWorker(s, disp.keys, "new", answering("new"))}  # fmt: skip
        try:
            await _wait_for(
                lambda: disp.workers == ["new"] and disp.incompatible, 30, "both announcements read"
            )
            refused = dict(disp.incompatible)
            first = [
                disp.submit(AnalysisJob(job_id=f"a{i}", plate_id="P1", design="p.stl"), b"") for i in range(4)
            ]
            envs = await asyncio.wait_for(asyncio.gather(*first), 30)
            workers.pop("old").close()  # the upgrade: stopped, started again in the new version
            await _wait_for(lambda: not disp.incompatible, 10, "the old worker gone")
            second = [
                disp.submit(AnalysisJob(job_id=f"b{i}", plate_id="P1", design="p.stl"), b"") for i in range(6)
            ]
            workers["old"] = FakeWorker(s, disp.keys, "old", answering("old"))
            envs += await asyncio.wait_for(asyncio.gather(*second), 30)
            return refused, envs
        finally:
            for fw in workers.values():
                fw.close()
            close_session(s)

    refused, envs = _run(hub, scenario, settings=DispatchSettings(worker_settle_s=0.0))
    assert refused == {"old": f"api_version 1, this daemon speaks {API_VERSION}"}
    assert [e.worker_id for e in envs[:4]] == ["new"] * 4 and all(e.ok for e in envs)
    assert sorted(j for j, _ in done) == sorted(e.job_id for e in envs) and len(envs) == 10  # each once
    assert not [j for j, w in done if w == "old" and j.startswith("a")]


def test_an_announcement_is_read_by_its_versions_whatever_else_it_holds():
    ok = json.dumps({"api_version": API_VERSION, "stream_format": STREAM_FORMAT, "later_field": 1}).encode()
    assert _version_verdict(ok) == (True, f"api_version {API_VERSION}, stream_format {STREAM_FORMAT}")
    old = json.dumps({"api_version": API_VERSION}).encode()  # before stream_format existed
    assert _version_verdict(old) == (False, f"stream_format 0, this daemon sends {STREAM_FORMAT}")
    assert _version_verdict(b"not json") is None and _version_verdict(b"{}") is None
