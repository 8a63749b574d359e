"""The spawned analysis process on its own (no Zenoh): its environment and one job through the pipe."""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.job import AnalysisJob
from cellctl.api.cloud_codec import Cloud, encode_cloud
from cellctl.worker.process import AnalysisProcess

pytestmark = pytest.mark.process  # the spawned analysis process

FN = "tests.support.zworker_fns:blas_environment"


def _run_once(proc: AnalysisProcess, out_dir: Path) -> dict:
    """One job through the child; what the analysis observed (its report is the minimal one)."""
    payload = encode_cloud(Cloud(xyz_mm=np.zeros((4, 3), np.float32), job_id="j1", plate_id="p1"))

    async def go():
        await proc.start()
        try:
            job = AnalysisJob(job_id="j1", plate_id="p1", design="none.stl", out_dir=str(out_dir))
            return await proc.run(job, bytes(payload))
        finally:
            proc.kill()

    out = asyncio.run(go())
    assert out.ok, out.error
    assert out.report is not None and out.report.job_id == "j1" and out.report.inputs.points == 4
    return json.loads((out_dir / "observed.json").read_text())


def test_analysis_process_asks_blas_for_the_configured_threads(monkeypatch, tmp_path):
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    report = _run_once(AnalysisProcess(FN, blas_threads=3), tmp_path)
    # OpenBLAS takes the setting up to the machine's cores
    assert report == {
        "OPENBLAS_NUM_THREADS": "3",
        "MKL_NUM_THREADS": "3",
        "numpy_openblas_threads": min(3, len(os.sched_getaffinity(0))),
    }


def test_numpy_in_the_analysis_process_runs_blas_on_one_thread(monkeypatch, tmp_path):
    """numpy (and its OpenBLAS) is loaded in the child before its own code runs: the setting must be
    in the environment the child starts with. (It was set inside the child: OpenBLAS ran on every
    core, and on a busy 2-core cell PC its spinning threads slowed the analysis' matrix products.)"""
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    report = _run_once(AnalysisProcess(FN, blas_threads=1), tmp_path)
    assert report["numpy_openblas_threads"] == 1
    assert "OPENBLAS_NUM_THREADS" not in os.environ  # the worker's own environment is left as it was


def test_an_explicit_blas_setting_in_the_environment_wins(monkeypatch, tmp_path):
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    assert _run_once(AnalysisProcess(FN, blas_threads=1), tmp_path) == {
        "OPENBLAS_NUM_THREADS": "2",
        "MKL_NUM_THREADS": "1",
        "numpy_openblas_threads": min(2, len(os.sched_getaffinity(0))),
    }


def test_a_request_the_child_cannot_use_ends_it_and_the_worker_sees_a_crash_not_a_wrong_answer(tmp_path):
    """Only the worker writes the pipe: an unknown op (or a job without its spec) is a broken pipe
    protocol; the child exits rather than answer it (an answer could pair with the wrong request)."""
    from cellctl.worker.process import AnalysisCrashed

    payload = encode_cloud(Cloud(xyz_mm=np.zeros((4, 3), np.float32), job_id="j1", plate_id="p1"))

    async def go(head: bytes):
        proc = AnalysisProcess(FN, blas_threads=1)
        await proc.start()
        try:
            proc._conn.send_bytes(head)  # what no ChildRequest can be
            proc._conn.send_bytes(b"")
            job = AnalysisJob(job_id="j1", plate_id="p1", design="none.stl", out_dir=str(tmp_path))
            with pytest.raises(AnalysisCrashed):
                await proc.run(job, bytes(payload))
        finally:
            proc.kill()

    asyncio.run(go(b'{"op": "nope"}'))
    asyncio.run(go(b'{"op": "job"}'))


def test_the_child_answers_with_a_typed_report_or_a_typed_error_and_nothing_in_between():
    """The child's answer is a ChildAnswer: the report when ok, else the error and its traceback;
    an answer with both, neither, or a field the protocol does not know is refused."""
    import time

    from pydantic import ValidationError

    from cellctl.worker.child import ChildAnswer, ChildHello, _error_text, _outcome_text
    from tests.support.zworker_fns import minimal_report

    job = AnalysisJob(job_id="j1", plate_id="p1", design="none.stl")
    report = minimal_report(job, 4)
    ok = ChildAnswer.model_validate_json(_outcome_text(report, {"analysis": 0.5}))
    assert ok.ok and ok.report == report and ok.error is None and ok.timings_s == {"analysis": 0.5}
    # an analysis callable may return the report's JSON object: it is validated into the model
    as_dict = ChildAnswer.model_validate_json(_outcome_text(report.model_dump(mode="json"), {}))
    assert as_dict.report == report
    try:
        raise ValueError("no plate surface")
    except ValueError as exc:
        failed = ChildAnswer.model_validate_json(_error_text(exc, time.perf_counter()))
    assert not failed.ok and failed.report is None and failed.error == "ValueError: no plate surface"
    assert "no plate surface" in failed.traceback and "total" in failed.timings_s
    for bad in (
        {"ok": True, "timings_s": {}},  # ok without a report
        {"ok": False, "timings_s": {}},  # failed without an error
        {"ok": True, "report": report.model_dump(mode="json"), "error": "x", "timings_s": {}},
        {"ok": False, "error": "x", "timings_s": {}, "detail": "?"},  # a field of no protocol
    ):
        with pytest.raises(ValidationError):
            ChildAnswer.model_validate_json(json.dumps(bad))
    assert (
        ChildHello.model_validate_json(b'{"ready": false, "error": "cannot import"}').error == "cannot import"
    )
    with pytest.raises(ValidationError):
        ChildHello.model_validate_json(b'{"ready": true, "pid": 3}')
