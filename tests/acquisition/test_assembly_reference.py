"""The vectorised assembly (the ingestion hot path) against a straightforward per-point reference.

The reference walks profile by profile and point by point with plain Python arithmetic: bracketing
samples by bisection, linear blend of the sample poses (cubic Hermite across a lost-packet gap, no
pose across a gap over the limit), ``p = R (x, 0, z) + t``, and the 100 m guard. The optimised path
must give the same validity bit for bit, the same points to float32 rounding, and exactly the float32
arithmetic it documents (``x * R[:, 0] + z * R[:, 2] + t`` per axis).
"""

from __future__ import annotations

import bisect
import math

import numpy as np
import pytest

from cellctl.acquisition.assembly import MAX_ABS_MM, assemble_batch
from cellctl.acquisition.poses import CUBIC_GAP_NS, transform_profiles, transform_profiles_within
from drivers.abb_egm.kinematics import fk_batch
from tests.support.synthetic_scan import T_FLANGE_SENSOR, q_true_deg

EPOCH = 1_000_000_000_000
MAX_GAP_NS = 30_000_000


def _inputs(seed: int):
    """Robot samples every 4 ms with a 20 ms gap (bridged) and a 40 ms gap (no pose); profiles
    spanning both and the ends of the history; a few invalid, huge and infinite returns."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(0.0, 0.3, 0.004)
    keep = np.ones(len(t_s), bool)
    keep[20:24] = False  # 20 ms without feedback: bridged by the cubic
    keep[50:59] = False  # 40 ms: over MAX_GAP_NS, no pose
    t_s = t_s[keep]
    sample_t = EPOCH + np.rint(t_s * 1e9).astype(np.int64) + rng.integers(-200_000, 200_000, len(t_s))
    T = fk_batch(q_true_deg(t_s, amp_deg=20.0, period_s=0.5), T_FLANGE_SENSOR)[:, :3, :]
    n, w = 40, 9
    t_ns = np.sort(EPOCH + rng.integers(-5_000_000, 305_000_000, n)).astype(np.int64)
    x = np.broadcast_to(np.linspace(-25, 25, w, dtype=np.float32), (n, w))
    z = rng.uniform(70, 130, (n, w)).astype(np.float32)
    valid = rng.random((n, w)) > 0.15
    z[~valid] = np.nan
    z[3, 2], z[7, 5], z[11, 0] = 1e30, np.inf, 3e5  # corrupted returns: far beyond the guard
    valid[[3, 7, 11], [2, 5, 0]] = True
    return sample_t, T, t_ns, x, z, valid


def _reference(sample_t, T, t_ns, x, z, valid):
    ts = [int(v) for v in sample_t]
    m = len(ts)
    n, w = x.shape
    xyz = np.full((n, w, 3), np.nan)
    ok = np.zeros((n, w), bool)
    sensor = np.full((n, 3), np.nan)
    for r in range(n):
        t = int(t_ns[r])
        i = min(max(bisect.bisect_right(ts, t) - 1, 0), m - 2)
        a, b = i, i + 1
        h = ts[b] - ts[a]
        s = min(max((t - ts[a]) / h, 0.0), 1.0)
        if ts[0] <= t <= ts[-1] and h > MAX_GAP_NS:
            continue
        if not ts[0] <= t <= ts[-1]:
            continue
        pose = np.empty((3, 4))
        for e in range(12):
            qa, qb = T[a].flat[e], T[b].flat[e]
            v = qa + (qb - qa) * s
            if h > CUBIC_GAP_NS:
                chord = (qb - qa) / h
                ma = (
                    (qa - T[a - 1].flat[e]) / (ts[a] - ts[a - 1])
                    if a >= 1 and ts[a] - ts[a - 1] <= CUBIC_GAP_NS
                    else chord
                )
                mb = (
                    (T[b + 1].flat[e] - qb) / (ts[b + 1] - ts[b])
                    if b + 1 < m and ts[b + 1] - ts[b] <= CUBIC_GAP_NS
                    else chord
                )
                v = (
                    (2 * s**3 - 3 * s**2 + 1) * qa
                    + (s**3 - 2 * s**2 + s) * h * ma
                    + (-2 * s**3 + 3 * s**2) * qb
                    + (s**3 - s**2) * h * mb
                )
            pose.flat[e] = v
        sensor[r] = pose[:, 3]
        for c in range(w):
            if not valid[r, c]:
                continue
            p = [pose[k, 0] * float(x[r, c]) + pose[k, 2] * float(z[r, c]) + pose[k, 3] for k in range(3)]
            if all(abs(v) < MAX_ABS_MM for v in p):  # False for inf and NaN
                xyz[r, c] = p
                ok[r, c] = True
    return xyz, ok, sensor


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_assembly_matches_the_per_point_reference(seed):
    sample_t, T, t_ns, x, z, valid = _inputs(seed)
    got = assemble_batch(
        x_mm=x, z_mm=z, valid=valid, frame_index=np.arange(len(t_ns)), t_ns=t_ns,
        sample_t_ns=sample_t, sample_T_base_sensor=T, epoch_ns=EPOCH,
        pass_id=np.zeros(len(t_ns), np.int32), first_profile_index=5, max_gap_ns=MAX_GAP_NS,
    )  # fmt: skip
    want_xyz, want_ok, want_sensor = _reference(sample_t, T, t_ns, x, z, valid)
    # the input exercises every branch: bridged gap, gap without pose, outside the history, guard
    assert (~want_ok.any(axis=1)).sum() >= 3 and want_ok.sum() > 200
    assert not want_ok[3, 2] and not want_ok[7, 5] and not want_ok[11, 0]
    np.testing.assert_array_equal(got.valid, want_ok)
    assert np.array_equal(np.isnan(got.xyz_mm), ~want_ok[..., None].repeat(3, axis=2))
    np.testing.assert_allclose(got.xyz_mm[want_ok], want_xyz[want_ok], rtol=0, atol=5e-4)  # float32
    np.testing.assert_allclose(got.sensor_pos_mm, want_sensor, rtol=0, atol=5e-4)
    assert np.array_equal(np.isnan(got.sensor_pos_mm), np.isnan(want_sensor))
    assert got.profile_index.tolist() == list(range(5, 5 + len(t_ns)))


def test_transform_is_the_documented_float32_arithmetic_and_the_guard_is_strict():
    rng = np.random.default_rng(3)
    n, w = 6, 11
    T = fk_batch(q_true_deg(rng.uniform(0, 5, n)), T_FLANGE_SENSOR)
    T[0, :3, :3] = np.eye(3)
    T[0, 0, 3] = MAX_ABS_MM - 2.0  # this profile straddles the limit in x, one point exactly on it
    x = rng.uniform(-25, 25, (n, w)).astype(np.float32)
    x[0, :3] = [1.0, 2.0, 3.0]
    z = rng.uniform(70, 130, (n, w)).astype(np.float32)
    z[1, 3], z[2, 4] = np.nan, np.inf
    T[5, 1, 3] = np.nan  # a pose with one NaN coordinate: the others stay finite
    xyz, within = transform_profiles_within(T, x, z, MAX_ABS_MM)
    R, t = T[:, :3, :3].astype(np.float32), T[:, :3, 3].astype(np.float32)
    for r in range(n):
        for c in range(w):
            p = [x[r, c] * R[r, k, 0] + z[r, c] * R[r, k, 2] + t[r, k] for k in range(3)]  # float32 scalars
            assert all(isinstance(v, np.float32) for v in p)
            assert np.array_equal(xyz[r, c], np.array(p, np.float32), equal_nan=True), (r, c)
            assert within[r, c] == all(abs(float(v)) < MAX_ABS_MM for v in p), (r, c)
    assert xyz[0, 1, 0] == MAX_ABS_MM and not within[0, 1] and within[0, 0]  # strictly below only
    assert not within[1, 3] and not within[2, 4] and math.isnan(xyz[1, 3, 0])
    assert not within[5].any() and np.isfinite(xyz[5, :, 0]).all()
    np.testing.assert_array_equal(transform_profiles(T, x, z), xyz)
