"""Sensor pose at every profile's exposure time, from the *measured* joints.

Joint-space linear interpolation between the two feedback samples that bracket each time, then the
vectorised forward kinematics (:func:`drivers.abb_egm.kinematics.fk_batch`) and the hand-eye
transform ``T_flange_sensor`` (``[robot.sensor_in_flange]`` of cell.toml). Joint-space interpolation
is exact for the controller's own interpolation at the 4 ms sample rate to well below a micrometre
on smooth scan motions (section 3.4 of line-laser-and-sync.md), and it needs no quaternion care.
Where EGM packets were lost (an interval over 1.5 cycles) a cubic Hermite with the slopes of the
intervals beside the gap bridges it; gaps over ``max_gap_ns`` give no pose.

Times are int64 host nanoseconds; they are turned into float seconds relative to a fixed
``epoch_ns`` (the job's), never relative to the slice of history at hand, so the same sample pair
gives the same bits whether it was interpolated live or when the raw files are replayed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from analysis.contracts.placement import T_from_pos_rpy
from drivers.abb_egm.kinematics import fk_batch

__all__ = [
    "PoseTimeError",
    "SensorPoses",
    "T_from_pos_rpy",
    "interpolate_joints",
    "interpolate_poses",
    "pos_rpy_from_T",
    "sensor_poses",
    "transform_profiles",
    "transform_profiles_within",
]


class PoseTimeError(ValueError):
    """Interpolation input is unusable: unsorted or too short history, wrong shapes."""


def pos_rpy_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`T_from_pos_rpy`: ``(pos_mm (3,), rpy_deg (3,))``."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)


#: intervals between feedback samples longer than this (1.5 controller cycles) are lost packets
CUBIC_GAP_NS = 6_000_000


def interpolate_joints(
    sample_t_ns: np.ndarray,
    sample_q_deg: np.ndarray,
    t_ns: np.ndarray,
    epoch_ns: int,
    max_gap_ns: int | None = None,
    cubic_gap_ns: int | None = CUBIC_GAP_NS,
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolation of joint samples at many times: linear between neighbouring samples, cubic
    Hermite across a gap (lost feedback packets).

    Args:
        sample_t_ns: (m,) int64 strictly increasing sample times, host ns.
        sample_q_deg: (m, 6) measured joints, deg.
        t_ns: (n,) int64 query times, host ns.
        epoch_ns: fixed time origin for the float arithmetic (the job's start).
        max_gap_ns: bracketing samples further apart than this (lost feedback) give no valid pose.
        cubic_gap_ns: bracketing samples further apart than this are bridged by a cubic Hermite
            whose end slopes are those of the sample intervals beside the gap (when those are not
            gaps themselves): a 50 ms burst of lost packets during an acceleration is off by
            ``a h^2 / 8`` linearly (0.6 mm at 2 m/s^2), well under a micrometre this way for a
            smooth motion. None: linear everywhere.

    Returns:
        ``(q_deg (n, 6), inside (n,) bool)``; outside the sample span the nearest sample is held and
        ``inside`` is False; so it is inside a gap longer than ``max_gap_ns``.
    """
    ts = np.asarray(sample_t_ns, dtype=np.int64)
    q = np.asarray(sample_q_deg, dtype=np.float64)
    t = np.asarray(t_ns, dtype=np.int64)
    if ts.ndim != 1 or q.ndim != 2 or q.shape[0] != ts.shape[0]:
        raise PoseTimeError(f"sample_t_ns {ts.shape} and sample values {q.shape} must be (m,) and (m, k)")
    if ts.shape[0] < 2:
        raise PoseTimeError(f"need at least 2 joint samples, have {ts.shape[0]}")
    if np.any(np.diff(ts) <= 0):
        raise PoseTimeError("sample_t_ns must be strictly increasing")
    i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.shape[0] - 2)
    t0 = (ts[i] - epoch_ns).astype(np.float64)
    t1 = (ts[i + 1] - epoch_ns).astype(np.float64)
    tf = (t - epoch_ns).astype(np.float64)
    w = np.clip((tf - t0) / (t1 - t0), 0.0, 1.0)[:, None]
    inside = (t >= ts[0]) & (t <= ts[-1])
    gap_ns = ts[i + 1] - ts[i]
    if max_gap_ns is not None:
        inside &= gap_ns <= max_gap_ns
    out = q[i] + (q[i + 1] - q[i]) * w
    if cubic_gap_ns is not None:
        _bridge_gaps(out, ts, q, i, w[:, 0], gap_ns > cubic_gap_ns, cubic_gap_ns)
    return out, inside


def _bridge_gaps(
    out: np.ndarray,
    ts: np.ndarray,
    q: np.ndarray,
    i: np.ndarray,
    w: np.ndarray,
    gap: np.ndarray,
    short_ns: int,
) -> None:
    """Replace, in place, the linear values of the queries inside gaps by a cubic Hermite whose end
    slopes come from the (short) sample intervals on each side; a side without one keeps the chord."""
    if not gap.any():
        return
    m = ts.shape[0]
    k = np.nonzero(gap)[0]
    a, b = i[k], i[k] + 1
    h = (ts[b] - ts[a]).astype(np.float64)
    chord = (q[b] - q[a]) / h[:, None]
    slope_a, slope_b = chord.copy(), chord.copy()
    has_a = a >= 1
    has_a[has_a] &= (ts[a[has_a]] - ts[a[has_a] - 1]) <= short_ns
    has_b = b + 1 < m
    has_b[has_b] &= (ts[b[has_b] + 1] - ts[b[has_b]]) <= short_ns
    if has_a.any():
        aa = a[has_a]
        slope_a[has_a] = (q[aa] - q[aa - 1]) / (ts[aa] - ts[aa - 1]).astype(np.float64)[:, None]
    if has_b.any():
        bb = b[has_b]
        slope_b[has_b] = (q[bb + 1] - q[bb]) / (ts[bb + 1] - ts[bb]).astype(np.float64)[:, None]
    s = w[k][:, None]
    s2, s3 = s * s, s * s * s
    h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
    out[k] = h00 * q[a] + h10 * (h[:, None] * slope_a) + h01 * q[b] + h11 * (h[:, None] * slope_b)


@dataclass(frozen=True, slots=True)
class SensorPoses:
    """Sensor poses at ``n`` profile times.

    Attributes:
        T_base_sensor: (n, 4, 4) sensor frame -> robot base frame, mm.
        q_deg: (n, 6) interpolated measured joints, deg.
        inside: (n,) bool, False where the time lies outside the joint history (pose is held, not valid).
    """

    T_base_sensor: np.ndarray
    q_deg: np.ndarray
    inside: np.ndarray


def sensor_poses(
    sample_t_ns: np.ndarray,
    sample_q_deg: np.ndarray,
    t_ns: np.ndarray,
    T_flange_sensor: np.ndarray,
    epoch_ns: int,
) -> SensorPoses:
    """Sensor pose at each time: joint interpolation, forward kinematics, hand-eye.

    Args:
        sample_t_ns: (m,) int64 joint sample times on the host time base, ns.
        sample_q_deg: (m, 6) measured joints, deg.
        t_ns: (n,) int64 profile exposure times on the host time base, ns.
        T_flange_sensor: (4, 4) sensor frame in the flange frame, mm.
        epoch_ns: fixed float origin (see :func:`interpolate_joints`).
    """
    q, inside = interpolate_joints(sample_t_ns, sample_q_deg, t_ns, epoch_ns)
    return SensorPoses(T_base_sensor=fk_batch(q, T_flange_sensor), q_deg=q, inside=inside)


def interpolate_poses(
    sample_t_ns: np.ndarray,
    sample_T: np.ndarray,
    t_ns: np.ndarray,
    epoch_ns: int,
    max_gap_ns: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Blend the sensor poses of the two samples bracketing each time (the ingestion fast path).

    The poses come from the measured joints through the forward kinematics once per sample (250 Hz),
    not once per profile. Between samples 4 ms apart the rotation changes by well under a
    milliradian, so the element-wise blend of the two matrices differs from joint-space interpolation
    followed by FK (:func:`sensor_poses`) by far less than a micrometre at the profile
    (``tests/acquisition/test_poses.py`` checks this).

    Args:
        sample_t_ns: (m,) int64 strictly increasing sample times, host ns.
        sample_T: (m, 3, 4) ``T_base_sensor`` rows of each sample, mm.
        t_ns: (n,) int64 query times, host ns.
        epoch_ns: fixed float origin (see :func:`interpolate_joints`).
        max_gap_ns: see :func:`interpolate_joints`.

    Returns:
        ``(T (n, 3, 4), inside (n,) bool)``.
    """
    m = sample_T.shape[0]
    T, inside = interpolate_joints(sample_t_ns, sample_T.reshape(m, 12), t_ns, epoch_ns, max_gap_ns)
    return T.reshape(-1, 3, 4), inside


def transform_profiles(T_base_sensor: np.ndarray, x_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Profile points (sensor x-z plane) into the base frame.

    Args:
        T_base_sensor: (n, 4, 4) or (n, 3, 4) pose per profile, mm.
        x_mm: (n, w) x across the line, mm.
        z_mm: (n, w) range along the laser axis, mm (NaN where invalid stays NaN).

    Returns:
        (n, w, 3) float32 base-frame points, mm. The arithmetic is float32 per axis (the hot path of
        ingestion): rounding stays below 0.3 um for a 2.5 m reach, 1 % of the sensor's noise.
    """
    return _transform(T_base_sensor, x_mm, z_mm, None)[0]


def transform_profiles_within(
    T_base_sensor: np.ndarray, x_mm: np.ndarray, z_mm: np.ndarray, max_abs_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`transform_profiles` and, per point, whether every coordinate lies within ``max_abs_mm``.

    Returns:
        ``(xyz_mm (n, w, 3) float32, within (n, w) bool)``: the same points as
        :func:`transform_profiles`, and ``(abs(xyz_mm) < max_abs_mm).all(axis=2)`` (False where a
        coordinate is NaN). The largest ``abs`` is kept while each axis is computed: that reduction
        over the last axis, of length 3, cost four times the transform itself (ingestion fell from
        ~75k to ~45k profiles/s with it; ``benchmarks/ingest.py``).
    """
    xyz, within = _transform(T_base_sensor, x_mm, z_mm, max_abs_mm)
    assert within is not None
    return xyz, within


def _transform(
    T_base_sensor: np.ndarray, x_mm: np.ndarray, z_mm: np.ndarray, max_abs_mm: float | None
) -> tuple[np.ndarray, np.ndarray | None]:
    T = np.asarray(T_base_sensor, dtype=np.float64)
    x = np.asarray(x_mm, dtype=np.float32)
    z = np.asarray(z_mm, dtype=np.float32)
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)) or x.shape != z.shape or x.shape[0] != T.shape[0]:
        raise PoseTimeError(f"T_base_sensor {T.shape}, x_mm {x.shape}, z_mm {z.shape} do not match")
    R = T[:, :3, :3].astype(np.float32)
    t = T[:, :3, 3].astype(np.float32)
    out = np.empty((*x.shape, 3), dtype=np.float32)
    tmp = np.empty(x.shape, dtype=np.float32)
    acc = np.empty(x.shape, dtype=np.float32)
    largest = None if max_abs_mm is None else np.empty(x.shape, dtype=np.float32)
    # y is 0 in the laser plane: p = x * R[:, 0] + z * R[:, 2] + t, one axis at a time on 2-D arrays
    for k in range(3):
        np.multiply(x, R[:, k, 0, None], out=acc)
        np.multiply(z, R[:, k, 2, None], out=tmp)
        acc += tmp
        acc += t[:, k, None]
        out[..., k] = acc
        if largest is not None:  # the largest |coordinate| so far (np.maximum keeps NaN)
            np.abs(acc, out=largest if k == 0 else tmp)
            if k:
                np.maximum(largest, tmp, out=largest)
    return out, None if largest is None else largest < max_abs_mm
