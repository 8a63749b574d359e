"""The ProfileBatch type and the ProfileSource bookkeeping shared by every source."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.laser.client import HD8Client
from drivers.laser.source import ProfileBatch, SourceEventKind, SourceStats


def batch(first: int, n: int, w: int = 4) -> ProfileBatch:
    return ProfileBatch(
        frame_index=np.arange(first, first + n, dtype=np.uint64),
        sensor_time_us=np.arange(n, dtype=np.uint64),
        hd8_ms=np.zeros(n, np.uint32),
        encoder=np.zeros(n, np.int64),
        status=np.zeros(n, np.uint32),
        exposure_ns=np.zeros(n, np.uint32),
        x_mm=np.zeros((n, w), np.float32),
        z_mm=np.zeros((n, w), np.float32),
        valid=np.ones((n, w), bool),
        host_recv_ns=np.zeros(n, np.int64),
    )


def test_batch_rejects_arrays_of_mismatched_length_naming_the_field() -> None:
    b = batch(0, 3)
    with pytest.raises(ValueError, match="hd8_ms"):
        ProfileBatch(**{**b.__dict__, "hd8_ms": np.zeros(2, np.uint32)})
    with pytest.raises(ValueError, match="valid"):
        ProfileBatch(**{**b.__dict__, "valid": np.ones((3, 5), bool)})


def test_batch_concat_and_select_keep_rows_together() -> None:
    c = ProfileBatch.concat([batch(0, 2), batch(5, 3)])
    assert len(c) == 5 and c.width == 4 and c.n_points == 20
    s = c.select(c.frame_index > 1)
    assert s.frame_index.tolist() == [5, 6, 7] and s.x_mm.shape == (3, 4)
    with pytest.raises(ValueError, match="widths"):
        ProfileBatch.concat([batch(0, 1, w=4), batch(1, 1, w=5)])


def test_stats_rate_is_measured_over_a_one_second_window() -> None:
    st = SourceStats()
    st.count_frames(10, now_ns=1_000_000_000)
    for k in range(1, 11):
        st.count_frames(20, now_ns=1_000_000_000 + k * 100_000_000)
    assert st.rate_hz == pytest.approx(210.0)
    assert "rate_hz" in st.as_dict() and "_window_frames" not in st.as_dict()


def test_event_queue_keeps_the_newest_events_when_nobody_reads() -> None:
    src = HD8Client()
    seen = []
    src.add_listener(seen.append)
    for k in range(300):
        src._emit(SourceEventKind.GAP, k=k)
    assert src.events.qsize() == 256
    assert src.events.get_nowait().detail["k"] == 300 - 256
    assert len(seen) == 300
