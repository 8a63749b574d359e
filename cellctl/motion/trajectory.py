"""The timed joint trajectory the executor streams: samples and their quintic Hermite interpolation.

The planner (:mod:`cellctl.planning.timing`) makes one; the executor (:mod:`cellctl.motion.executor`)
samples it every EGM cycle. It lives with motion, the lower floor, so that planning imports motion
(the trajectory and the safety envelope it checks a plan against) and motion imports nothing of
planning.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

__all__ = ["PLAN_JERK_SHARE", "TimedTrajectory"]

#: the share of the joint jerk limits a plan's time law may use (:mod:`cellctl.planning.timing`);
#: the executor's pause / resume / abort ramps of the playback rate keep the rest, so a stop
#: anywhere on a plan keeps the limits (:meth:`cellctl.motion.executor.MotionExecutor._rate_limits_at`)
PLAN_JERK_SHARE = 0.8


@dataclass
class TimedTrajectory:
    """The timed joint trajectory, sampled: ``t_s`` (m,) s from the start, ``q_deg`` (m, 6) deg,
    ``qd_deg_s`` (m, 6) deg/s, ``qdd_deg_s2`` (m, 6) deg/s^2, ``segment`` (m,) int index into the plan's
    segments. Between samples the executor interpolates with quintic Hermite polynomials."""

    t_s: np.ndarray
    q_deg: np.ndarray
    qd_deg_s: np.ndarray
    qdd_deg_s2: np.ndarray
    segment: np.ndarray

    def __post_init__(self) -> None:
        # a plain list makes the per-cycle lookup (bisect) cheap; the arrays stay the data
        self._t_list: list[float] = np.asarray(self.t_s, dtype=np.float64).tolist()

    @property
    def duration_s(self) -> float:
        """Total duration, s."""
        return float(self.t_s[-1]) if self.t_s.size else 0.0

    def sample_many(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised :meth:`sample`: times (m,) s -> ``q_deg`` (m, 6), ``qd_deg_s`` (m, 6),
        ``qdd_deg_s2`` (m, 6), segment (m,) int."""
        t = np.clip(np.asarray(t_s, dtype=np.float64), self.t_s[0], self.t_s[-1])
        i = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, self.t_s.size - 2)
        h = self.t_s[i + 1] - self.t_s[i]
        hs = np.where(h > 0, h, 1.0)
        u = np.where(h > 0, (t - self.t_s[i]) / hs, 0.0)[:, None]
        q, qd, qdd = _quintic_hermite(
            u, hs[:, None], self.q_deg[i], self.q_deg[i + 1], self.qd_deg_s[i], self.qd_deg_s[i + 1],
            self.qdd_deg_s2[i], self.qdd_deg_s2[i + 1],
        )  # fmt: skip
        seg = np.where(u[:, 0] < 1.0, self.segment[i], self.segment[i + 1])
        return q, qd, qdd, seg

    def sample(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """State at time ``t_s`` (clamped to the trajectory): ``(q_deg (6,), qd_deg_s (6,),
        qdd_deg_s2 (6,), segment index)``.

        Quintic Hermite interpolation between the samples (position, velocity and acceleration at
        both ends), so the interpolated trajectory is continuous in acceleration and its jerk stays
        bounded: a jerk-limited tracker can follow it without lag.
        """
        ts = self._t_list
        t = min(max(float(t_s), ts[0]), ts[-1])
        i = min(max(bisect.bisect_right(ts, t) - 1, 0), len(ts) - 2)
        t0, t1 = ts[i], ts[i + 1]
        h = t1 - t0
        if h <= 0:
            return (
                self.q_deg[i].copy(),
                self.qd_deg_s[i].copy(),
                self.qdd_deg_s2[i].copy(),
                int(self.segment[i]),
            )
        u = (t - t0) / h
        q, qd, qdd = _quintic_hermite(
            u, h, self.q_deg[i], self.q_deg[i + 1], self.qd_deg_s[i], self.qd_deg_s[i + 1],
            self.qdd_deg_s2[i], self.qdd_deg_s2[i + 1],
        )  # fmt: skip
        seg = int(self.segment[i] if u < 1.0 else self.segment[i + 1])
        return q, qd, qdd, seg


def _quintic_hermite(u, h, p0, p1, qd0, qd1, qdd0, qdd1):
    """Quintic Hermite between two samples h seconds apart at u in [0, 1] (scalar or broadcast
    arrays): position, velocity and acceleration at both ends in; (q, qd, qdd) out."""
    v0, v1 = qd0 * h, qd1 * h
    a0, a1 = qdd0 * (h * h), qdd1 * (h * h)
    u2, u3, u4, u5 = u * u, u**3, u**4, u**5
    q = (
        (1 - 10 * u3 + 15 * u4 - 6 * u5) * p0
        + (u - 6 * u3 + 8 * u4 - 3 * u5) * v0
        + (0.5 * u2 - 1.5 * u3 + 1.5 * u4 - 0.5 * u5) * a0
        + (0.5 * u3 - u4 + 0.5 * u5) * a1
        + (-4 * u3 + 7 * u4 - 3 * u5) * v1
        + (10 * u3 - 15 * u4 + 6 * u5) * p1
    )
    qd = (
        (-30 * u2 + 60 * u3 - 30 * u4) * (p0 - p1)
        + (1 - 18 * u2 + 32 * u3 - 15 * u4) * v0
        + (u - 4.5 * u2 + 6 * u3 - 2.5 * u4) * a0
        + (1.5 * u2 - 4 * u3 + 2.5 * u4) * a1
        + (-12 * u2 + 28 * u3 - 15 * u4) * v1
    ) / h
    qdd = (
        (-60 * u + 180 * u2 - 120 * u3) * (p0 - p1)
        + (-36 * u + 96 * u2 - 60 * u3) * v0
        + (1 - 9 * u + 18 * u2 - 10 * u3) * a0
        + (3 * u - 12 * u2 + 10 * u3) * a1
        + (-24 * u + 84 * u2 - 60 * u3) * v1
    ) / (h * h)
    return q, qd, qdd
