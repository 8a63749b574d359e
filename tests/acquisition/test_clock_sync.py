"""Clock synchronisation: lower-envelope offset + drift, 32-bit ms counter wrap, frame timeline."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.acquisition.clock_sync import (
    ClockSync,
    ClockSyncConfig,
    ClockSyncError,
    CounterUnwrapper,
    FrameTimeline,
    fit_lower_envelope,
)


def _pairs(offset_ms, drift_ppm, jitter_ms, spike_fraction, seed, n=3000, period_s=0.02, min_lat_ms=1.0):
    rng = np.random.default_rng(seed)
    t_true_s = np.arange(n) * period_s
    host0 = 7_000_000_000_000
    src_us = np.rint(t_true_s * (1 + drift_ppm * 1e-6) * 1e6 + offset_ms * 1e3 + 42_000_000).astype(np.int64)
    lat_s = min_lat_ms * 1e-3 + rng.exponential(max(jitter_ms, 1e-6) * 1e-3, n)
    spikes = rng.random(n) < spike_fraction
    lat_s[spikes] += rng.uniform(0.005, 0.08, spikes.sum())
    host_ns = host0 + np.rint((t_true_s + lat_s) * 1e9).astype(np.int64)
    truth_ns = host0 + np.rint((t_true_s + min_lat_ms * 1e-3) * 1e9).astype(np.int64)
    return src_us, host_ns, truth_ns


@settings(max_examples=12, deadline=None)
@given(
    offset_ms=st.floats(-500, 500),
    drift_ppm=st.floats(-200, 200),
    jitter_ms=st.floats(0.01, 2.0),
    spike_fraction=st.floats(0.0, 0.2),
    seed=st.integers(0, 10_000),
)
def test_fit_recovers_offset_and_drift_despite_jitter_and_latency_spikes(
    offset_ms, drift_ppm, jitter_ms, spike_fraction, seed
):
    src, host, truth = _pairs(offset_ms, drift_ppm, jitter_ms, spike_fraction, seed)
    sync = ClockSync(ClockSyncConfig(refit_interval_s=1.0), "sensor")
    for i in range(0, len(src), 10):  # online: batches of pairs as they arrive
        sync.add(src[i : i + 10], host[i : i + 10])
    sync._fit = sync._refit()  # final fit over everything, as a long scan would have
    err_ms = (sync.to_host_ns(src) - truth) * 1e-6
    # the envelope converges to the minimum latency: error bounded by the fastest arrivals' spread
    assert np.max(np.abs(err_ms)) < max(0.05, 0.1 * jitter_ms)
    assert abs(sync.fit.drift_ppm + drift_ppm) < 5.0  # host per source: drift appears negated
    assert sync.fit.spike_fraction >= 0.5 * spike_fraction - 0.02


def test_envelope_line_stays_below_every_pair():
    src, host, _ = _pairs(30.0, 50.0, 0.3, 0.05, seed=1)
    sync = ClockSync()
    sync.add(src, host)
    assert np.all(sync.to_host_ns(src) <= host + 1)  # +1 ns: rounding


def test_naive_least_squares_would_be_biased_by_spikes_but_envelope_is_not():
    src, host, truth = _pairs(0.0, 0.0, 0.2, 0.1, seed=2)
    d = (host - src * 1000).astype(np.float64)
    naive_bias_ms = (np.mean(d) - np.mean(truth - src * 1000)) * 1e-6
    sync = ClockSync()
    sync.add(src, host)
    env_bias_ms = np.mean(sync.to_host_ns(src) - truth) * 1e-6
    assert naive_bias_ms > 2.0
    assert abs(env_bias_ms) < 0.05


def test_drift_is_clamped_to_the_configured_bound():
    s = np.array([0.0, 1.0, 2.0])
    a, b = fit_lower_envelope(s, np.array([0.0, 1e6, 2e6]), max_slope=500e3)
    assert b == pytest.approx(500e3)
    assert a <= 0.0


def test_add_rejects_arrays_of_different_lengths_naming_them():
    with pytest.raises(ClockSyncError, match="src_us"):
        ClockSync().add(np.arange(3), np.arange(4))


def test_mapping_before_any_fit_is_a_clear_error():
    with pytest.raises(ClockSyncError, match="no clock fit yet"):
        ClockSync(name="sensor").to_host_ns(np.arange(3))


@settings(max_examples=50, deadline=None)
@given(start=st.integers(2**32 - 5000, 2**32 - 1), chunk=st.integers(1, 50))
def test_counter_unwrapper_is_monotonic_across_the_32bit_wrap(start, chunk):
    true_ms = start + np.arange(0, 10_000, 5, dtype=np.int64)
    counter = (true_ms % 2**32).astype(np.uint32)
    u = CounterUnwrapper()
    out = np.concatenate([u.unwrap(counter[i : i + chunk]) for i in range(0, len(counter), chunk)])
    np.testing.assert_array_equal(out, true_ms)


def test_counter_unwrapper_rejects_values_outside_32_bits():
    with pytest.raises(ClockSyncError, match="32-bit"):
        CounterUnwrapper().unwrap(np.array([2**32], dtype=np.int64))


def test_frame_timeline_recovers_sub_millisecond_times_from_a_1ms_counter():
    rate_hz = 199.37  # not commensurate with 1 ms, so the counter's truncation phase varies
    f = np.arange(4000)
    t_us = 123_456.7 + f * 1e6 / rate_hz
    counter_mid_us = (np.floor(t_us / 1000) * 1000 + 500).astype(np.int64)
    tl = FrameTimeline(window=4000)
    est = np.concatenate([tl.times_us(f[i : i + 20], counter_mid_us[i : i + 20]) for i in range(0, 4000, 20)])
    late = slice(2000, None)  # once the window holds enough frames
    assert np.max(np.abs(est[late] - t_us[late])) < 60.0  # us, versus 500 us from the counter alone
    assert np.max(np.abs(counter_mid_us - t_us)) > 400.0
