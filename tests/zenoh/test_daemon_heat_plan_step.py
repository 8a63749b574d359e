"""The daemon's plan step (cellctl.daemon.heat_plan.make_heating_plan): after the job is done with
report.json, the plan child writes heating-plan.json and the job record names it; a child that fails
leaves the reason in heating-plan.json, never a changed report (no Zenoh, no cell: the step alone)."""

from __future__ import annotations

import asyncio
import time

import pytest

from analysis.design.plates import FormingError, GaussianBump, plate_spec
from analysis.forming.coefficients import DEFAULT_TABLE
from analysis.forming.plan_file import read_heating_plan
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.handover import render_html
from cellctl.daemon.heat_plan import make_heating_plan
from cellctl.jobstore.jobs import JobRecord, JobStore
from tests.support.results_fixture import CELL_LAYOUT, write_synthetic_results

# the plan runs in a child process: an interpreter, cellctl and the FE model, 3-10 s on the shared
# machine; no simulator, no Zenoh: it only computes, so make test runs it on both cores
pytestmark = [pytest.mark.slow, pytest.mark.compute]


def _store_and_job(tmp_path, **forming) -> tuple[CellConfig, JobStore, ActiveJob]:
    cfg = CellConfig.model_validate({
        "cell": {"data_dir": str(tmp_path / "data")},
        "forming": {"element_mm": 40.0, "max_lines_per_round": 4, **forming},
    })  # fmt: skip
    store = JobStore(cfg.cell.data_dir)
    rec = JobRecord(job_id="20260101T000000-heat", plate_id="P1", design="d.ply", design_path="/d.ply",
                    placement={"pos_mm": [0, 0, 0], "rpy_deg": [0, 0, 0]})  # fmt: skip
    store.create(rec)
    job = ActiveJob(rec)
    # a 600 x 400 cylinder under-bent by 20 %: 3.6 mm at its ends
    error = FormingError(bumps=(GaussianBump(0.0, 0.0, 0.0, 50.0),) * 2, bend_fraction=-0.2)
    spec = plate_spec("cylinder", length_mm=600.0, width_mm=400.0)
    write_synthetic_results(
        store.results_dir(rec.job_id), spec=spec, error=error, n_points=6000, layout=CELL_LAYOUT
    )
    return cfg, store, job


def test_the_plan_is_written_beside_the_report_and_recorded_with_the_job(tmp_path):
    cfg, store, job = _store_and_job(tmp_path)
    results = store.results_dir(job.record.job_id)
    report_before = (results / "report.json").read_bytes()
    assert asyncio.run(make_heating_plan(cfg, store, job)) is True
    stored = store.load(job.record.job_id).info
    assert stored.heating_plan == str((results / "heating-plan.json").resolve())
    assert stored.heating_plan_status == "plan" and stored.heating_plan_s > 0
    plan = read_heating_plan(results)
    assert plan.status == "plan" and plan.lines and plan.job_id == "job-fixture"
    assert (
        plan.model is not None and plan.model.element_mm == 40.0
    )  # the daemon's [forming] reached the child
    assert (results / "heating-plan.dxf").is_file()
    assert (results / "report.json").read_bytes() == report_before
    # the daemon renders report.html again once a plan is there: the plan drawn, the first render's
    # time after the last profile left as it was
    asyncio.run(render_html(store, job, with_plan=True))
    info = store.load(job.record.job_id).info
    assert info.html_with_plan_s > 0 and info.html_after_last_profile_s is None
    html = (results / "report.html").read_text(encoding="utf-8")
    assert "Heating plan" in html and "H1" in html


def test_a_failed_plan_child_leaves_its_reason_and_the_report_untouched(tmp_path):
    # the yard's table the daemon read at start is gone when the child reads the configuration
    table = tmp_path / "yard.toml"
    table.write_bytes(DEFAULT_TABLE.read_bytes())
    cfg, store, job = _store_and_job(tmp_path, coefficients_file=str(table))
    table.unlink()
    results = store.results_dir(job.record.job_id)
    report_before = (results / "report.json").read_bytes()
    assert asyncio.run(make_heating_plan(cfg, store, job)) is False
    stored = store.load(job.record.job_id).info
    assert stored.heating_plan_status == "no_plan"
    plan = read_heating_plan(results)
    assert plan.status == "no_plan" and plan.job_id == job.record.job_id
    assert "the plan child failed (exit 2)" in (plan.reason or "")
    assert "yard.toml" in (plan.reason or "")
    assert not (results / "heating-plan.dxf").exists()
    assert (results / "report.json").read_bytes() == report_before
    assert store.load(job.record.job_id).info.verdict is None  # the step never sets a verdict


def test_plans_turned_off_start_no_child_and_say_so(tmp_path):
    cfg, store, job = _store_and_job(tmp_path, enabled=False)
    t0 = time.perf_counter()
    asyncio.run(make_heating_plan(cfg, store, job))
    assert time.perf_counter() - t0 < 1.0  # no interpreter started
    plan = read_heating_plan(store.results_dir(job.record.job_id))
    assert plan.status == "no_plan" and "[forming] enabled = false" in (plan.reason or "")
    assert store.load(job.record.job_id).info.heating_plan_status == "no_plan"


def test_a_daemon_stopping_as_the_plan_starts_ends_the_step_at_once_with_the_reason(tmp_path):
    """The stop arrives while the child is being started (the daemon stopping just as a job's report
    was stored): the step ends without waiting for a plan, the file says how to make it."""
    cfg, store, job = _store_and_job(tmp_path)

    async def main() -> float:
        task = asyncio.create_task(make_heating_plan(cfg, store, job))
        await asyncio.sleep(0)  # the step has begun: it is starting its child
        t0 = time.perf_counter()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return time.perf_counter() - t0

    assert asyncio.run(main()) < 2.0
    plan = read_heating_plan(store.results_dir(job.record.job_id))
    assert plan.status == "no_plan" and "the daemon stopped while planning" in (plan.reason or "")
    assert "cellctl heat-plan" in (plan.reason or "")
