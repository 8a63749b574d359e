"""The spawned analysis process on its own (no Zenoh): its environment and one job through the pipe."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cellctl.cloud_codec import Cloud, encode_cloud
from cellctl.worker import AnalysisProcess

pytestmark = pytest.mark.process  # the spawned analysis process

FN = "tests.zenoh.zworker_fns:blas_environment"


def _run_once(proc: AnalysisProcess) -> dict:
    payload = encode_cloud(Cloud(xyz_mm=np.zeros((4, 3), np.float32), job_id="j1", plate_id="p1"))

    async def go():
        await proc.start()
        try:
            return await proc.run({"job_id": "j1", "plate_id": "p1"}, bytes(payload))
        finally:
            proc.kill()

    out = asyncio.run(go())
    assert out.ok, out.error
    return out.report


def test_analysis_process_asks_blas_for_the_configured_threads(monkeypatch):
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    report = _run_once(AnalysisProcess(FN, blas_threads=3))
    assert report == {"OPENBLAS_NUM_THREADS": "3", "MKL_NUM_THREADS": "3"}


def test_an_explicit_blas_setting_in_the_environment_wins(monkeypatch):
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    assert _run_once(AnalysisProcess(FN, blas_threads=1)) == {
        "OPENBLAS_NUM_THREADS": "2",
        "MKL_NUM_THREADS": "1",
    }
