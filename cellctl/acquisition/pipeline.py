"""The acquisition pipeline: raw data to disk first, then stamp, pose, transform, assemble.

:class:`Acquisition` is fed three kinds of input in arrival order: joint feedback samples
(:meth:`Acquisition.feed_robot`), profile batches (:meth:`Acquisition.feed_profiles`) and pass
markers (:meth:`Acquisition.begin_pass` / :meth:`Acquisition.end_pass`). Each input is appended to the
job's raw files *before* it is processed. The pipeline is a deterministic function of that input
sequence, so replaying the raw files (:mod:`cellctl.acquisition.reassemble`) rebuilds the same cloud
bit for bit. Clock fits are also recorded; the replay checks it recomputes exactly the same ones.

A batch waits until the robot history covers its exposure times (the pose after the last profile
must be known before interpolating), so batches are assembled a few milliseconds after arrival.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import structlog

from cellctl.acquisition.assembly import (
    AssembledBatch,
    AssembledScan,
    PassSchedule,
    ScanBuilder,
    assemble_batch,
)
from cellctl.acquisition.clock_sync import (
    ClockFit,
    ClockSync,
    ClockSyncConfig,
    CounterUnwrapper,
    FrameTimeline,
)
from cellctl.acquisition.poses import T_from_pos_rpy
from cellctl.config import CellConfig
from cellctl.jobstore.rawstore import RawWriter
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.limits import LinearTrack
from drivers.laser.source import ProfileBatch

__all__ = [
    "KIND_CLOCK_FIT",
    "KIND_PASS_BEGIN",
    "KIND_PASS_END",
    "KIND_PROFILES",
    "KIND_ROBOT",
    "Acquisition",
    "AcquisitionSettings",
    "AcquisitionStats",
]

log = structlog.get_logger(__name__)

KIND_PROFILES = 1
KIND_ROBOT = 2
KIND_CLOCK_FIT = 3
KIND_PASS_BEGIN = 4
KIND_PASS_END = 5
CLOCK_IDS = {"sensor": 0, "robot": 1}
_FIT_FIELDS = tuple(f for f in ClockFit.__slots__)


def _track_json(track: LinearTrack) -> dict[str, Any]:
    """A track's fields as plain JSON values (job.json keeps them beside the hand-eye)."""
    return {
        "origin_mm": [float(v) for v in track.origin_mm],
        "direction": [float(v) for v in track.direction],
        "travel_min_mm": float(track.travel_min_mm),
        "travel_max_mm": float(track.travel_max_mm),
        "speed_max_mm_s": float(track.speed_max_mm_s),
        "accel_max_mm_s2": float(track.accel_max_mm_s2),
        "jerk_max_mm_s3": float(track.jerk_max_mm_s3),
    }


@dataclass(frozen=True)
class AcquisitionSettings:
    """Everything the assembly depends on (stored in the job's ``job.json``).

    Attributes:
        sensor_in_flange_pos_mm, sensor_in_flange_rpy_deg: hand-eye (cell.toml ``[robot.sensor_in_flange]``).
        latency_ms: fixed latency removed after clock sync (cell.toml ``[laser] latency_ms``): the
            sensor link's minimum latency minus the controller link's, plus any stamp bias.
        sensor_clock: ``"us"`` uses the protocol's microsecond mid-exposure stamp; ``"ms"`` uses the
            HD8's 32-bit millisecond counter (unwrapped, refined over the frame index).
        ms_counter_at: where in the exposure the HD8 counter is latched (``"start"`` adds half the
            exposure to stamp at mid-exposure).
        sensor_sync: ``"envelope"`` (the online fit); ``"host_receive"`` stamps each profile with its
            host receive time (the naive method, for comparison); ``"none"`` takes the sensor's
            stamps as host time as they are (a sensor clock believed to be set to the PC's).
        robot_clock: ``"controller"`` maps the EGM feedback clock onto the host base; ``"host"`` uses
            the receive times as they are (when the controller sends no clock).
        epoch_ns: fixed origin of the float time arithmetic (the job's start, host ns).
        sensor_sync_config, robot_sync_config: clock estimator settings.
        max_pending_profiles: profiles waiting for robot data beyond this are assembled without a
            pose (invalid) so a silent controller cannot grow memory without bound.
        max_sample_gap_ms: a profile whose two bracketing feedback samples are further apart than
            this (lost EGM packets: the controller sends every 4 ms) gets no pose; counted in the
            stats. Shorter gaps are bridged by a cubic Hermite with the slopes of the intervals
            beside them (``poses.interpolate_joints``): on the synthetic scan motion within 7 um
            over 100 ms where the chord is 0.17 mm off. 100 ms covers the 50 ms loss bursts of
            issue 10's fault list with one more burst right behind it.
        track: the linear track's fields (:class:`~drivers.abb_egm.limits.LinearTrack`, JSON-able)
            when the robot rides on one (cell.toml ``[robot.track]``), else None. The feedback rows
            are then ``axes_mm_deg`` (track mm, then joints) and the poses are in the world frame.
    """

    sensor_in_flange_pos_mm: tuple[float, float, float] = (0.0, 0.0, 150.0)
    sensor_in_flange_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    latency_ms: float = 0.0
    sensor_clock: Literal["us", "ms"] = "us"
    ms_counter_at: Literal["start", "mid"] = "start"
    robot_clock: Literal["controller", "host"] = "controller"
    sensor_sync: Literal["envelope", "host_receive", "none"] = "envelope"
    epoch_ns: int = 0
    sensor_sync_config: ClockSyncConfig = field(default_factory=ClockSyncConfig)
    robot_sync_config: ClockSyncConfig = field(default_factory=ClockSyncConfig)
    max_pending_profiles: int = 4000
    max_sample_gap_ms: float = 100.0
    track: dict[str, Any] | None = None

    @classmethod
    def from_config(cls, cfg: CellConfig, epoch_ns: int) -> AcquisitionSettings:
        """The settings cell.toml implies: ``[robot.sensor_in_flange]``, ``[laser] latency_ms`` and
        ``sensor_clock``."""
        mount = cfg.robot.sensor_in_flange
        track = None if cfg.robot.track is None else _track_json(cfg.robot.track.linear_track())
        return cls(
            track=track,
            sensor_in_flange_pos_mm=tuple(mount.pos_mm),
            sensor_in_flange_rpy_deg=tuple(mount.rpy_deg),
            latency_ms=cfg.laser.latency_ms,
            sensor_clock=cfg.laser.sensor_clock,
            epoch_ns=epoch_ns,
        )

    @property
    def linear_track(self) -> LinearTrack | None:
        """The track the robot rides on, or None."""
        return None if self.track is None else LinearTrack(**self.track)

    @property
    def n_axes(self) -> int:
        """Values per feedback sample: 6 joints, or the track and 6 joints."""
        return 6 + (self.track is not None)

    @property
    def T_flange_sensor(self) -> np.ndarray:
        """(4, 4) hand-eye transform, mm."""
        return T_from_pos_rpy(self.sensor_in_flange_pos_mm, self.sensor_in_flange_rpy_deg)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON-able dict."""
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> AcquisitionSettings:
        """Inverse of :meth:`to_json`."""
        d = dict(d)
        d["sensor_sync_config"] = ClockSyncConfig(**d.get("sensor_sync_config", {}))
        d["robot_sync_config"] = ClockSyncConfig(**d.get("robot_sync_config", {}))
        for k in ("sensor_in_flange_pos_mm", "sensor_in_flange_rpy_deg"):
            if k in d:
                d[k] = tuple(float(v) for v in d[k])
        return cls(**d)


@dataclass
class AcquisitionStats:
    """Counters: inputs seen, profiles assembled, profiles without pose, fits made."""

    robot_samples: int = 0
    robot_samples_dropped: int = 0
    batches_in: int = 0
    profiles_in: int = 0
    profiles_assembled: int = 0
    profiles_without_pose: int = 0
    sensor_fits: int = 0
    robot_fits: int = 0


class _Growable:
    """Amortised O(1) append of rows to a numpy array (the robot track)."""

    def __init__(self, row_shape: tuple[int, ...], dtype) -> None:
        self._a = np.empty((1024, *row_shape), dtype=dtype)
        self.n = 0

    def extend(self, rows: np.ndarray) -> None:
        k = len(rows)
        if self.n + k > len(self._a):
            new = np.empty((max(2 * len(self._a), self.n + k), *self._a.shape[1:]), dtype=self._a.dtype)
            new[: self.n] = self._a[: self.n]
            self._a = new
        self._a[self.n : self.n + k] = rows
        self.n += k

    @property
    def view(self) -> np.ndarray:
        return self._a[: self.n]


class Acquisition:
    """Stamp, pose and assemble profiles, writing every input to the raw files first.

    Args:
        settings: hand-eye, latency, clock choices (stored in ``job.json`` by the writer's owner).
        writer: the job's raw writer, or None (replay, tests).
        keep_batches: keep the assembled rows in memory for :meth:`cloud` (False for long soak runs
            where only the raw files and a consumer of :meth:`feed_profiles`' return value matter).
        expected_profiles: profiles the scan is expected to have (the plan's duration x the sensor
            rate): the whole-scan arrays are reserved once at that size (:class:`ScanBuilder`).
        fixed_fits: ``{"sensor": ClockFit, "robot": ClockFit, "frames": line}`` to use instead of the
            online fits (the final assembly after a scan, with fits over the whole scan; see
            :mod:`.reassemble`); ``frames`` is a :meth:`FrameTimeline.line` for the ms counter.
        clocks_only: only feed the clock estimators (the first pass of the final assembly).
        spill_dir: where the whole scan's per-point arrays are kept in a file instead of memory
            (:class:`ScanBuilder`, :mod:`.spill`); by default the raw writer's directory, with no
            writer in memory. ``False``: in memory whatever the writer.
    """

    def __init__(
        self,
        settings: AcquisitionSettings,
        writer: RawWriter | None = None,
        *,
        keep_batches: bool = True,
        fixed_fits: dict | None = None,
        clocks_only: bool = False,
        expected_profiles: int = 0,
        spill_dir: str | Path | Literal[False] | None = None,
    ) -> None:
        self.settings = settings
        self.fixed_fits = dict(fixed_fits or {})
        self.clocks_only = clocks_only
        self.writer = writer
        self.keep_batches = keep_batches
        self.stats = AcquisitionStats()
        self.sensor_sync = ClockSync(settings.sensor_sync_config, "sensor")
        self.robot_sync = ClockSync(settings.robot_sync_config, "robot")
        self.fits: list[tuple[str, ClockFit]] = []
        self.schedule = PassSchedule()
        self._T_fs = settings.T_flange_sensor
        self._track = settings.linear_track
        self._n_axes = settings.n_axes
        self._latency_ns = round(settings.latency_ms * 1e6)
        self._track_t = _Growable((), np.int64)
        self._track_T = _Growable((3, 4), np.float64)
        self._pending: list[tuple[ProfileBatch, np.ndarray]] = []
        self._pending_profiles = 0
        self._unwrap = CounterUnwrapper()
        frames_line = self.fixed_fits.get("frames")
        self._timeline = FrameTimeline(line=frames_line) if frames_line is not None else FrameTimeline()
        if spill_dir is None and writer is not None:
            spill_dir = writer.job_dir
        self._rows = ScanBuilder(expected_profiles, spill_dir=spill_dir or None)
        self._next_profile = 0
        self._width = 0

    # ---- inputs ---------------------------------------------------------------------------------

    def feed_robot(
        self, t_host_ns: np.ndarray, t_ctrl_us: np.ndarray, q_deg: np.ndarray
    ) -> list[AssembledBatch]:
        """Joint feedback samples (m,) host receive ns, (m,) controller clock us (-1: none), (m, 6) deg
        (``axes_mm_deg`` (m, 7) with a track).

        Returns the batches this made assemblable.
        """
        t_host = np.ascontiguousarray(t_host_ns, dtype=np.int64)
        t_ctrl = np.ascontiguousarray(t_ctrl_us, dtype=np.int64)
        q = np.ascontiguousarray(q_deg, dtype=np.float64)
        if t_host.ndim != 1 or t_ctrl.shape != t_host.shape or q.shape != (len(t_host), self._n_axes):
            raise ValueError(
                f"robot samples: t_host_ns {t_host.shape}, t_ctrl_us {t_ctrl.shape}, q_deg {q.shape}"
            )
        if len(t_host) == 0:
            return []
        if self.writer is not None:
            self.writer.append("robot", KIND_ROBOT, {"t_host_ns": t_host, "t_ctrl_us": t_ctrl, "q_deg": q})
        self.stats.robot_samples += len(t_host)
        if self.settings.robot_clock == "controller" and np.all(t_ctrl >= 0):
            fit = self.robot_sync.add(t_ctrl, t_host)
            if fit is not None:
                self._record_fit("robot", fit)
            robot_fit = self.fixed_fits.get("robot", self.robot_sync.fit)
            if self.clocks_only:
                return []
            if robot_fit is None:
                self.stats.robot_samples_dropped += len(t_host)
                return []
            t = robot_fit.to_host_ns(t_ctrl)
        else:
            if self.clocks_only:
                return []
            t = t_host
        last = self._track_t.view[-1] if self._track_t.n else np.iinfo(np.int64).min
        # a refit may move mapped times by microseconds; the track must stay strictly increasing
        keep = t > np.maximum.accumulate(np.concatenate([[last], t[:-1]]))
        self.stats.robot_samples_dropped += int((~keep).sum())
        if keep.any():
            # FK once per sample (250 Hz), not once per profile: profiles blend the bracketing poses
            self._track_T.extend(fk_batch(q[keep], self._T_fs, track=self._track)[:, :3, :])
            self._track_t.extend(t[keep])
        return self._drain()

    def feed_profiles(self, batch: ProfileBatch) -> list[AssembledBatch]:
        """One profile batch as the source delivered it. Returns the batches now assembled."""
        if self.writer is not None:
            self.writer.append("profiles", KIND_PROFILES, _batch_arrays(batch), items=len(batch))
        self.stats.batches_in += 1
        self.stats.profiles_in += len(batch)
        self._width = batch.width
        src_us = self._sensor_src_us(batch)
        fit = self.sensor_sync.add(src_us[-1:], batch.host_recv_ns[-1:])
        if fit is not None:
            self._record_fit("sensor", fit)
        if self.clocks_only:
            return []
        self._pending.append((batch, src_us))
        self._pending_profiles += len(batch)
        return self._drain()

    def begin_pass(self, pass_id: int, t_ns: int) -> None:
        """Profiles exposed from ``t_ns`` (host ns) on belong to ``pass_id``."""
        if self.writer is not None:
            self.writer.append(
                "events", KIND_PASS_BEGIN, {"pass_id": np.int64(pass_id), "t_ns": np.int64(t_ns)}
            )
        self.schedule.begin(pass_id, t_ns)

    def end_pass(self, t_ns: int) -> None:
        """The open pass ends at ``t_ns`` (host ns)."""
        if self.writer is not None:
            self.writer.append("events", KIND_PASS_END, {"t_ns": np.int64(t_ns)})
        self.schedule.end(t_ns)

    def finish(self) -> list[AssembledBatch]:
        """Assemble whatever still waits (without pose where the robot history ends) and flush."""
        out = self._drain(force=True)
        if self.writer is not None:
            self.writer.flush()
        return out

    # ---- results --------------------------------------------------------------------------------

    def cloud(self) -> AssembledScan:
        """Everything assembled so far as one organised cloud (views of the acquisition's arrays: later
        batches do not change it, they may reallocate the arrays behind it)."""
        return self._rows.scan(self._width)

    def batches_since(self, k: int) -> list[AssembledBatch]:
        """The batches assembled after the first ``k`` (in order; with ``keep_batches``): a consumer
        that follows the scan while it runs (the cloud streamed pass by pass)."""
        return self._rows.batches_since(k)

    def quality(self) -> dict[str, Any]:
        """Clock fit reports and counters (for the job record and logs)."""
        return {
            "sensor_clock": None if self.sensor_sync.fit is None else self.sensor_sync.fit.report(),
            "robot_clock": None if self.robot_sync.fit is None else self.robot_sync.fit.report(),
            "latency_ms": self.settings.latency_ms,
            **asdict(self.stats),
        }

    # ---- internals ------------------------------------------------------------------------------

    def _record_fit(self, which: str, fit: ClockFit) -> None:
        self.fits.append((which, fit))
        if which == "sensor":
            self.stats.sensor_fits += 1
        else:
            self.stats.robot_fits += 1
        if self.writer is not None:
            self.writer.append("clock", KIND_CLOCK_FIT, fit_to_arrays(which, fit))

    def _sensor_src_us(self, batch: ProfileBatch) -> np.ndarray:
        if self.settings.sensor_clock == "us":
            return batch.sensor_time_us.astype(np.int64)
        ms = self._unwrap.unwrap(batch.hd8_ms)
        # a truncating ms counter: the true instant lies in [k, k+1) ms, its middle is k + 0.5
        mid_us = ms * 1000 + 500
        if self.settings.ms_counter_at == "start":
            mid_us = mid_us + (batch.exposure_ns.astype(np.int64) // 2000)
        return self._timeline.times_us(batch.frame_index.astype(np.int64), mid_us)

    def _drain(self, force: bool = False) -> list[AssembledBatch]:
        out: list[AssembledBatch] = []
        fit = self.fixed_fits.get("sensor", self.sensor_sync.fit)
        while self._pending and (fit is not None or force or self.settings.sensor_sync != "envelope"):
            batch, src_us = self._pending[0]
            mode = self.settings.sensor_sync
            if mode == "host_receive" or (fit is None and mode == "envelope"):
                t = batch.host_recv_ns.astype(np.int64) - self._latency_ns
            elif mode == "none":
                t = src_us * 1000 - self._latency_ns
            else:
                t = fit.to_host_ns(src_us) - self._latency_ns
            covered = self._track_t.n >= 2 and t.max() <= self._track_t.view[-1]
            overdue = self._pending_profiles - len(batch) >= self.settings.max_pending_profiles
            if not (covered or force or overdue):
                break
            self._pending.pop(0)
            self._pending_profiles -= len(batch)
            out.append(self._assemble(batch, t))
        return out

    def _assemble(self, batch: ProfileBatch, t_ns: np.ndarray) -> AssembledBatch:
        if self._track_t.n >= 2:
            ab = assemble_batch(
                x_mm=batch.x_mm,
                z_mm=batch.z_mm,
                valid=batch.valid,
                frame_index=batch.frame_index,
                t_ns=t_ns,
                sample_t_ns=self._track_t.view,
                sample_T_base_sensor=self._track_T.view,
                epoch_ns=self.settings.epoch_ns,
                pass_id=self.schedule.assign(t_ns),
                first_profile_index=self._next_profile,
                max_gap_ns=round(self.settings.max_sample_gap_ms * 1e6),
            )
        else:
            n, w = batch.x_mm.shape
            ab = AssembledBatch(
                profile_index=np.arange(self._next_profile, self._next_profile + n, dtype=np.int64),
                frame_index=batch.frame_index.astype(np.uint64),
                pass_id=self.schedule.assign(t_ns),
                t_ns=t_ns,
                xyz_mm=np.full((n, w, 3), np.nan, np.float32),
                valid=np.zeros((n, w), bool),
                sensor_pos_mm=np.full((n, 3), np.nan, np.float32),
            )
        self._next_profile += len(t_ns)
        self.stats.profiles_assembled += len(t_ns)
        if ab.valid is not batch.valid:  # (the same array when every profile had a pose)
            self.stats.profiles_without_pose += int((~ab.valid.any(axis=1) & batch.valid.any(axis=1)).sum())
        if self.keep_batches:
            self._rows.append(ab)
        return ab


def _batch_arrays(batch: ProfileBatch) -> dict[str, np.ndarray]:
    arrays = {
        "frame_index": batch.frame_index,
        "sensor_time_us": batch.sensor_time_us,
        "hd8_ms": batch.hd8_ms,
        "encoder": batch.encoder,
        "status": batch.status,
        "exposure_ns": batch.exposure_ns,
        "host_recv_ns": batch.host_recv_ns,
        "z_mm": batch.z_mm,
        "valid_bits": np.packbits(batch.valid, axis=1),
        "width": np.int64(batch.width),
    }
    x = batch.x_mm
    # uniform profiles share one x row: store it once (halves the raw volume); the decoder hands
    # them over as a broadcast row (stride 0), which needs no comparison
    if len(x) and (x.strides[0] == 0 or np.array_equal(x, np.broadcast_to(x[0], x.shape))):
        arrays["x_row"] = x[0]
    else:
        arrays["x_mm"] = x
    return arrays


def batch_from_arrays(a: dict[str, np.ndarray]) -> ProfileBatch:
    """Rebuild a :class:`ProfileBatch` from a stored profiles record."""
    n = len(a["frame_index"])
    w = int(a["width"])
    # the same read-only broadcast row the decoder delivers (no n copies of it)
    x = np.broadcast_to(a["x_row"], (n, w)) if "x_row" in a else a["x_mm"]
    return ProfileBatch(
        frame_index=a["frame_index"],
        sensor_time_us=a["sensor_time_us"],
        hd8_ms=a["hd8_ms"],
        encoder=a["encoder"],
        status=a["status"],
        exposure_ns=a["exposure_ns"],
        x_mm=x,
        z_mm=a["z_mm"],
        valid=np.unpackbits(a["valid_bits"], axis=1, count=w).astype(bool),
        host_recv_ns=a["host_recv_ns"],
    )


def fit_to_arrays(which: str, fit: ClockFit) -> dict[str, np.ndarray]:
    """A clock fit as a raw record."""
    d = {"clock": np.int64(CLOCK_IDS[which])}
    for f in _FIT_FIELDS:
        v = getattr(fit, f)
        d[f] = np.int64(v) if isinstance(v, int) else np.float64(v)
    return d


def fit_from_arrays(a: dict[str, np.ndarray]) -> tuple[str, ClockFit]:
    """Inverse of :func:`fit_to_arrays`."""
    names = {v: k for k, v in CLOCK_IDS.items()}
    kw = {}
    for f in _FIT_FIELDS:
        v = a[f]
        kw[f] = int(v) if v.dtype.kind == "i" else float(v)
    return names[int(a["clock"])], ClockFit(**kw)
