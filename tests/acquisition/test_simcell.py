"""End to end through the simulators: EGM controller + HD8 sensor on loopback, a formed sail plate.

One scan (four straight passes along one line, back and forth at 100 and 200 mm/s, over the plate's
sloped end) with the sensor clock 30 ms off and drifting 50 ppm, its 32-bit ms counter wrapping
mid-scan, is recorded once into raw files; the tests rebuild clouds from those files with different
clock handling, and calibrate the time offset on it.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cellctl.acquisition.pipeline import AcquisitionSettings
from cellctl.acquisition.reassemble import reassemble
from cellctl.calibration.time_offset import calibrate_time_offset
from cellctl.simcell.truth import plate_truth
from drivers.runtime import precise_event_loop
from tests.support.simcell import SimCell, SimCellConfig, joint_path, raster_poses

pytestmark = pytest.mark.slow

WRAP_AFTER_MS = 5000


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    truth = plate_truth()
    cfg = SimCellConfig(counter_start_ms=2**32 - WRAP_AFTER_MS, seed=3)
    T, passes = raster_poses(
        truth, [-230.0] * 4, x_range_mm=(280.0, 520.0), speed_mm_s=[100.0, 100.0, 200.0, 200.0]
    )
    path = joint_path(T, cfg.egm_cycle_s, cfg.T_flange_sensor, passes=passes)
    job = tmp_path_factory.mktemp("simscan") / "job"

    async def main():
        async with SimCell(truth.scene(), cfg, AcquisitionSettings(), job, path.q_deg[0]) as cell:
            await cell.run(path)
        return cell

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        cell = runner.run(main())
    return truth, cell, job


def _errors(truth, cell, cloud):
    ok = cell.truth_reliable(cloud.frame_index)
    keep = cloud.valid & ok[:, None]
    d, inside = truth.distance_mm(cloud.xyz_mm[keep].astype(np.float64))
    pass_id = np.broadcast_to(cloud.pass_id[:, None], cloud.valid.shape)[keep]
    return d[inside], pass_id[inside]


def _pass_gap_mm(d, pass_id):
    means = [float(np.mean(d[pass_id == k])) for k in range(4)]
    return max(means) - min(means)


@pytest.fixture(scope="module")
def final(scan):
    """The final cloud with the job's settings (latency 0): shared by several tests."""
    return reassemble(scan[2])


@pytest.fixture(scope="module")
def calibrated(scan):
    _, _, job = scan
    return calibrate_time_offset(job)


def test_time_offset_calibration_recovers_the_simulators_true_offset(scan, final, calibrated):
    _, cell, _ = scan
    true_ms = cell.true_time_offset_ms(final.fits)
    assert abs(calibrated.latency_ms - true_ms) < 0.5, (calibrated.report(), true_ms)
    rep = calibrated.report()
    assert rep["disagreement_after_mm"] < rep["disagreement_before_mm"]
    # the residual timing error does not grow with speed once calibrated
    assert all(abs(v) < 0.5 for v in rep["per_speed_residual_ms"].values())


def test_synchronised_scan_matches_the_true_plate_surface(scan, calibrated):
    truth, cell, job = scan
    res = reassemble(job, {"latency_ms": calibrated.latency_ms})
    d, pid = _errors(truth, cell, res.cloud)
    assert len(d) > 200_000
    rms, mx = float(np.sqrt(np.mean(d**2))), float(np.max(np.abs(d)))
    assert rms < 0.05, (rms, res.quality["sensor_clock"])
    assert mx < 0.2, mx
    assert _pass_gap_mm(d, pid) < 0.02  # forward and backward passes agree: no doubled surface


def test_without_synchronisation_the_passes_visibly_disagree(scan, final):
    truth, cell, job = scan
    d_sync, _ = _errors(truth, cell, final.cloud)
    d_raw, pid_raw = _errors(truth, cell, reassemble(job, {"sensor_sync": "none"}).cloud)
    # 30 ms at 100 mm/s is 3 mm along the pass: on the plate's ~0.1 slope, 0.3 mm up or down
    assert _pass_gap_mm(d_raw, pid_raw) > 0.3
    assert np.sqrt(np.mean(d_raw**2)) > 3 * np.sqrt(np.mean(d_sync**2))


def test_ms_counter_wrapping_mid_scan_changes_nothing(scan, final):
    truth, cell, job = scan
    res_us = final
    res_ms = reassemble(job, {"sensor_clock": "ms"})
    hd8 = np.concatenate([r.arrays["hd8_ms"] for r in _profile_records(job)]).astype(np.int64)
    assert np.count_nonzero(np.diff(hd8) < -(2**31)) == 1  # it did wrap, once
    d, _ = _errors(truth, cell, res_ms.cloud)
    assert np.sqrt(np.mean(d**2)) < 0.05
    diff_ms = (res_ms.cloud.t_ns - res_us.cloud.t_ns) * 1e-6
    # counter-based stamps agree with the us stamps across the wrap, to the counter's 1 ms resolution
    assert np.max(np.abs(diff_ms)) < 1.0


def test_live_cloud_is_rebuilt_bit_for_bit_from_the_raw_files(scan):
    _, cell, job = scan
    assert reassemble(job, final=False).cloud.digest() == cell.acq.cloud().digest()


def _profile_records(job):
    from cellctl.acquisition.rawstore import RawReader

    return [r for r in RawReader(job).records() if r.stream == "profiles"]
