"""The safety envelope: the last check every commanded joint set-point passes before it is sent.

Four rules, from ``cell.toml [robot]``: joint limits shrunk by the margin, a workspace box for the
sensor (the cell's TCP), a TCP speed cap, and a maximum joint step per EGM cycle (the joint speed
limits times the cycle). A violation raises :class:`EnvelopeViolation`; the envelope never clamps a
set-point into range, because a silently altered reference hides the fault that produced it. The
executor answers a violation with a smooth stop.

With a linear track (``EnvelopeLimits.track``) a set-point is ``axes_mm_deg`` (7,): the track
position in mm first, then the six joints. The track is checked like the joints: its travel
(``track_travel``), its speed as the step per cycle (``track_speed``) and its acceleration as the
change of that step (``track_accel``); the workspace box stays in the base frame (it rides with the
carriage), and the TCP speed cap applies in the world frame, the track's motion included.

The same rules check a whole planned trajectory at once (:meth:`SafetyEnvelope.check_trajectory`),
vectorised over its samples, so a plan that would trip the envelope is refused before it runs. A
whole trajectory is also held to the joints' acceleration limits (``joint_accel``, from second
differences of its samples at the EGM cycle, as the track's): a plan, or a cached plan edited on
disk, whose accelerations the arm cannot follow is refused before anything moves. (Single
set-points come from the executor's own jerk-limited generators, inside the same limits.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.abb_egm.kinematics import RobotKinematics, fk_batch
from drivers.abb_egm.limits import EGM_CYCLE_S, JOINT_NAMES, N_ARM_JOINTS, LinearTrack

__all__ = ["EnvelopeLimits", "EnvelopeViolation", "SafetyEnvelope"]

#: a set-point may exceed a speed limit by this fraction before it is a violation (rounding, not slack)
_SPEED_TOLERANCE = 1e-3
#: the same for the track's acceleration, from second differences of the set-points: a jerk-limited
#: profile sampled at the EGM cycle differs from its continuous acceleration by ~jerk x cycle
_ACCEL_TOLERANCE = 2e-2


class EnvelopeViolation(Exception):
    """A set-point outside the envelope.

    Attributes:
        rule: ``"joint_limit"``, ``"workspace"``, ``"tcp_speed"``, ``"joint_step"``, ``"joint_accel"``,
            ``"track_travel"``, ``"track_speed"``, ``"track_accel"`` or ``"input"``.
        joint: 0-based arm joint index (joint rules) or None.
        value: the offending value (deg, mm, mm/s, deg/s^2, mm/s^2 or deg per step).
        limit: the limit it broke, same unit.
        sample: index into a checked trajectory, or None for a single set-point.
    """

    def __init__(
        self, rule: str, message: str, *, joint: int | None = None, value: float = float("nan"),
        limit: float = float("nan"), sample: int | None = None,
    ) -> None:  # fmt: skip
        self.rule = rule
        self.joint = joint
        self.value = float(value)
        self.limit = float(limit)
        self.sample = sample
        super().__init__(message + (f" (sample {sample})" if sample is not None else ""))


@dataclass(frozen=True)
class EnvelopeLimits:
    """The envelope's numbers.

    q_min_deg / q_max_deg: (6,) usable joint range (hard limits already shrunk by the margin), deg.
    workspace_min_mm / workspace_max_mm: (3,) box for the sensor origin, base frame, mm.
    tcp_speed_max_mm_s: cap on the sensor origin's speed, mm/s.
    joint_speed_max_deg_s: (6,) joint speed limits; the step per cycle is this times ``cycle_s``.
    cycle_s: EGM cycle, s.
    T_flange_tcp: (4, 4) flange -> TCP (sensor) transform, mm.
    track: the linear track (usable travel, speed and acceleration limits), or None for a fixed base.
    joint_accel_max_deg_s2: (6,) joint acceleration limits a whole trajectory is checked against, or
        None (not checked).
    """

    q_min_deg: np.ndarray
    q_max_deg: np.ndarray
    workspace_min_mm: np.ndarray
    workspace_max_mm: np.ndarray
    tcp_speed_max_mm_s: float
    joint_speed_max_deg_s: np.ndarray
    cycle_s: float
    T_flange_tcp: np.ndarray
    track: LinearTrack | None = None
    joint_accel_max_deg_s2: np.ndarray | None = None

    @property
    def n_axes(self) -> int:
        """Values in a set-point: 6 joints, or the track and 6 joints."""
        return N_ARM_JOINTS + (self.track is not None)

    def __post_init__(self) -> None:
        for name in ("q_min_deg", "q_max_deg", "joint_speed_max_deg_s"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (6,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"EnvelopeLimits.{name}: expected 6 finite values, got {arr}")
            object.__setattr__(self, name, arr)
        for name in ("workspace_min_mm", "workspace_max_mm"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"EnvelopeLimits.{name}: expected 3 finite values, got {arr}")
            object.__setattr__(self, name, arr)
        if self.joint_accel_max_deg_s2 is not None:
            arr = np.asarray(self.joint_accel_max_deg_s2, dtype=np.float64)
            if arr.shape != (6,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
                raise ValueError(
                    f"EnvelopeLimits.joint_accel_max_deg_s2: expected 6 positive values, got {arr}"
                )
            object.__setattr__(self, "joint_accel_max_deg_s2", arr)
        if np.any(self.q_min_deg >= self.q_max_deg):
            raise ValueError("EnvelopeLimits: q_min_deg must be below q_max_deg on every joint")
        if not (self.cycle_s > 0 and self.tcp_speed_max_mm_s > 0):
            raise ValueError("EnvelopeLimits: cycle_s and tcp_speed_max_mm_s must be positive")
        object.__setattr__(self, "T_flange_tcp", np.asarray(self.T_flange_tcp, dtype=np.float64))

    @classmethod
    def from_settings(cls, settings, cycle_s: float = EGM_CYCLE_S) -> EnvelopeLimits:
        """From :class:`cellctl.planning.PlannerSettings` (which mirrors ``cell.toml [robot]``)."""
        return cls(
            q_min_deg=settings.q_min_deg,
            q_max_deg=settings.q_max_deg,
            workspace_min_mm=np.asarray(settings.workspace_min_mm),
            workspace_max_mm=np.asarray(settings.workspace_max_mm),
            tcp_speed_max_mm_s=settings.tcp_speed_max_mm_s,
            joint_speed_max_deg_s=np.asarray(settings.joint_speed_max_deg_s),
            cycle_s=cycle_s,
            T_flange_tcp=settings.T_flange_sensor,
            track=getattr(settings, "track", None),
            joint_accel_max_deg_s2=np.asarray(settings.joint_accel_max_deg_s2),
        )


class SafetyEnvelope:
    """Checks set-points against :class:`EnvelopeLimits`; keeps the last accepted one for the step rules."""

    def __init__(self, limits: EnvelopeLimits) -> None:
        self.limits = limits
        # pinocchio for single set-points (tens of us); the vectorised numpy FK for whole trajectories
        self._kin = RobotKinematics(tools={"tcp": limits.T_flange_tcp})
        self._n = limits.n_axes
        self._last_q: np.ndarray | None = None
        self._last_p: np.ndarray | None = None
        #: the track's last accepted speed, mm/s, and the time it was measured over, s (the
        #: acceleration rule's memory); at rest after a reset
        self._last_v_track = 0.0
        self._last_dt_track: float | None = None
        self.accepted = 0
        self.violations = 0

    def reset(self, q_deg: np.ndarray | None = None) -> None:
        """Forget the last set-point, or set it to where the robot is at rest (``q_deg`` (6,), or
        ``axes_mm_deg`` (7,) with a track)."""
        self._last_v_track = 0.0
        self._last_dt_track = None
        if q_deg is None:
            self._last_q = self._last_p = None
        else:
            q = np.asarray(q_deg, dtype=np.float64)
            self._last_q = q.copy()
            self._last_p = self.tcp_mm(q)

    @property
    def last_q_deg(self) -> np.ndarray | None:
        """The last accepted set-point (6,) deg, or None."""
        return None if self._last_q is None else self._last_q.copy()

    def tcp_mm(self, q_deg: np.ndarray) -> np.ndarray:
        """TCP (sensor origin) position (3,) mm in the base frame at one configuration ``q_deg`` (6,)
        deg, or ``axes_mm_deg`` (7,) (only the arm's joints place the TCP relative to the base)."""
        return self._kin.fk(np.asarray(q_deg)[-N_ARM_JOINTS:], "tcp").pos_mm

    def _tcp(self, q: np.ndarray) -> np.ndarray:
        """(n, 3) TCP positions in the base frame (the workspace box's frame)."""
        if q.shape[0] == 1:
            return self.tcp_mm(q[0])[None]
        return fk_batch(q[:, -N_ARM_JOINTS:], self.limits.T_flange_tcp)[:, :3, 3]

    def world_mm(self, q: np.ndarray, p_base: np.ndarray) -> np.ndarray:
        """TCP positions in the world frame (the TCP speed cap's frame): the base's, plus the carriage."""
        track = self.limits.track
        return p_base if track is None else p_base + track.base_pos_mm(q[..., 0])

    def check(self, q_deg: np.ndarray, cycles: int = 1) -> np.ndarray:
        """Check one set-point ``q_deg`` (6,) deg (``axes_mm_deg`` (7,) with a track), ``cycles``
        EGM cycles after the last accepted one.

        Returns the TCP position (3,) mm in the base frame. Raises :class:`EnvelopeViolation` (the
        set-point is then not accepted and the last accepted one is kept).
        """
        q = np.asarray(q_deg, dtype=np.float64)
        if q.shape != (self._n,) or not np.all(np.isfinite(q)):
            self.violations += 1
            raise EnvelopeViolation("input", f"set-point must be {self._n} finite values, got {q!r}")
        cycles = max(1, int(cycles))
        lim = self.limits
        track = lim.track
        arm = q[-N_ARM_JOINTS:]
        # fast path (runs every EGM cycle): plain comparisons; the detailed check only to explain a failure
        p = self.tcp_mm(arm)
        ok = bool(np.all(arm >= lim.q_min_deg) and np.all(arm <= lim.q_max_deg))
        ok = ok and bool(np.all(p >= lim.workspace_min_mm) and np.all(p <= lim.workspace_max_mm))
        if track is not None:
            ok = ok and track.travel_min_mm <= q[0] <= track.travel_max_mm
        v_track = 0.0
        if ok and self._last_q is not None:
            dt = cycles * lim.cycle_s
            last_arm = self._last_q[-N_ARM_JOINTS:]
            ok = bool(
                np.all(np.abs(arm - last_arm) <= lim.joint_speed_max_deg_s * dt * (1 + _SPEED_TOLERANCE))
            )
            dp = self.world_mm(q, p) - self.world_mm(self._last_q, self._last_p)
            ok = ok and float(np.linalg.norm(dp)) <= lim.tcp_speed_max_mm_s * dt * (1 + _SPEED_TOLERANCE)
            if track is not None:
                v_track = (q[0] - self._last_q[0]) / dt
                ok = ok and abs(v_track) <= track.speed_max_mm_s * (1 + _SPEED_TOLERANCE)
                # the two speeds are means over their steps: their centres lie half of each apart
                gap = 0.5 * (dt + (self._last_dt_track or dt))
                ok = ok and abs(v_track - self._last_v_track) <= track.accel_max_mm_s2 * gap * (
                    1 + _ACCEL_TOLERANCE
                )
        if not ok:
            self.violations += 1
            self._check_rows(
                q[None],
                self._last_q,
                self._last_p,
                cycles,
                v_prev=self._last_v_track,
                dt_prev=self._last_dt_track,
            )
            raise EnvelopeViolation("input", f"set-point {q.round(4).tolist()} rejected")  # not reached
        if self._last_q is not None:
            self._last_dt_track = cycles * lim.cycle_s
        self._last_q, self._last_p = q.copy(), p
        self._last_v_track = v_track
        self.accepted += 1
        return p

    def check_trajectory(self, t_s: np.ndarray, q_deg: np.ndarray) -> None:
        """Check a sampled trajectory ``q_deg`` (n, 6) (``axes_mm_deg`` (n, 7) with a track) at
        times ``t_s`` (n,) s against every rule.

        Sample it at the EGM cycle first (the executor sends one set-point per cycle): the step and
        speed rules are then exactly the per-cycle rules. The trajectory starts and ends at rest.
        """
        q = np.asarray(q_deg, dtype=np.float64)
        t = np.asarray(t_s, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != self._n or t.shape != (q.shape[0],):
            raise EnvelopeViolation(
                "input", f"expected t_s (n,) and q_deg (n, {self._n}), got {t.shape} and {q.shape}"
            )
        if not np.all(np.isfinite(q)):
            raise EnvelopeViolation("input", "the trajectory has non-finite values")
        if q.shape[0] == 0:
            return
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise EnvelopeViolation("input", "t_s must increase")
        cycles = dt / self.limits.cycle_s
        self._check_rows(q, None, None, cycles)
        self._check_joint_accel(q[:, -N_ARM_JOINTS:], dt)

    def _check_joint_accel(self, q: np.ndarray, dt: np.ndarray) -> None:
        """The joints' accelerations along a whole trajectory ``q`` (n, 6) sampled ``dt`` (n - 1,) s
        apart, at rest before and after: each change of the mean speed over a step, divided by the
        time between the two steps' centres (the track's rule, per joint)."""
        amax = self.limits.joint_accel_max_deg_s2
        if amax is None or q.shape[0] < 2:
            return
        v = np.diff(q, axis=0) / dt[:, None]
        zero = np.zeros((1, q.shape[1]))
        vv = np.vstack([zero, v, zero])
        ww = np.concatenate([dt[:1], dt, dt[-1:]])
        accel = np.abs(np.diff(vv, axis=0)) / (0.5 * (ww[:-1] + ww[1:]))[:, None]
        hard = accel > amax[None] * (1 + _ACCEL_TOLERANCE)
        if hard.any():
            i, j = np.argwhere(hard)[0]
            raise EnvelopeViolation(
                "joint_accel",
                f"{JOINT_NAMES[j]} accelerates at {accel[i, j]:.1f} deg/s^2, above its limit {amax[j]:.1f} deg/s^2",
                joint=int(j), value=accel[i, j], limit=amax[j], sample=min(int(i), q.shape[0] - 1),
            )  # fmt: skip

    def check_path(self, q_deg: np.ndarray) -> None:
        """Check the positions of a path ``q_deg`` (n, 6) (``axes_mm_deg`` (n, 7) with a track) that
        has no time law yet: joint limits, track travel, workspace box. The move to the plan's
        start gets its time law cycle by cycle (:mod:`cellctl.motion.executor`), where the speed
        rules are checked; where it goes is known before it starts, and is checked here."""
        q = np.asarray(q_deg, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != self._n or not np.all(np.isfinite(q)):
            raise EnvelopeViolation("input", f"expected finite q_deg (n, {self._n}), got shape {q.shape}")
        if q.shape[0]:
            self._check_positions(q)

    def _check_positions(self, q7: np.ndarray, travel: bool = True) -> np.ndarray:
        """The positional rules on ``q7`` (n, 6 or 7): track travel (unless ``travel`` is False: the
        track's own rules checked it), joint limits, the workspace box. Returns the TCP positions
        (n, 3) mm, base frame."""
        lim = self.limits
        if travel and lim.track is not None:
            self._check_travel(q7[:, 0])
        q = q7[:, -N_ARM_JOINTS:]
        below, above = q < lim.q_min_deg, q > lim.q_max_deg
        if below.any() or above.any():
            i, j = np.argwhere(below | above)[0]
            side, bound = ("lower", lim.q_min_deg[j]) if below[i, j] else ("upper", lim.q_max_deg[j])
            raise EnvelopeViolation(
                "joint_limit",
                f"{JOINT_NAMES[j]} at {q[i, j]:.3f} deg beyond its {side} limit {bound:.3f} deg (with margin)",
                joint=int(j), value=q[i, j], limit=bound, sample=int(i) if q.shape[0] > 1 else None,
            )  # fmt: skip
        p = self._tcp(q)
        out = (p < lim.workspace_min_mm) | (p > lim.workspace_max_mm)
        if out.any():
            i, k = np.argwhere(out)[0]
            bound = lim.workspace_min_mm[k] if p[i, k] < lim.workspace_min_mm[k] else lim.workspace_max_mm[k]
            raise EnvelopeViolation(
                "workspace",
                f"TCP {'xyz'[k]} = {p[i, k]:.2f} mm outside the workspace box (limit {bound:.1f} mm)",
                value=p[i, k], limit=bound, sample=int(i) if q.shape[0] > 1 else None,
            )  # fmt: skip
        return p

    def _check_rows(
        self, q7: np.ndarray, q_prev7: np.ndarray | None, p_prev: np.ndarray | None, cycles,
        v_prev: float = 0.0, dt_prev: float | None = None,
    ) -> np.ndarray:  # fmt: skip
        lim = self.limits
        if lim.track is not None:
            self._check_track(q7, q_prev7, cycles, v_prev, dt_prev)
        p = self._check_positions(q7, travel=False)
        q = q7[:, -N_ARM_JOINTS:]
        q_prev = None if q_prev7 is None else q_prev7[-N_ARM_JOINTS:]
        if q_prev is not None:
            qq = np.vstack([q_prev[None], q])
            pp = np.vstack([self.world_mm(q_prev7, p_prev)[None], self.world_mm(q7, p)])
            cyc = np.atleast_1d(np.asarray(cycles, dtype=np.float64))
        else:
            qq, pp = q, self.world_mm(q7, p)
            cyc = np.atleast_1d(np.asarray(cycles, dtype=np.float64))
            if qq.shape[0] < 2:
                return p
        dq = np.abs(np.diff(qq, axis=0))
        max_step = lim.joint_speed_max_deg_s[None] * lim.cycle_s * cyc[:, None] * (1 + _SPEED_TOLERANCE)
        bad = dq > max_step
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise EnvelopeViolation(
                "joint_step",
                f"{JOINT_NAMES[j]} steps {dq[i, j]:.4f} deg in {cyc[i]:.2f} cycle(s), above {max_step[i, j]:.4f} deg "
                f"(speed limit {lim.joint_speed_max_deg_s[j]:.1f} deg/s)",
                joint=int(j), value=dq[i, j], limit=max_step[i, j], sample=int(i) + 1 if q_prev is None else None,
            )  # fmt: skip
        speed = np.linalg.norm(np.diff(pp, axis=0), axis=1) / (cyc * lim.cycle_s)
        fast = speed > lim.tcp_speed_max_mm_s * (1 + _SPEED_TOLERANCE)
        if fast.any():
            i = int(np.argmax(fast))
            raise EnvelopeViolation(
                "tcp_speed",
                f"TCP speed {speed[i]:.1f} mm/s above the cap {lim.tcp_speed_max_mm_s:.1f} mm/s",
                value=speed[i], limit=lim.tcp_speed_max_mm_s, sample=i + 1 if q_prev is None else None,
            )  # fmt: skip
        return p

    def _check_travel(self, s: np.ndarray) -> None:
        """The track's travel rule on carriage positions ``s`` (n,) mm."""
        track = self.limits.track
        sample = lambda i: int(i) if s.shape[0] > 1 else None  # noqa: E731 - one-line index rule
        out = (s < track.travel_min_mm) | (s > track.travel_max_mm)
        if out.any():
            i = int(np.argmax(out))
            side, bound = (
                ("lower", track.travel_min_mm)
                if s[i] < track.travel_min_mm
                else ("upper", track.travel_max_mm)
            )
            raise EnvelopeViolation(
                "track_travel",
                f"track at {s[i]:.2f} mm beyond its {side} travel limit {bound:.2f} mm (with margin)",
                value=s[i], limit=bound, sample=sample(i),
            )  # fmt: skip

    def _check_track(
        self, q: np.ndarray, q_prev: np.ndarray | None, cycles, v_prev: float, dt_prev: float | None = None
    ) -> None:
        """The track's rules on ``q`` (n, 7): travel, speed (step per cycle), acceleration (change of
        the step). ``q_prev`` (7,) is the last accepted set-point (the robot at ``v_prev`` mm/s,
        measured over ``dt_prev`` s; None: at rest) or None for a whole trajectory, which starts and
        ends at rest. A speed is the mean over its step, so a change of speed is divided by the time
        between the two steps' centres (steps of several cycles, after lost packets, count right)."""
        track = self.limits.track
        s = q[:, 0]
        self._check_travel(s)
        cyc = np.atleast_1d(np.asarray(cycles, dtype=np.float64))
        if q_prev is not None:
            ss = np.concatenate([[q_prev[0]], s])
            v0 = float(v_prev)
        else:
            ss = s
            v0 = 0.0
        if ss.shape[0] < 2:
            return
        dt = cyc * self.limits.cycle_s
        v = np.diff(ss) / dt
        fast = np.abs(v) > track.speed_max_mm_s * (1 + _SPEED_TOLERANCE)
        if fast.any():
            i = int(np.argmax(fast))
            raise EnvelopeViolation(
                "track_speed",
                f"track moves at {abs(v[i]):.1f} mm/s, above its limit {track.speed_max_mm_s:.1f} mm/s",
                value=abs(v[i]), limit=track.speed_max_mm_s, sample=i + 1 if q_prev is None else None,
            )  # fmt: skip
        # speeds start from v0 (at rest for a trajectory, and end at rest); each change over the
        # time between the centres of its two steps
        if q_prev is None:
            vv, ww = np.concatenate([[0.0], v, [0.0]]), np.concatenate([dt[:1], dt, dt[-1:]])
        else:
            vv, ww = np.concatenate([[v0], v]), np.concatenate([[dt_prev or dt[0]], dt])
        accel = np.abs(np.diff(vv)) / (0.5 * (ww[:-1] + ww[1:]))
        hard = accel > track.accel_max_mm_s2 * (1 + _ACCEL_TOLERANCE)
        if hard.any():
            i = int(np.argmax(hard))
            raise EnvelopeViolation(
                "track_accel",
                f"track accelerates at {accel[i]:.1f} mm/s^2, above its limit {track.accel_max_mm_s2:.1f} mm/s^2",
                value=accel[i], limit=track.accel_max_mm_s2,
                sample=min(i, q.shape[0] - 1) if q_prev is None else None,
            )  # fmt: skip
