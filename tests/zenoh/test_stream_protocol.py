"""A streamed job's cloud (issue 22) through Zenoh on loopback to real `cellctl worker` processes.

The dispatcher's side (:meth:`Dispatcher.submit_stream`) and, for the faults a dispatcher never
makes (a chunk twice, out of order, lost, corrupt), a test daemon that puts the chunks itself.
"""

from __future__ import annotations

import asyncio
import hashlib
import secrets

import numpy as np
import pytest

from cellctl.acquisition.spill import ByteSpill
from cellctl.api import JobEvent, JobSpec, Keys, ReportEnvelope, StreamChunk, StreamEnd, list_workers
from cellctl.api.cloud_codec import ENCODING, Cloud, concat_encoded, decode_cloud, encode_cloud
from cellctl.api.session import (
    build_zenoh_config,
    close_session,
    declare_async_queryable,
    open_session,
    subscribe,
)
from cellctl.daemon.dispatch import Dispatcher, DispatchSettings, JobFailed
from tests.support.waits import wait_subscribed, wait_until
from tests.zenoh.test_dispatch_workers import _job, _observed, _run, _wait_for

pytestmark = pytest.mark.e2e


def _chunks(job_id: str, n_chunks: int = 4, n: int = 500) -> tuple[list[bytearray], np.ndarray]:
    """``n_chunks`` encoded clouds of ``n`` points, pass k in chunk k; the centroid of them all."""
    rng = np.random.default_rng(len(job_id))
    out, xyz_all = [], []
    for k in range(n_chunks):
        xyz = (rng.normal(0, 50, (n, 3)) + 100.0 * k).astype(np.float32)
        out.append(encode_cloud(Cloud(
            xyz_mm=xyz, job_id=job_id, plate_id="P1", pass_id=np.full(n, k, np.uint16),
            profile_index=(k * 50 + np.arange(n) // 10).astype(np.uint32),
            point_index=(np.arange(n) % 10).astype(np.uint16),
        )))  # fmt: skip
        xyz_all.append(xyz.astype(np.float64))
    return out, np.concatenate(xyz_all).mean(axis=0)


def test_a_streamed_job_is_analysed_from_chunks_sent_before_and_after_the_worker_accepted(
    hub, start_worker, tmp_path
):
    start_worker("w1")
    spill = ByteSpill(tmp_path)  # two chunks memory-mapped from a file, as the daemon keeps them (issue 42)

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        chunks, centroid = _chunks("jobS")
        fut = disp.submit_stream(_job(hub, "jobS"))
        disp.stream_chunk("jobS", 0, chunks[0], 500)  # before the worker has even been offered it
        await _wait_for(lambda: disp._jobs["jobS"].accepted, 30, "accepted")
        for k in (1, 2):
            disp.stream_chunk("jobS", k, spill.keep(chunks[k]), 500)
        await asyncio.sleep(0.3)  # stays: pacing, the later chunks come apart from these as a scan's do
        with pytest.raises(ValueError, match="not a pending streamed job"):
            disp.stream_chunk("nojob", 0, chunks[0], 500)
        disp.stream_chunk("jobS", -1, chunks[3], 500)
        disp.end_stream("jobS")
        with pytest.raises(ValueError, match="has ended"):
            disp.stream_chunk("jobS", 0, chunks[0], 500)
        return await asyncio.wait_for(fut, 60), centroid

    env, centroid = _run(hub, scenario)
    assert env.ok and env.attempt == 1 and env.worker_id == "w1", env.error
    seen = _observed(hub, "jobS")
    assert seen["n_points"] == 2000 and seen["passes"] == [0, 1, 2, 3]
    np.testing.assert_allclose(seen["centroid_mm"], centroid, atol=1e-3)
    assert env.timings_s["stream_chunks"] == 4 and env.timings_s["stream_fallback"] == 0


@pytest.mark.parametrize("tail_points", [0, 500])
def test_the_last_pass_starts_the_analysis_before_the_end_and_a_tail_with_points_makes_it_again(
    hub, start_worker, tail_points
):
    """The chunk the daemon marks ``last_pass`` reaches the worker marked (through Zenoh) and the
    analysis runs at once; the report made then is the job's when the retract's rows add no point,
    and is made again from every chunk when they do."""
    start_worker("w1", analysis="tests.support.zworker_fns:centroid_streamed")
    job_id = f"jobR{tail_points}"

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        chunks, _ = _chunks(job_id)
        tail = _chunks(job_id, n_chunks=1, n=tail_points)[0][0]
        fut = disp.submit_stream(_job(hub, job_id, ahead_sleep_s=1.0))
        await _wait_for(lambda: disp._jobs[job_id].accepted, 30, "accepted")
        for k in range(4):
            disp.stream_chunk(job_id, k, chunks[k], 500, last_pass=k == 3)
        # the retract's rows come while the analysis made ahead still runs (ahead_sleep_s 1 s)
        started = hub.tmp / job_id / "out" / "ahead_started"
        await wait_until(started.exists, 0.3, "the worker making the result ahead")
        disp.stream_chunk(job_id, -1, tail, tail_points)
        disp.end_stream(job_id)
        return await asyncio.wait_for(fut, 60)

    env = _run(hub, scenario)
    assert env.ok, env.error
    seen = _observed(hub, job_id)
    assert seen["ahead_points"] == 2000  # every pass in, before the tail
    assert seen["n_points"] == 2000 + tail_points
    assert seen["made"] == ("ahead" if tail_points == 0 else "finish")
    assert env.timings_s["stream_chunks"] == 5 and env.timings_s["stream_fallback"] == 0


def test_a_stream_abandoned_mid_scan_frees_the_worker_for_the_next_job(hub, start_worker):
    start_worker("w1")

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        chunks, _ = _chunks("jobA")
        fut = disp.submit_stream(_job(hub, "jobA"))
        disp.stream_chunk("jobA", 0, chunks[0], 500)
        await _wait_for(lambda: disp._jobs["jobA"].accepted, 30, "accepted")
        disp.abandon("jobA", "the scan was aborted")
        with pytest.raises(JobFailed, match="aborted"):
            await fut
        announced = await list_workers(disp.session, Keys(hub.prefix))
        t_end = asyncio.get_running_loop().time() + 20
        while announced[0].busy_job is not None and asyncio.get_running_loop().time() < t_end:
            await asyncio.sleep(0.2)
            announced = await list_workers(disp.session, Keys(hub.prefix))
        nxt = disp.submit(_job(hub, "jobB"), chunks[1])
        return announced, await asyncio.wait_for(nxt, 60)

    announced, env = _run(hub, scenario)
    assert announced[0].busy_job is None
    assert env.ok and env.worker_id == "w1" and _observed(hub, "jobB")["n_points"] == 500


async def _fake_daemon(hub, job_id: str, deliver, whole: bytes | None):
    """A test daemon: offers a streamed job to worker w1, calls ``deliver(put_chunk, put_end)`` once
    the worker accepted, serves ``whole`` on ``Keys.job_cloud``; returns the ReportEnvelope."""
    keys = Keys(hub.prefix)
    session = open_session(
        build_zenoh_config(hub.section, role="serve", key_prefix=hub.prefix), what="test daemon"
    )
    events: list[JobEvent] = []
    reports: list[ReportEnvelope] = []
    served: list[str] = []
    ents = []
    try:
        ents.append(
            subscribe(
                session,
                keys.job_event("*"),
                lambda s: events.append(JobEvent.model_validate_json(s.payload.to_bytes())),
            )
        )
        ents.append(
            subscribe(
                session,
                keys.report("*"),
                lambda s: reports.append(ReportEnvelope.model_validate_json(s.payload.to_bytes())),
            )
        )

        async def on_cloud(q):
            served.append(str(q.key_expr))
            if whole is None:
                q.reply_err(b"no cloud here")
            else:
                q.reply(q.key_expr, whole)

        ents.append(declare_async_queryable(session, keys.job_cloud("*"), on_cloud))
        alive: list[str] = []
        ents.append(
            subscribe(
                session, keys.worker_alive("*"), lambda s: alive.append(str(s.key_expr)), liveliness=True
            )
        )
        await _wait_for(lambda: alive, 30, "worker token")
        await wait_subscribed(session, keys.worker_job("w1", job_id), 0.5, "the worker's job subscriber")
        spec = JobSpec(attempt=1, job=_job(hub, job_id), stream=True)
        session.put(keys.worker_job("w1", job_id), b"", encoding=ENCODING, attachment=spec.to_json())
        await _wait_for(lambda: any(e.event == "accepted" for e in events), 30, "accepted")

        def put_chunk(seq: int, data: bytes, points: int, sha: str | None = None) -> None:
            head = StreamChunk(job_id=job_id, attempt=1, seq=seq, pass_index=seq, points=points,
                               sha256=sha or hashlib.sha256(data).hexdigest())  # fmt: skip
            session.put(keys.worker_stream("w1", job_id, 1, seq), bytes(data), attachment=head.to_json())

        def put_end(chunks: int, points: int) -> None:
            end = StreamEnd(job_id=job_id, attempt=1, chunks=chunks, points=points)
            session.put(keys.worker_stream_end("w1", job_id, 1), end.to_json())

        await deliver(put_chunk, put_end)
        await _wait_for(lambda: reports or any(e.event == "failed" for e in events), 60, "report or failure")
        return (reports[0] if reports else None), served, events
    finally:
        for e in ents:
            e.undeclare()
        close_session(session)


def test_duplicate_and_out_of_order_chunks_are_put_in_order_and_counted_once(hub, start_worker):
    start_worker("w1")
    chunks, centroid = _chunks("jobO")

    async def deliver(put_chunk, put_end):
        for seq in (2, 0, 0, 3, 1, 2):
            put_chunk(seq, chunks[seq], 500)
            await asyncio.sleep(0.05)  # stays: pacing, each chunk a put of its own as a scan's passes
        put_end(4, 2000)

    env, served, _ = asyncio.run(_fake_daemon(hub, "jobO", deliver, None))
    assert env.ok, env.error
    assert served == []  # nothing missing: the whole cloud was never asked for
    assert env.timings_s["stream_chunks"] == 4 and env.timings_s["stream_duplicates"] == 2
    assert env.timings_s["stream_fallback"] == 0
    seen = _observed(hub, "jobO")
    assert seen["n_points"] == 2000 and seen["passes"] == [0, 1, 2, 3]
    np.testing.assert_allclose(seen["centroid_mm"], centroid, atol=1e-3)


def test_a_lost_and_a_corrupt_chunk_make_the_worker_fetch_the_whole_cloud(hub, start_worker):
    start_worker("w1")
    chunks, centroid = _chunks("jobL")
    whole = bytes(concat_encoded(chunks))

    async def deliver(put_chunk, put_end):
        put_chunk(0, chunks[0], 500)
        put_chunk(2, chunks[2], 500, sha="0" * 64)  # corrupt: its checksum does not match
        put_chunk(3, chunks[3], 500)  # chunk 1 is lost
        put_end(4, 2000)

    env, served, _ = asyncio.run(_fake_daemon(hub, "jobL", deliver, whole))
    assert env.ok, env.error
    assert served == [Keys(hub.prefix).job_cloud("jobL")]
    assert env.timings_s["stream_fallback"] == 1
    seen = _observed(hub, "jobL")
    assert seen["n_points"] == 2000 == decode_cloud(whole).n_points
    np.testing.assert_allclose(seen["centroid_mm"], centroid, atol=1e-3)


def test_a_stream_missing_a_chunk_with_no_whole_cloud_fails_the_attempt_not_the_worker(hub, start_worker):
    w = start_worker("w1")
    chunks, _ = _chunks("jobM")

    async def deliver(put_chunk, put_end):
        put_chunk(0, chunks[0], 500)
        put_end(2, 1000)

    env, served, events = asyncio.run(_fake_daemon(hub, "jobM", deliver, None))
    assert env is None and served == [Keys(hub.prefix).job_cloud("jobM")]
    failed = [e for e in events if e.event == "failed"]
    assert len(failed) == 1 and "whole cloud unavailable" in failed[0].message, events
    assert w.proc.poll() is None  # a failed attempt (the dispatcher retries it), the worker serves on


def test_a_daemon_gone_mid_stream_frees_the_worker_for_its_restart_to_reanalyse_the_same_job(
    hub, start_worker
):
    """kill -9 of the daemon mid-scan (tests/faults/test_daemon_crash.py at full scale): its stream
    never ends. The worker sees the daemon's liveliness token end and gives the attempt up, so the
    restarted daemon's re-analysis of the same job (attempt 1 again, the whole cloud) is taken at once,
    not after the offer's acknowledgement timeout and a second attempt."""
    start_worker("w1")
    keys = Keys(hub.prefix)
    chunks, centroid = _chunks("jobK")

    async def first_daemon() -> None:
        session = open_session(
            build_zenoh_config(hub.section, role="serve", key_prefix=hub.prefix), what="test daemon"
        )
        events: list[JobEvent] = []
        try:
            token = session.liveliness().declare_token(keys.daemon_alive)
            alive: list[str] = []
            subs = [
                subscribe(
                    session, keys.worker_alive("*"), lambda s: alive.append(str(s.key_expr)), liveliness=True
                ),
                subscribe(
                    session,
                    keys.job_event("*"),
                    lambda s: events.append(JobEvent.model_validate_json(s.payload.to_bytes())),
                ),
            ]
            await _wait_for(lambda: alive, 30, "worker token")
            await wait_subscribed(session, keys.worker_job("w1", "jobK"), 0.5, "the worker's job subscriber")
            # the killed daemon's offer, named as every daemon names its offers
            spec = JobSpec(attempt=1, job=_job(hub, "jobK"), stream=True, offer_id=secrets.token_hex(8))
            session.put(keys.worker_job("w1", "jobK"), b"", encoding=ENCODING, attachment=spec.to_json())
            await _wait_for(lambda: any(e.event == "accepted" for e in events), 30, "accepted")
            head = StreamChunk(job_id="jobK", attempt=1, seq=0, pass_index=0, points=500,
                               sha256=hashlib.sha256(chunks[0]).hexdigest())  # fmt: skip
            session.put(keys.worker_stream("w1", "jobK", 1, 0), bytes(chunks[0]), attachment=head.to_json())
            await asyncio.sleep(0.5)  # stays: the chunk reaches the worker (nothing acknowledges a chunk)
            del token, subs  # the session ends below with no cancel and no end: as a kill -9 leaves it
        finally:
            close_session(session)

    asyncio.run(first_daemon())

    async def restarted(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        return await asyncio.wait_for(disp.submit(_job(hub, "jobK"), concat_encoded(chunks)), 60)

    settings = DispatchSettings(
        ack_timeout_s=20.0, heartbeat_timeout_s=60.0, job_timeout_s=120.0, max_attempts=3
    )
    env = _run(hub, restarted, settings)
    assert env.ok and env.attempt == 1, (env.attempt, env.error)  # taken at once, not after a second offer
    seen = _observed(hub, "jobK")
    assert seen["n_points"] == 2000
    np.testing.assert_allclose(seen["centroid_mm"], centroid, atol=1e-3)
