"""assemble_batch never lets a point far outside any cell through as a valid measurement."""

from __future__ import annotations

import numpy as np

from cellctl.acquisition.assembly import MAX_ABS_MM, assemble_batch


def _batch(sensor_x_mm: float):
    n, w = 4, 5
    T = np.zeros((2, 3, 4))
    T[:, :3, :3] = np.eye(3)
    T[:, 0, 3] = sensor_x_mm
    return assemble_batch(
        x_mm=np.tile(np.linspace(-2, 2, w, dtype=np.float32), (n, 1)),
        z_mm=np.full((n, w), 100.0, np.float32),
        valid=np.ones((n, w), bool),
        frame_index=np.arange(n),
        t_ns=np.linspace(1_000_000, 3_000_000, n).astype(np.int64),
        sample_t_ns=np.array([0, 4_000_000], np.int64),
        sample_T_base_sensor=T,
        epoch_ns=0,
        pass_id=np.zeros(n, np.int32),
        first_profile_index=0,
    )


def test_points_in_the_cell_stay_valid():
    b = _batch(1500.0)
    assert b.valid.all()
    assert np.allclose(b.xyz_mm[..., 0].mean(), 1500.0, atol=1e-3)


def test_absurd_points_are_invalid_and_nan():
    b = _batch(10 * MAX_ABS_MM)  # a corrupted pose: 1 km from the base
    assert not b.valid.any()
    assert np.isnan(b.xyz_mm).all()
