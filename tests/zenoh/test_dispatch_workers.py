"""Dispatcher and workers end to end through Zenoh on loopback (workers are real `cellctl worker` processes)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.job import AnalysisJob
from cellctl.api import Keys, list_workers
from cellctl.api.cloud_codec import Cloud, encode_cloud
from cellctl.api.session import build_zenoh_config, close_session, open_session, subscribe
from cellctl.config import load_config
from cellctl.daemon.dispatch import Dispatcher, DispatchHooks, DispatchSettings, JobFailed
from tests.support.waits import wait_until_sync

pytestmark = pytest.mark.e2e
# For the cases not about the dispatcher's timeouts: bounds no loaded machine reaches (a worker
# starved of CPU for 3 s missed its heartbeats and lost a job it was still analysing: attempt 2),
# so a retry here comes from what the case does (kill, SIGTERM), never from the load.
GENEROUS = DispatchSettings(ack_timeout_s=60.0, heartbeat_timeout_s=60.0, job_timeout_s=240.0, max_attempts=3)


def _cloud_bytes(job_id: str, n: int = 2000, offset_mm: float = 0.0) -> tuple[bytearray, np.ndarray]:
    rng = np.random.default_rng(abs(hash(job_id)) % 2**32)
    xyz = (rng.normal(0, 100, (n, 3)) + offset_mm).astype(np.float32)
    cloud = Cloud(xyz_mm=xyz, job_id=job_id, plate_id="P1", pass_id=(np.arange(n) % 4).astype(np.uint16),
                  profile_index=(np.arange(n) // 40).astype(np.uint32), point_index=(np.arange(n) % 10).astype(np.uint16))  # fmt: skip
    return encode_cloud(cloud), xyz.astype(np.float64).mean(axis=0)


async def _wait_for(pred, timeout_s: float, what: str) -> None:
    t_end = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.05)


def _run(hub, scenario, settings=GENEROUS, hooks=None):
    """Open the daemon-side session, run ``scenario(dispatcher)``, close everything."""

    async def main():
        cfg = build_zenoh_config(hub.section, role="serve", key_prefix=hub.prefix)
        session = open_session(cfg, what="test daemon")
        disp = Dispatcher(session, Keys(hub.prefix), settings, hooks)
        try:
            await disp.start()
            return await scenario(disp)
        finally:
            await disp.close()
            close_session(session)

    return asyncio.run(main())


def _job(hub, job_id: str, plate_id: str = "P1", **todo) -> AnalysisJob:
    """The job parameters of a test job: ``todo`` (sleep_s, record_path) rides in the design file,
    which the test analysis reads; it writes what it saw under ``out_dir`` (:func:`_observed`)."""
    d = hub.tmp / job_id
    d.mkdir(parents=True, exist_ok=True)
    (d / "todo.json").write_text(json.dumps(todo))
    return AnalysisJob(job_id=job_id, plate_id=plate_id, design=str(d / "todo.json"), out_dir=str(d / "out"))


def _observed(hub, job_id: str) -> dict:
    return json.loads((hub.tmp / job_id / "out" / "observed.json").read_text())


def _records(path: Path) -> list[tuple[str, str, int]]:
    if not path.exists():
        return []
    return [(a, b, int(c)) for a, b, c in (ln.split() for ln in path.read_text().splitlines() if ln.strip())]


def test_two_workers_ten_jobs_each_analysed_exactly_once(hub, start_worker):
    record = hub.tmp / "calls.txt"
    w1, w2 = start_worker("w1"), start_worker("w2")

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 2, 30, "two workers")
        futures, centroids = {}, {}
        for i in range(10):
            job_id = f"job{i:02d}"
            payload, centroids[job_id] = _cloud_bytes(job_id, offset_mm=10.0 * i)
            futures[job_id] = disp.submit(_job(hub, job_id, record_path=str(record), sleep_s=0.2), payload)
        reports = dict(
            zip(futures, await asyncio.wait_for(asyncio.gather(*futures.values()), 60), strict=True)
        )
        announced = await list_workers(disp.session, Keys(hub.prefix))
        return reports, centroids, announced

    reports, centroids, announced = _run(hub, scenario)
    assert [(a.worker_id, a.busy_job) for a in announced] == [("w1", None), ("w2", None)]
    assert sum(a.jobs_done for a in announced) == 10
    assert all(env.ok for env in reports.values()), [env.error for env in reports.values()]
    for job_id, env in reports.items():
        seen = _observed(hub, job_id)
        assert env.report.job_id == job_id and env.attempt == 1 and env.report.inputs.points == 2000
        assert seen["n_points"] == 2000
        np.testing.assert_allclose(seen["centroid_mm"], centroids[job_id], atol=1e-3)
        assert seen["passes"] == [0, 1, 2, 3]
    starts = Counter(job for kind, job, _ in _records(record) if kind == "start")
    assert starts == Counter({f"job{i:02d}": 1 for i in range(10)})
    assert {env.worker_id for env in reports.values()} == {"w1", "w2"}  # the work was shared
    assert w1.proc.poll() is None and w2.proc.poll() is None


def test_worker_killed_mid_analysis_the_other_completes_the_job(hub, start_worker):
    record = hub.tmp / "calls.txt"
    workers = {"w1": start_worker("w1"), "w2": start_worker("w2")}
    assigned: list[tuple[str, str, int]] = []
    retries: list[tuple[str, str, str]] = []
    hooks = DispatchHooks(
        on_assigned=lambda j, w, a: assigned.append((j, w, a)),
        on_retry=lambda j, w, r: retries.append((j, w, r)),
    )

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 2, 30, "two workers")
        payload, centroid = _cloud_bytes("jobK")
        fut = disp.submit(_job(hub, "jobK", "P1", record_path=str(record), sleep_s=1.5), payload)
        await _wait_for(lambda: any(k == "start" for k, _, _ in _records(record)), 20, "analysis start")
        victim = assigned[0][1]
        child_pid = _records(record)[0][2]
        workers[victim].proc.send_signal(signal.SIGKILL)
        env = await asyncio.wait_for(fut, 30)
        return env, victim, child_pid, centroid

    env, victim, child_pid, centroid = _run(hub, scenario, hooks=hooks)
    assert env.ok and env.attempt == 2 and env.worker_id != victim
    np.testing.assert_allclose(_observed(hub, env.job_id)["centroid_mm"], centroid, atol=1e-3)
    assert retries and retries[0][1] == victim and "disappeared" in retries[0][2]
    # the killed worker's analysis process does not outlive it
    wait_until_sync(lambda: not _pid_alive(child_pid), 0.5, "the killed worker's analysis process gone")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (not yet reaped by init) counts as gone
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("shm_pool_mb", [0, 64], ids=["tcp", "shared-memory"])
def test_job_waits_without_workers_and_is_analysed_when_one_starts(hub, start_worker, shm_pool_mb):
    async def scenario(disp: Dispatcher):
        payload, centroid = _cloud_bytes("jobW")
        fut = disp.submit(_job(hub, "jobW", "P1"), payload)
        await asyncio.sleep(1.0)  # stays: time passing with no worker, in which nothing must happen
        assert not fut.done() and disp.workers == [] and disp.pending == ["jobW"]
        start_worker("late")
        env = await asyncio.wait_for(fut, 30)
        return env, centroid

    env, centroid = _run(hub, scenario, settings=DispatchSettings(shm_pool_mb=shm_pool_mb))
    assert env.ok and env.worker_id == "late" and env.attempt == 1
    np.testing.assert_allclose(_observed(hub, env.job_id)["centroid_mm"], centroid, atol=1e-3)


def test_analysis_exception_is_reported_once_and_not_retried(hub, start_worker):
    start_worker("w1", analysis="tests.support.zworker_fns:always_raises")
    retries: list = []

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        return await asyncio.wait_for(disp.submit(_job(hub, "jobE", "P9"), _cloud_bytes("jobE", n=7)[0]), 30)

    env = _run(hub, scenario, hooks=DispatchHooks(on_retry=lambda *a: retries.append(a)))
    assert not env.ok and env.report is None
    assert "ValueError: plate P9: no plate surface in 7 points" in env.error
    assert retries == []


def test_a_result_that_is_no_report_is_an_analysis_error_named_by_the_worker(hub, start_worker):
    start_worker("w1", analysis="tests.support.zworker_fns:not_a_report")

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        return await asyncio.wait_for(disp.submit(_job(hub, "jobN", "P2"), _cloud_bytes("jobN", n=9)[0]), 30)

    env = _run(hub, scenario)
    assert not env.ok and env.report is None and env.attempt == 1
    assert "ValidationError" in env.error and "n_points" in env.error and "verdict" in env.error


@pytest.mark.slow
def test_job_fails_after_max_attempts_when_every_worker_dies(hub, start_worker):
    workers = [start_worker("w1"), start_worker("w2")]
    record = hub.tmp / "calls.txt"

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 2, 30, "two workers")
        fut = disp.submit(
            _job(hub, "jobX", "P1", record_path=str(record), sleep_s=30), _cloud_bytes("jobX")[0]
        )
        for n in (1, 2):
            await _wait_for(lambda n=n: len(_records(record)) >= n, 20, f"analysis start {n}")
            holder = disp.assignment("jobX")[0]
            next(w for w in workers if w.worker_id == holder).proc.send_signal(signal.SIGKILL)
        with pytest.raises(JobFailed, match=r"2 attempts; last: worker w[12] disappeared"):
            await asyncio.wait_for(fut, 30)

    _run(hub, scenario, settings=DispatchSettings(ack_timeout_s=5, heartbeat_timeout_s=3, max_attempts=2))


def test_worker_exits_zero_on_sigterm_and_its_token_goes_away(hub, start_worker):
    w = start_worker("w1")

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        w.proc.send_signal(signal.SIGTERM)
        await _wait_for(lambda: disp.workers == [], 10, "token removal")

    _run(hub, scenario)
    assert w.proc.wait(10) == 0, w.log()
    assert "worker_stopped" in w.log()


def test_worker_with_unknown_analysis_callable_exits_2_naming_it(hub, start_worker):
    w = start_worker("w1", analysis="tests.support.zworker_fns:no_such_function")
    assert w.proc.wait(60) == 2
    assert "has no attribute 'no_such_function'" in w.log()


@pytest.mark.slow
def test_frozen_worker_loses_its_job_to_the_other_after_heartbeat_timeout(hub, start_worker):
    record = hub.tmp / "calls.txt"
    workers = {"w1": start_worker("w1"), "w2": start_worker("w2")}
    retries: list[tuple[str, str, str]] = []

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 2, 30, "two workers")
        fut = disp.submit(
            _job(hub, "jobF", "P1", record_path=str(record), sleep_s=1.0), _cloud_bytes("jobF")[0]
        )
        await _wait_for(lambda: disp.assignment("jobF")[0] is not None, 10, "assignment")
        holder = workers[disp.assignment("jobF")[0]]
        holder.proc.send_signal(signal.SIGSTOP)  # alive to the OS and the link, silent to us
        try:
            env = await asyncio.wait_for(fut, 30)
        finally:
            holder.proc.send_signal(signal.SIGCONT)
        await asyncio.sleep(1.0)  # the thawed worker's late report, if any, must change nothing
        return env, holder.worker_id

    settings = DispatchSettings(ack_timeout_s=3.0, heartbeat_timeout_s=2.5, max_attempts=3)
    env, victim = _run(
        hub, scenario, settings=settings, hooks=DispatchHooks(on_retry=lambda *a: retries.append(a))
    )
    assert env.ok and env.worker_id != victim and env.attempt == 2
    assert retries[0][1] == victim
    assert "no heartbeat" in retries[0][2] or "no acknowledgement" in retries[0][2]
    assert len(retries) == 1


def test_malformed_messages_are_counted_and_endpoints_keep_serving(hub, start_worker):
    w = start_worker("w1")
    keys = Keys(hub.prefix)

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        disp.session.put(keys.worker_job("w1", "jobZ"), b"garbage")  # no JobSpec attachment
        disp.session.put(keys.worker_job("w1", "jobZ"), b"garbage", attachment=b"{not json")
        disp.session.put(keys.report("jobZ"), b"\xff not a report")
        disp.session.put(keys.job_event("jobZ"), b'{"job_id": "jobZ"}')
        payload, centroid = _cloud_bytes("jobOK")
        env = await asyncio.wait_for(disp.submit(_job(hub, "jobOK", "P1"), payload), 30)
        return env, centroid, disp.malformed

    env, centroid, malformed = _run(hub, scenario)
    assert env.ok and env.attempt == 1
    np.testing.assert_allclose(_observed(hub, env.job_id)["centroid_mm"], centroid, atol=1e-3)
    assert malformed == 2
    assert w.proc.poll() is None
    assert "job_message_malformed" in w.log() and "no JobSpec attachment" in w.log()


def test_jobs_flow_with_password_auth_and_access_control_on(hub, start_worker, monkeypatch):
    """Liveliness, jobs, events and reports all pass the ACL; keys outside the cell prefix do not."""
    users = hub.tmp / "users.txt"
    users.write_text("cellctl:pw-123\n")
    users.chmod(0o600)  # a dictionary readable by others is refused
    monkeypatch.setenv("TEST_CELL_ZENOH_PW", "pw-123")  # inherited by the worker process
    with hub.toml.open("a") as f:
        f.write(
            f'\n[zenoh.access]\nenabled = true\npassword_env = "TEST_CELL_ZENOH_PW"\ndictionary_file = "{users}"\n'
        )
    cfg = load_config(hub.toml)
    hub.section = cfg.zenoh
    start_worker("w1")
    outside: list = []

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "worker")
        subscribe(disp.session, "other/**", outside.append)
        client = open_session(build_zenoh_config(cfg.zenoh, role="connect", key_prefix=hub.prefix))
        try:
            client.put("other/x", b"must be filtered")
            payload, centroid = _cloud_bytes("jobA")
            env = await asyncio.wait_for(disp.submit(_job(hub, "jobA", "P1"), payload), 30)
        finally:
            close_session(client)
        return env, centroid

    env, centroid = _run(hub, scenario)
    assert env.ok and env.worker_id == "w1"
    np.testing.assert_allclose(_observed(hub, env.job_id)["centroid_mm"], centroid, atol=1e-3)
    assert outside == []


def test_worker_started_before_the_daemon_connects_once_it_listens(hub, start_worker):
    w = start_worker("early")
    # it is up and retrying its connection
    wait_until_sync(
        lambda: "worker_connect_failed" in w.log() or w.proc.poll() is not None, 3.0, "the worker's retry"
    )
    assert w.proc.poll() is None, w.log()

    async def scenario(disp: Dispatcher):
        payload, centroid = _cloud_bytes("jobE1")
        return await asyncio.wait_for(disp.submit(_job(hub, "jobE1", "P1"), payload), 30), centroid

    env, centroid = _run(hub, scenario)
    assert env.ok and env.worker_id == "early"
    np.testing.assert_allclose(_observed(hub, env.job_id)["centroid_mm"], centroid, atol=1e-3)


@pytest.mark.slow
def test_sigterm_mid_analysis_hands_the_job_back_and_exits_zero(hub, start_worker):
    record = hub.tmp / "calls.txt"
    workers = {"w1": start_worker("w1"), "w2": start_worker("w2")}
    retries: list[tuple[str, str, str]] = []

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 2, 30, "two workers")
        fut = disp.submit(
            _job(hub, "jobT", "P1", record_path=str(record), sleep_s=1.5), _cloud_bytes("jobT")[0]
        )
        await _wait_for(lambda: len(_records(record)) >= 1, 20, "analysis start")
        holder = workers[disp.assignment("jobT")[0]]
        t0 = time.monotonic()
        holder.proc.send_signal(signal.SIGTERM)
        env = await asyncio.wait_for(fut, 30)
        return env, holder, time.monotonic() - t0

    env, holder, _ = _run(hub, scenario, hooks=DispatchHooks(on_retry=lambda *a: retries.append(a)))
    assert env.ok and env.worker_id != holder.worker_id and env.attempt == 2
    assert holder.proc.wait(10) == 0, holder.log()
    assert retries[0][1] == holder.worker_id
    assert "worker stopping" in retries[0][2] or "disappeared" in retries[0][2]
    assert "analysis_process_ready" in holder.log() and holder.log().count("analysis_process_ready") == 1


def test_a_job_cancelled_mid_analysis_is_handed_back_and_the_worker_analyses_the_next_one_afresh(
    hub, start_worker
):
    # The dispatcher cancels a job it took back (heartbeat lost over a cut link). The worker must
    # say "cancelled" (so the job is retried at once) and restart its analysis process: the old
    # child is still busy with the cancelled cloud, and its late answer must not become the next
    # job's report.
    record = hub.tmp / "calls.txt"
    w1 = start_worker("w1")
    retries: list[tuple[str, str, str]] = []

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 1, 30, "the worker")
        payload, centroid_c = _cloud_bytes("jobC", offset_mm=50.0)
        fut = disp.submit(_job(hub, "jobC", "P1", record_path=str(record), sleep_s=3.0), payload)
        await _wait_for(lambda: len(_records(record)) >= 1, 20, "analysis start")
        disp.session.put(Keys(hub.prefix).worker_cancel("w1", "jobC"), b"")
        env_c = await asyncio.wait_for(fut, 60)
        payload, centroid_d = _cloud_bytes("jobD", offset_mm=-50.0)
        env_d = await asyncio.wait_for(disp.submit(_job(hub, "jobD", "P1", sleep_s=0.0), payload), 60)
        return env_c, centroid_c, env_d, centroid_d

    env_c, centroid_c, env_d, centroid_d = _run(
        hub, scenario, hooks=DispatchHooks(on_retry=lambda *a: retries.append(a))
    )
    assert retries and "cancelled by the dispatcher" in retries[0][2], retries
    assert env_c.ok and env_c.attempt == 2 and env_c.report.job_id == "jobC"
    assert env_d.ok and env_d.attempt == 1 and env_d.report.job_id == "jobD"
    np.testing.assert_allclose(_observed(hub, "jobC")["centroid_mm"], centroid_c, atol=1e-3)
    np.testing.assert_allclose(_observed(hub, "jobD")["centroid_mm"], centroid_d, atol=1e-3)
    assert w1.log().count("analysis_process_ready") == 2, w1.log()[-3000:]


def test_a_forged_report_from_a_peer_naming_another_worker_is_refused_and_the_real_one_counts(
    hub, start_worker
):
    """Access control off: any peer can publish on ``reports/<job>``. A report naming another worker
    (or an attempt that is not current) must not resolve the job, and the real worker's analysis
    must go on to its report (issue 24, finding 4). The forged reports are valid envelopes (here an
    analysis failure, which would have failed the job as surely as a forged verdict passes it)."""
    start_worker("w1")
    record = hub.tmp / "calls.txt"

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: len(disp.workers) == 1, 30, "the worker")
        payload, centroid = _cloud_bytes("jobF")
        fut = disp.submit(_job(hub, "jobF", "P1", record_path=str(record), sleep_s=2.0), payload)
        await _wait_for(lambda: any(k == "start" for k, _, _ in _records(record)), 20, "analysis start")
        forged = [
            {"worker_id": "intruder", "attempt": 1},  # a worker id nobody assigned
            {"worker_id": "w1", "attempt": 2},  # the right worker, an attempt that does not exist
        ]
        for f in forged:
            body = {"job_id": "jobF", "plate_id": "P1", "ok": False, "error": "forged", **f}
            disp.session.put(disp.keys.report("jobF"), json.dumps(body).encode())
        await _wait_for(lambda: disp.refused_reports == 2, 10, "both forged reports refused")
        assert not fut.done() and disp.malformed == 0
        env = await asyncio.wait_for(fut, 30)
        return env, centroid

    env, centroid = _run(hub, scenario)
    assert env.ok and env.worker_id == "w1" and env.attempt == 1 and env.error is None
    np.testing.assert_allclose(_observed(hub, "jobF")["centroid_mm"], centroid, atol=1e-3)
