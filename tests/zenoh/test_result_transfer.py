"""Nothing shared but Zenoh: the design by hash, the results back in checksummed chunks; a result
that arrives incomplete or corrupt costs a retry, never the job."""

from __future__ import annotations

import asyncio
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.job import AnalysisJob
from cellctl.api import JobSpec, Keys
from cellctl.api.session import build_zenoh_config, close_session, open_session
from cellctl.api.transfer import (
    ResultChunk,
    ResultRefused,
    TransferError,
    TransferSpec,
    design_ref,
    pack_results,
)
from cellctl.daemon.dispatch import Dispatcher
from cellctl.daemon.result_collector import ResultCollector, store_results
from cellctl.worker.design_cache import cache_design, cached_design
from tests.support.zworker_fns import minimal_report
from tests.zenoh.fake_worker import FakeWorker
from tests.zenoh.test_dispatch_workers import GENEROUS, _cloud_bytes, _run, _wait_for


def _results_dir(tmp_path: Path) -> Path:
    d = tmp_path / "out"
    d.mkdir()
    (d / "report.json").write_text('{"verdict": "pass"}')
    (d / "results.npz").write_bytes(np.random.default_rng(1).bytes(10_000))
    (d / "empty.csv").write_bytes(b"")
    (d / "report.json.tmp").write_text("half written")
    return d


def _heads(manifest, chunks, job_id="j1", worker="w1", attempt=1):
    return [
        ResultChunk(job_id=job_id, worker_id=worker, attempt=attempt, index=i, chunks=len(chunks),
                    sha256=hashlib.sha256(c).hexdigest())
        for i, c in enumerate(chunks)
    ]  # fmt: skip


def test_a_packed_results_directory_comes_back_file_for_file_and_temp_files_stay_behind(tmp_path):
    d = _results_dir(tmp_path)
    manifest, chunks = pack_results(d, chunk_bytes=4096)
    assert manifest.chunks == len(chunks) == 3 and [f.name for f in manifest.files] == [
        "empty.csv",
        "report.json",
        "results.npz",
    ]
    col = ResultCollector()
    for head, data in zip(_heads(manifest, chunks), chunks, strict=True):
        assert col.add(head, data)
    files = col.take("j1", 1, "w1", manifest)
    store_results(files, tmp_path / "stored")
    for name in ("empty.csv", "report.json", "results.npz"):
        assert (tmp_path / "stored" / name).read_bytes() == (d / name).read_bytes()
    assert sorted(p.name for p in (tmp_path / "stored").iterdir()) == [
        "empty.csv",
        "report.json",
        "results.npz",
    ]


@pytest.mark.parametrize("damage", ["missing", "corrupt", "other_worker", "truncated_manifest"])
def test_an_incomplete_or_corrupt_bundle_is_refused(tmp_path, damage):
    manifest, chunks = pack_results(_results_dir(tmp_path), chunk_bytes=4096)
    col = ResultCollector()
    heads = _heads(manifest, chunks)
    for i, (head, data) in enumerate(zip(heads, chunks, strict=True)):
        if damage == "missing" and i == 1:
            continue
        if damage == "corrupt" and i == 1:
            assert not col.add(head, data[:-1] + bytes([data[-1] ^ 1]))  # its own checksum catches it
            continue
        if damage == "other_worker" and i == 2:
            head = head.model_copy(update={"worker_id": "w2"})
            assert not col.add(head, data)
            continue
        col.add(head, data)
    if damage == "truncated_manifest":
        manifest = manifest.model_copy(update={"total_bytes": manifest.total_bytes - 1})
    with pytest.raises(ResultRefused):
        col.take("j1", 1, "w1", manifest)
    assert col.held_bytes == 0


def test_a_bundle_beyond_the_bound_is_refused_by_both_sides(tmp_path):
    d = _results_dir(tmp_path)
    with pytest.raises(TransferError, match="more than"):
        pack_results(d, max_bytes=100)
    manifest, chunks = pack_results(d, chunk_bytes=4096)
    col = ResultCollector(max_bytes=5000)
    added = [col.add(h, c) for h, c in zip(_heads(manifest, chunks), chunks, strict=True)]
    assert added[0] and not added[-1] and col.held_bytes == 0
    with pytest.raises(ResultRefused, match="more than"):
        col.take("j1", 1, "w1", manifest)


def test_a_design_is_cached_by_hash_and_bytes_with_another_hash_are_refused(tmp_path):
    src = tmp_path / "plate.stl"
    src.write_bytes(b"solid plate\nendsolid\n")
    ref = design_ref(src)
    cache = tmp_path / "cache"
    assert cached_design(cache, ref) is None
    with pytest.raises(TransferError, match="do not have hash"):
        cache_design(cache, ref, b"solid other\nendsolid\n")
    path = cache_design(cache, ref, src.read_bytes())
    assert cached_design(cache, ref) == path and path.read_bytes() == src.read_bytes()
    path.write_bytes(b"tampered")
    assert cached_design(cache, ref) is None


@pytest.mark.e2e
def test_a_worker_gets_the_design_by_hash_and_returns_its_results_over_zenoh(hub, start_worker):
    start_worker("w1")
    design = hub.tmp / "designs" / "todo.json"
    design.parent.mkdir()
    design.write_text(json.dumps({"sleep_s": 0.1}))

    async def scenario(disp: Dispatcher):
        await _wait_for(lambda: disp.workers == ["w1"], 30, "the worker")
        payload, centroid = _cloud_bytes("jobT")
        ref = disp.designs.register(design)
        job = AnalysisJob(job_id="jobT", plate_id="P1", design=str(design), out_dir="/nonexistent/daemon/dir")
        env = await asyncio.wait_for(
            disp.submit(job, payload, transfer=TransferSpec(design=ref, chunk_bytes=4096)), 60
        )
        return env, centroid, ref, disp.take_results("jobT")

    env, centroid, ref, files = _run(hub, scenario)
    assert env.ok and env.results is not None
    seen = json.loads(files["observed.json"])
    np.testing.assert_allclose(seen["centroid_mm"], centroid, atol=1e-3)
    # the worker ran on its cached copy, under its own data dir, not on the daemon's paths
    assert not Path("/nonexistent/daemon/dir").exists()
    assert (
        hub.tmp / "worker-data" / "designs" / ref.sha256 / "todo.json"
    ).read_bytes() == design.read_bytes()
    assert env.report.inputs.design.endswith(f"{ref.sha256}/todo.json")


@pytest.mark.e2e
def test_a_result_that_arrives_incomplete_costs_a_retry_and_the_next_complete_one_counts(hub, tmp_path):
    """A worker (here a session of the test speaking the protocol) loses a chunk on its first
    attempt: the dispatcher refuses that result and sends the job again; the second is kept."""
    out = _results_dir(tmp_path)
    manifest, chunks = pack_results(out, chunk_bytes=4096)
    keys = Keys(hub.prefix)
    attempts: list[int] = []

    async def scenario(disp: Dispatcher):
        s = open_session(
            build_zenoh_config(hub.section, role="connect", key_prefix=hub.prefix), what="fake worker"
        )

        def answer(spec: JobSpec) -> None:
            attempts.append(spec.attempt)
            fw.event(spec, "accepted")
            fw.chunks(
                spec, chunks, skip=(1,) if spec.attempt == 1 else ()
            )  # attempt 1: chunk 1 lost on the way
            fw.report(spec, report=minimal_report(spec.job, 1), results=manifest)

        fw = FakeWorker(s, keys, "fw", answer)
        try:
            await _wait_for(lambda: disp.workers == ["fw"], 30, "the fake worker")
            job = AnalysisJob(job_id="jobR", plate_id="P1", design="p.stl")
            env = await asyncio.wait_for(
                disp.submit(job, _cloud_bytes("jobR")[0], transfer=TransferSpec()), 60
            )
            return env, disp.take_results("jobR"), disp.refused_results
        finally:
            fw.close()
            close_session(s)

    env, files, refused = _run(hub, scenario, settings=GENEROUS)
    assert attempts == [1, 2] and refused == 1 and env.attempt == 2
    assert files["results.npz"] == (out / "results.npz").read_bytes() and "report.json.tmp" not in files
