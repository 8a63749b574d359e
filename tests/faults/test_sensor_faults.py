"""Sensor faults: the HD8 stream disconnects, corrupts frames, stalls, or its clock jumps.

Injected into the simulated HD8 through ``<prefix>/sim/faults``; the daemon meets them only on the
HD8 protocol. Each case states its expected outcome and checks that nothing acquired is lost (raw
profiles == profiles received, no frame stored twice, no profile twice in the cloud) and that the
job's history is consistent. The job record's ``info.sensor`` says what the link went through.
"""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from tests.support.faultcell import (
    ANALYSIS_REFUSED_WHEN_SENSOR_STARVED,
    STALL_WHEN_CONTROLLER_STARVED,
    expect_done,
    module_cell,
    overruns,
    run_job,
)

STARVED = (STALL_WHEN_CONTROLLER_STARVED, ANALYSIS_REFUSED_WHEN_SENSOR_STARVED)

pytestmark = [pytest.mark.slow, pytest.mark.e2e]


cell = module_cell("sensorfaults")


def _contiguous(frame_index: np.ndarray) -> bool:
    return bool(frame_index.size and np.all(np.diff(np.sort(frame_index)) == 1))


def _gap_reported_exactly(run) -> None:
    """Every frame missing between the first and the last one on disk is in the job record's count."""
    sensor = run.info["sensor"]
    fi = np.sort(run.check.raw_frame_index)
    assert int(fi[-1] - fi[0] + 1 - fi.size) == sensor["missing_frames"] + sensor["overflow_frames"], sensor
    assert sensor["frames"] == run.check.raw_profiles


def test_disconnect_mid_pass_reconnects_and_replays_the_missed_frames_without_duplicates(cell):
    """The data connection is cut 30 frames after 30 % of the scan. Expected: the client reconnects
    and subscribes from the frame after the last one it delivered, the sensor's ring buffer fills the
    hole, replayed frames it already had are dropped; the scan completes with every frame exactly once
    (contiguous frame indices, no gap), the cloud holds no profile twice, the analysis reports."""
    run = asyncio.run(run_job(cell, [(0.3, {"laser": {"disconnect_after_frames": 30}})]))
    sensor = run.info["sensor"]
    assert sensor["reconnects"] >= 1, sensor
    _gap_reported_exactly(run)
    assert run.check.cloud_duplicate_points == 0 and run.check.cloud_points > 0
    expect_done(run, *STARVED)
    # The only frames allowed missing are those a starved simulator could not render in time: it
    # skips and counts them (overrun_frames), so they never existed to be replayed. Idle: none.
    overrun = run.sim_delta("laser", "overrun_frames")
    assert sensor["missing_frames"] == overrun, (sensor, overruns(run))  # and on disk: see above
    if overrun == 0:
        assert sensor["gaps"] == 0 and _contiguous(run.check.raw_frame_index), sensor


def test_corrupt_frames_are_skipped_counted_and_the_gap_is_reported(cell):
    """Three frame groups with a broken payload (framing intact) at 30 %, one with broken framing at
    60 %. Expected: the payload-corrupt groups are skipped and counted (decode errors), the frames in
    them are a gap that the job record reports (``info.sensor.gaps`` / ``missing_frames``); the broken
    framing makes the client reconnect and resume from the ring buffer (no gap from it); the scan
    completes, nothing received is lost, nothing is stored twice."""
    run = asyncio.run(
        run_job(
            cell,
            [
                (0.3, {"laser": {"corrupt": {"groups": 3, "mode": "payload"}}}),
                (0.6, {"laser": {"corrupt": {"groups": 1, "mode": "framing"}}}),
            ],
        )
    )
    _gap_reported_exactly(run)  # the reported gap is the real one, whatever the outcome
    expect_done(run, *STARVED)
    assert len(run.replies) == 2, run.replies
    sensor = run.info["sensor"]
    assert sensor["decode_errors"] >= 3, sensor
    assert sensor["gaps"] >= 1 and sensor["missing_frames"] >= 3, sensor
    assert sensor["reconnects"] >= 1, sensor


def test_stalled_stream_resumes_and_delivers_the_held_frames(cell):
    """The sensor sends nothing for 1.5 s at 30 % (it keeps acquiring). Expected: the client reports the
    stall (STALLED after its 0.5 s watchdog, then RESUMED), the held frames arrive late and are all
    kept: no gap, every frame exactly once, the scan completes. (Regression: the simulator released
    the held groups at equal send times, which the event loop's timer heap does not keep in order;
    the client counted the overtaken frames missing, then dropped them as stale.)"""
    run = asyncio.run(run_job(cell, [(0.3, {"laser": {"stall_s": 1.5, "stall_acquire": True}})]))
    _gap_reported_exactly(run)
    assert cell.log_events("run", "hd8_frames_stalled") and cell.log_events("run", "hd8_frames_resumed")
    expect_done(run, *STARVED)
    assert run.info["sensor"]["missing_frames"] == 0, run.info["sensor"]
    assert _contiguous(run.check.raw_frame_index)


@pytest.mark.parametrize("jump_ms", [250.0])
def test_sensor_clock_jump_mid_scan_keeps_every_profile_and_the_cloud_on_the_plate(cell, jump_ms):
    """The sensor's clock jumps 250 ms ahead at 40 % of the scan. Expected: the stamps jump, the online
    clock fit (lower envelope) follows at its next refit instead of mapping the rest of the scan
    250 ms off; the scan
    completes, every frame is kept once, and the analysis still reports on the plate."""
    run = asyncio.run(run_job(cell, [(0.4, {"laser": {"clock_jump_ms": jump_ms}})]))
    _gap_reported_exactly(run)
    assert run.replies[0].laser["clock_jump_ms"] == jump_ms
    expect_done(run, *STARVED)
    assert _contiguous(run.check.raw_frame_index)
    report = json.loads((cell.jobs_dir / run.job_id / "report.json").read_text())
    # a clean scan of this plate registers at about 0.36 mm rms; 250 ms of stamp error on a pass at
    # over 200 mm/s would put profiles tens of mm off
    assert report["registration"]["icp_rms_mm"] < 0.6, report["registration"]


@pytest.mark.parametrize("jump_ms", [250.0, -250.0, 2000.0, -2000.0])
def test_clock_fit_follows_a_step_of_the_device_clock_and_not_a_latency_burst(jump_ms):
    """The estimator alone: 200 pairs/s with exponential latency, the device clock steps at 10 s.
    Expected: the fit maps the new stamps within 5 ms again 2.5 s of device time later (a jump back
    is detected as a step; without that it stayed off for the whole 120 s window; a jump ahead is
    followed by the next refit of the lower envelope); a 0.5 s latency burst of 150 ms is no step."""
    from cellctl.acquisition.clock_sync import ClockSync, ClockSyncConfig

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 16.0, 0.005)
    src = (t * 1e6).astype(np.int64) + 7_000_000
    src[t >= 10.0] += int(jump_ms * 1000)
    lat_ns = 2e6 + rng.exponential(1e6, t.size)
    lat_ns[(t >= 5.0) & (t < 5.5)] += 150e6  # a latency burst, not a step
    host = (t * 1e9 + lat_ns).astype(np.int64)
    cs = ClockSync(ClockSyncConfig(step_ms=200.0), name="sensor")  # the detection is opt-in
    err_ms = np.full(t.size, np.nan)
    for i in range(0, t.size, 5):
        cs.add(src[i : i + 5], host[i : i + 5])
        if cs.fit is not None:
            err_ms[i : i + 5] = (cs.to_host_ns(src[i : i + 5]) - (t[i : i + 5] * 1e9 + 2e6)) * 1e-6
    assert cs.steps == (1 if jump_ms < 0 else 0)
    assert np.nanmax(np.abs(err_ms[(t > 1.0) & (t < 10.0)])) < 5.0  # the burst moved nothing
    assert np.nanmax(np.abs(err_ms[t > 12.5])) < 5.0
