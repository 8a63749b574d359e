"""The daemon's HTML step (cellctl.daemon.handover.render_html): after the job is done with report.json, the render runs in a child process
and its path and time are recorded with the job (no Zenoh, no cell: the step on its own)."""

from __future__ import annotations

import asyncio
import time

import pytest

from analysis.templates import DetectionLayout
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.handover import render_html
from cellctl.jobstore.jobs import JobRecord, JobStore
from tests.support.results_fixture import write_synthetic_results

pytestmark = pytest.mark.process  # the render runs in a child process


def _store_and_job(tmp_path) -> tuple[JobStore, ActiveJob]:
    cfg = CellConfig.model_validate({"cell": {"data_dir": str(tmp_path / "data")}})
    store = JobStore(cfg.cell.data_dir)
    rec = JobRecord(job_id="20260101T000000-html", plate_id="P1", design="d.ply", design_path="/d.ply",
                    placement={"pos_mm": [0, 0, 0], "rpy_deg": [0, 0, 0]})  # fmt: skip
    store.create(rec)
    rec.info = rec.info.updated(last_profile_utc_s=time.time())
    return store, ActiveJob(rec)


def test_html_render_is_recorded_with_the_job_after_the_last_profile(tmp_path):
    store, job = _store_and_job(tmp_path)
    results = store.results_dir(job.record.job_id)
    # three lines: the render's cost is one plot per line
    write_synthetic_results(results, n_points=5_000, layout=DetectionLayout(2, 100.0, 1, 100.0, False))
    asyncio.run(render_html(store, job))
    stored = store.load(job.record.job_id).info
    assert stored.report_html == str((results / "report.html").resolve())
    assert (results / "report.html").stat().st_size > 10_000 and (results / "report.pdf").exists()
    assert 0 < stored.html_s <= stored.html_after_last_profile_s


def test_a_failed_render_leaves_the_job_without_html_and_raises_nothing(tmp_path):
    store, job = _store_and_job(tmp_path)
    results = store.results_dir(job.record.job_id)
    results.mkdir(parents=True)
    (results / "report.json").write_text("{ not json")
    asyncio.run(render_html(store, job))
    stored = store.load(job.record.job_id).info
    assert stored.report_html is None and stored.html_after_last_profile_s is None and stored.html_s > 0
    assert not (results / "report.html").exists()
