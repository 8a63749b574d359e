"""The acquisition pipeline on synthetic inputs with known truth (a tilted plane under a sweeping arm)."""

from __future__ import annotations

import numpy as np
import pytest

from cellctl.acquisition.clock_sync import ClockSyncConfig
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from tests.support.synthetic_scan import feed, make_run, plane_errors_mm


@pytest.fixture(scope="module")
def run():
    return make_run(6.0)


def _cloud(run, **kw):
    acq = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns, **kw))
    feed(acq, run)
    return acq, acq.cloud()


def _rms_max(cloud):
    e = plane_errors_mm(cloud.points()["xyz_mm"])
    return float(np.sqrt(np.mean(e**2))), float(np.max(np.abs(e)))


def test_synchronised_cloud_lies_on_the_true_surface_within_sensor_noise(run):
    # the synthetic links' minimum latencies differ by 0.8 ms; drift is fitted from 3 s of pairs on
    acq, cloud = _cloud(run, latency_ms=0.8, sensor_sync_config=ClockSyncConfig(min_drift_span_s=3.0))
    rms, mx = _rms_max(cloud)
    assert rms < 0.025  # sensor noise is 0.02 mm
    assert mx < 0.12
    q = acq.quality()
    assert q["sensor_clock"]["drift_ppm"] == pytest.approx(-50.0, abs=3.0)
    assert q["profiles_without_pose"] == 0


def test_without_synchronisation_the_30ms_offset_shows_as_a_large_error(run):
    _, synced = _cloud(run, latency_ms=0.8)
    _, raw = _cloud(run, sensor_sync="none")
    _, naive = _cloud(run, sensor_sync="host_receive")
    rms_sync = _rms_max(synced)[0]
    assert _rms_max(raw)[0] > 10 * rms_sync
    assert _rms_max(naive)[1] > 5 * _rms_max(synced)[1]  # latency spikes: misplaced profiles


def test_millisecond_counter_wrapping_mid_scan_changes_nothing():
    start = 2**32 - 3000  # wraps 3 s into the 6 s run
    plain = make_run(6.0, counter_start_ms=0)
    wrapping = make_run(6.0, counter_start_ms=start)
    assert np.any(
        np.diff(np.concatenate([p.hd8_ms for k, p in wrapping.events if k == "profiles"]).astype(np.int64))
        < 0
    )
    _, a = _cloud(plain, latency_ms=0.8, sensor_clock="ms")
    _, b = _cloud(wrapping, latency_ms=0.8, sensor_clock="ms")
    assert a.digest() == b.digest()
    assert _rms_max(b)[0] < 0.03


def test_profiles_keep_their_grid_and_pass_ids(run):
    acq = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns, latency_ms=0.8))
    acq.begin_pass(3, run.epoch_ns + 1_000_000_000)
    acq.end_pass(run.epoch_ns + 2_000_000_000)
    acq.begin_pass(4, run.epoch_ns + 2_500_000_000)
    feed(acq, run)
    c = acq.cloud()
    t_s = (c.t_ns - run.epoch_ns) * 1e-9
    assert np.all(c.pass_id[(t_s > 1.01) & (t_s < 1.99)] == 3)
    assert np.all(c.pass_id[(t_s > 2.01) & (t_s < 2.49)] == -1)
    assert np.all(c.pass_id[t_s > 2.51] == 4)
    assert c.xyz_mm.shape == (len(c), 200, 3)
    np.testing.assert_array_equal(c.profile_index, np.arange(len(c)))
    assert np.all(np.diff(c.frame_index.astype(np.int64)) == 1)
    pts = c.points()
    assert len(pts["xyz_mm"]) == c.n_valid == int(c.valid.sum())
    assert pts["point_index"].max() < 200


def test_a_silent_controller_does_not_grow_the_backlog_without_bound(run):
    acq = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns, max_pending_profiles=100))
    for kind, payload in run.events:
        if kind == "profiles":
            acq.feed_profiles(payload)
    assert acq.stats.profiles_in - acq.stats.profiles_assembled <= 102
    assert acq.stats.profiles_without_pose > 0
