"""The platform probe (benchmarks/platform_latency.py): the floor egm_latency and end_to_end set
their stale cycles against."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.platform_latency import in_stalls, start_probes, stop_probes

_interval = st.tuples(st.integers(0, 10_000), st.integers(0, 3_000)).map(lambda t: (t[0], t[0] + t[1]))


@settings(max_examples=300, deadline=None)
@given(st.lists(_interval, max_size=12), st.lists(_interval, max_size=12))
def test_a_window_is_in_a_stall_exactly_when_they_overlap(windows, stalls):
    got = in_stalls(np.array(windows, dtype=np.int64).reshape(-1, 2), stalls)
    want = [any(a <= w1 and b >= w0 for a, b in stalls) for w0, w1 in windows]
    assert got.tolist() == want


@pytest.mark.process
def test_the_probes_wake_every_period_and_report_each_cpu():
    procs = start_probes([0], period_us=1000)
    try:
        time.sleep(1.0)  # stays: the probes measure for a second (a measurement's duration)
    finally:
        result = stop_probes(procs)
    (cpu,) = result["per_cpu"]
    assert cpu["cpu"] == 0
    # one wake-up per millisecond, less what a stall skipped; every wake-up in the histogram
    assert cpu["seconds"] > 0.2
    assert 0.5 * cpu["seconds"] * 1000 <= result["wakeups"] <= cpu["seconds"] * 1000 + 2
    assert result["late_p50_us"] is not None and result["late_p50_us"] <= result["late_max_us"] + 10
    assert result["over_cycle"] == len(result["stalls"])
    for deadline, woke in result["stalls"]:
        assert woke - deadline > 4_032_000
