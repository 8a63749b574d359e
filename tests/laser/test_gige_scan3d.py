"""The GigE Vision codec: range rows <-> profiles, row stamps, block-id unwrapping (no device)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.laser.gige.scan3d import (
    BlockIdUnwrapper,
    RangeLayout,
    profiles_to_rows,
    row_times_us,
    rows_to_profiles,
)

LAYOUT = RangeLayout(
    width=4, a_scale_mm=0.1, a_offset_mm=-0.15, c_scale_mm=0.002, c_offset_mm=70.0, invalid_value=0,
    line_rate_hz=1000.0,
)  # fmt: skip


def test_rows_convert_with_the_devices_scale_and_offset_and_invalid_value():
    raw = np.array([[0, 1, 5000, 65535], [10, 0, 20, 30]], dtype=np.uint16)
    x, z, valid = rows_to_profiles(raw, LAYOUT)
    np.testing.assert_allclose(x[0], [-0.15, -0.05, 0.05, 0.15], atol=1e-6)
    assert valid.tolist() == [[False, True, True, True], [True, False, True, True]]
    assert np.isnan(z[0, 0]) and np.isnan(z[1, 1])
    np.testing.assert_allclose(z[0, 1:], [70.002, 80.0, 70.0 + 65535 * 0.002], rtol=1e-6)


def test_profiles_round_trip_through_rows_within_half_a_code():
    rng = np.random.default_rng(1)
    z = rng.uniform(71.0, 130.0, (50, 4))
    valid = rng.random((50, 4)) > 0.1
    raw = profiles_to_rows(z, valid, LAYOUT)
    _, z2, v2 = rows_to_profiles(raw, LAYOUT)
    assert (v2 == valid).all()
    assert np.nanmax(np.abs(z2 - z)[valid]) <= 0.001 + 1e-5


def test_points_outside_the_code_range_become_invalid_not_clipped():
    z = np.array([[60.0, 70.0, 70.0 + 70000 * 0.002, np.nan]])
    raw = profiles_to_rows(z, np.ones_like(z, dtype=bool), LAYOUT)
    assert raw.tolist() == [[0, 0, 0, 0]]  # 70.0 is code 0, the invalid value itself


def test_rows_are_stamped_one_line_period_apart_from_the_buffer_stamp():
    t = row_times_us(5_000_000_000, 3, LAYOUT)  # ns ticks
    assert t.tolist() == [5_000_000, 5_001_000, 5_002_000]


def test_wrong_row_width_is_refused():
    with pytest.raises(ValueError, match=r"expected \(n, 4\)"):
        rows_to_profiles(np.zeros((2, 5), np.uint16), LAYOUT)


def test_gev1_block_ids_unwrap_across_65535_skipping_zero():
    u = BlockIdUnwrapper()
    assert [u.push(i) for i in (65533, 65534, 65535, 1, 2, 4)] == [0, 1, 2, 3, 4, 6]


def test_a_repeated_or_late_block_id_does_not_count_as_65000_ahead():
    u = BlockIdUnwrapper()
    assert [u.push(i) for i in (10, 11, 11, 9, 12)] == [0, 1, 1, -1, 2]


def test_64_bit_block_ids_are_taken_as_they_are():
    u = BlockIdUnwrapper()
    assert [u.push(i) for i in (70_000, 70_001, 70_010)] == [0, 1, 10]
