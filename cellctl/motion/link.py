"""The daemon's side of the motion process: start and supervise it, hand it plans, follow them.

:class:`MotionLink` starts ``python -m cellctl.motion.process`` with one end of the typed channel
(:mod:`cellctl.motion.channel`), waits for it to bind the EGM port, and from then reads its events
on the daemon's event loop; the feedback the acquisition poses its profiles with, and the plan's
playback time the pass markers follow, come from the shared-memory ring the motion process alone
writes (:mod:`drivers.abb_egm.shared_history`). :meth:`MotionLink.execution` gives a
:class:`RemoteExecution`, which has the in-process executor's controls (pause, resume, abort,
progress, ``await run()``) and runs the plan in the motion process.

A motion process that dies ends a running execution FAULTED with the reason (its exit code or
signal); :meth:`MotionLink.restart` (the daemon's ``reset``) starts a new one.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog
from pydantic import ValidationError

from cellctl.api.models import MotionCounters, MotionRealtime
from cellctl.motion.channel import (
    MAX_MESSAGE_BYTES,
    ControlCommand,
    EndedEvent,
    EnvelopeSpec,
    ExecuteCommand,
    HelloCommand,
    ProgressMsg,
    ReadyEvent,
    RealtimeSpec,
    ShutdownCommand,
    StatsEvent,
    TrackSpec,
    decode_event,
    encode,
    socket_pair,
)
from cellctl.motion.envelope import EnvelopeLimits
from cellctl.motion.executor import (
    STATE_CODES,
    TERMINAL_STATES,
    ExecState,
    ExecutionResult,
    ExecutorConfig,
    ProgressEvent,
)
from cellctl.motion.trajectory import TimedTrajectory
from drivers.abb_egm.endpoint import EgmEndpointConfig
from drivers.abb_egm.shared_history import SharedFeedbackHistory

__all__ = [
    "FeedbackSample",
    "MotionLink",
    "MotionLinkError",
    "MotionSettings",
    "RemoteExecution",
    "envelope_spec",
]

log = structlog.get_logger(__name__)

_CODE_STATES = {v: k for k, v in STATE_CODES.items()}
_COUNTERS = itertools.count(1)


class MotionLinkError(Exception):
    """The motion process could not be started, or is not there."""


def envelope_spec(limits: EnvelopeLimits) -> EnvelopeSpec:
    """The channel's form of the envelope limits."""
    t = limits.track
    track = None
    if t is not None:
        track = TrackSpec(
            origin_mm=list(map(float, t.origin_mm)), direction=list(map(float, t.direction)),
            travel_min_mm=t.travel_min_mm, travel_max_mm=t.travel_max_mm, speed_max_mm_s=t.speed_max_mm_s,
            accel_max_mm_s2=t.accel_max_mm_s2, jerk_max_mm_s3=t.jerk_max_mm_s3,
        )  # fmt: skip
    return EnvelopeSpec(
        q_min_deg=list(map(float, limits.q_min_deg)),
        q_max_deg=list(map(float, limits.q_max_deg)),
        workspace_min_mm=list(map(float, limits.workspace_min_mm)),
        workspace_max_mm=list(map(float, limits.workspace_max_mm)),
        tcp_speed_max_mm_s=float(limits.tcp_speed_max_mm_s),
        joint_speed_max_deg_s=list(map(float, limits.joint_speed_max_deg_s)),
        cycle_s=float(limits.cycle_s),
        T_flange_tcp=np.asarray(limits.T_flange_tcp, dtype=np.float64).tolist(),
        track=track,
        joint_accel_max_deg_s2=None
        if limits.joint_accel_max_deg_s2 is None
        else list(map(float, limits.joint_accel_max_deg_s2)),
    )


@dataclass(frozen=True)
class MotionSettings:
    """What the motion process is started with: the EGM endpoint, the envelope every reference
    passes, the real-time settings, logging."""

    endpoint: EgmEndpointConfig
    envelope: EnvelopeSpec
    realtime: RealtimeSpec
    log_format: str = "json"
    log_level: str = "info"
    cell_id: str = ""
    ready_timeout_s: float = 90.0


@dataclass(frozen=True)
class FeedbackSample:
    """The newest feedback in the ring: host receive time (monotonic ns), axes (deg; a track's mm
    first), and whether the controller takes commands (motors on, EGM and RAPID running)."""

    t_host_ns: int
    axes_mm_deg: np.ndarray
    ok_to_command: bool


class _StatsView:
    """The motion process's last EGM statistics, read like the endpoint's (``stats.received``)."""

    def __init__(self) -> None:
        self._snap: dict = {}

    def update(self, snap: dict) -> None:
        self._snap = snap

    def snapshot(self) -> dict:
        return dict(self._snap)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return self._snap.get(name, 0)


class MotionLink:
    """The motion process, seen from the daemon (see the module docstring). ``on_death(reason)`` is
    called on the loop when the process ends without being asked to."""

    def __init__(self, settings: MotionSettings, *, on_death: Callable[[str], None] | None = None) -> None:
        self.settings = settings
        self.on_death = on_death
        self.stats = _StatsView()
        self.realtime: MotionRealtime | None = None
        self._proc: asyncio.subprocess.Process | None = None
        self._sock: socket.socket | None = None
        self._ring: SharedFeedbackHistory | None = None
        self._reader: asyncio.Task[None] | None = None
        self._address: tuple[str, int] | None = None
        self._ready: asyncio.Future[ReadyEvent] | None = None
        self._executions: dict[int, RemoteExecution] = {}
        self._closing = False
        self.death: str | None = None

    # ---- life cycle -------------------------------------------------------------------------------

    async def start(self) -> tuple[str, int]:
        """Start the process and wait until it serves the EGM port; returns the bound address.

        Raises:
            MotionLinkError: it did not come up (the reason: its exit, a refused real-time setting
                that ``required`` asks for, a timeout).
        """
        if self._proc is not None:
            raise MotionLinkError("the motion process is running already")
        s = self.settings
        loop = asyncio.get_running_loop()
        mine, theirs = socket_pair()
        shm_name = f"cellctl-egm-{os.getpid()}-{next(_COUNTERS)}"
        self._closing = False
        self.death = None
        try:
            self._proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "cellctl.motion.process", str(theirs.fileno()),
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, start_new_session=True,
            )  # fmt: skip
        finally:
            theirs.close()
        mine.setblocking(False)
        self._sock = mine
        self._ready = loop.create_future()
        hello = HelloCommand(
            endpoint=s.endpoint, envelope=s.envelope, realtime=s.realtime, shm_name=shm_name,
            log_format=s.log_format, log_level=s.log_level, cell_id=s.cell_id,
        )  # fmt: skip
        await loop.sock_sendall(mine, encode(hello))
        self._reader = asyncio.create_task(self._read_loop(), name="motion-link")
        try:
            async with asyncio.timeout(s.ready_timeout_s):
                ready = await self._ready
        except TimeoutError:
            await self._kill()
            raise MotionLinkError(
                f"the motion process did not come up within {s.ready_timeout_s} s"
            ) from None
        except MotionLinkError:
            await self._kill()
            raise
        self.realtime = ready.realtime
        if s.realtime.required and ready.realtime.refused:
            await self.close()
            raise MotionLinkError(
                f"the motion process's real-time settings were refused ({ready.realtime.refused}) "
                "and [robot] motion_realtime_required is set"
            )
        self._ring = SharedFeedbackHistory.attach(shm_name)
        self._address = (ready.host, ready.port)
        log.info(
            "motion_process_started", pid=ready.pid, host=ready.host, port=ready.port,
            **self.realtime.model_dump(),
        )  # fmt: skip
        return self._address

    async def close(self, timeout_s: float = 30.0) -> None:
        """Ask the process to stop (a running execution stops smoothly first) and wait for it."""
        self._closing = True
        proc = self._proc
        if proc is not None and proc.returncode is None and self._sock is not None:
            with contextlib.suppress(OSError):
                await asyncio.get_running_loop().sock_sendall(self._sock, encode(ShutdownCommand()))
            try:
                async with asyncio.timeout(timeout_s):
                    await proc.wait()
            except TimeoutError:
                log.error("motion_process_did_not_stop", timeout_s=timeout_s)
        await self._kill()

    async def restart(self) -> tuple[str, int]:
        """A new motion process in place of the old one (the old one is stopped or gone)."""
        await self.close(timeout_s=5.0)
        return await self.start()

    async def _kill(self) -> None:
        proc = self._proc
        if proc is not None and proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(proc.wait(), 10.0)
        if self._reader is not None and not self._reader.done():
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        self._reader = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        self._proc = None
        self._address = None

    @property
    def alive(self) -> bool:
        """The process runs and answers the controller."""
        return self._proc is not None and self._proc.returncode is None and self._address is not None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def local_address(self) -> tuple[str, int]:
        """The EGM address the motion process serves."""
        if self._address is None:
            raise MotionLinkError("the motion process is not running")
        return self._address

    @property
    def history(self) -> SharedFeedbackHistory:
        """The feedback ring (the acquisition's feedback source)."""
        if self._ring is None:
            raise MotionLinkError("the motion process is not running")
        return self._ring

    # ---- events -------------------------------------------------------------------------------------

    async def _read_loop(self) -> None:
        loop = asyncio.get_running_loop()
        sock = self._sock
        assert sock is not None
        while True:
            try:
                data = await loop.sock_recv(sock, MAX_MESSAGE_BYTES + 1)
            except OSError:
                data = b""
            if not data:
                break
            try:
                ev = decode_event(data)
            except (ValidationError, ValueError) as exc:
                log.warning("motion_event_invalid", error=str(exc)[:300])
                continue
            if isinstance(ev, ReadyEvent):
                if self._ready is not None and not self._ready.done():
                    self._ready.set_result(ev)
            elif isinstance(ev, StatsEvent):
                self.stats.update(ev.egm.model_dump())
            elif isinstance(ev, ProgressMsg | EndedEvent):
                ex = self._executions.get(ev.execution_id)
                if ex is not None:
                    ex._on_event(ev)
        await self._ended()

    async def _ended(self) -> None:
        """The channel closed: the process ended (or is ending)."""
        proc = self._proc
        code = None
        if proc is not None:
            with contextlib.suppress(Exception):
                code = await asyncio.wait_for(proc.wait(), 5.0)
        if code is None:
            why = "the motion process closed its channel"
        elif code < 0:
            why = f"the motion process died (signal {signal.Signals(-code).name})"
        else:
            why = f"the motion process exited with code {code}"
        self._address = None
        if self._ready is not None and not self._ready.done():
            self._ready.set_exception(MotionLinkError(f"{why} before it was ready (see its log)"))
        for ex in list(self._executions.values()):
            ex._on_death(why)
        self._executions.clear()
        if not self._closing:
            self.death = why
            log.error("motion_process_lost", reason=why)
            if self.on_death is not None:
                try:
                    self.on_death(why)
                except Exception:
                    log.exception("motion_death_callback_failed")

    # ---- what the daemon asks -------------------------------------------------------------------------

    def latest(self) -> FeedbackSample | None:
        """The newest feedback, or None before the first (or without a process)."""
        ring = self._ring
        got = None if ring is None else ring.latest()
        return None if got is None else FeedbackSample(got[0], got[1], got[2])

    async def wait_for_feedback(self, timeout_s: float) -> FeedbackSample:
        """Wait for a feedback newer than the call; TimeoutError after ``timeout_s``,
        MotionLinkError when there is no motion process."""
        deadline = time.monotonic() + timeout_s
        ring = self.history
        start = ring.count
        while True:
            if not self.alive:
                raise MotionLinkError(self.death or "the motion process is not running")
            if ring.count > start:
                got = self.latest()
                if got is not None:
                    return got
            if time.monotonic() >= deadline:
                raise TimeoutError(f"no EGM feedback within {timeout_s} s")
            await asyncio.sleep(0.002)

    def execution(
        self,
        trajectory: TimedTrajectory,
        config: ExecutorConfig,
        *,
        segment_labels: list[str],
        segment_kinds: list[str],
        work_dir: Path,
        on_progress: Callable[[ProgressEvent], None] | None = None,
    ) -> RemoteExecution:
        """An execution of ``trajectory`` in the motion process (started by ``await run()``); its plan
        and record files go into ``work_dir``."""
        return RemoteExecution(
            self, trajectory, config, segment_labels=segment_labels, segment_kinds=segment_kinds,
            work_dir=work_dir, on_progress=on_progress,
        )  # fmt: skip

    async def _send(self, msg) -> None:
        if self._sock is None or not self.alive:
            raise MotionLinkError(self.death or "the motion process is not running")
        await asyncio.get_running_loop().sock_sendall(self._sock, encode(msg))


class RemoteExecution:
    """One plan run by the motion process, with the in-process executor's controls."""

    def __init__(
        self,
        link: MotionLink,
        trajectory: TimedTrajectory,
        config: ExecutorConfig,
        *,
        segment_labels: list[str],
        segment_kinds: list[str],
        work_dir: Path,
        on_progress: Callable[[ProgressEvent], None] | None,
    ) -> None:
        self.link = link
        self.trajectory = trajectory
        self.config = config
        self.segment_labels = list(segment_labels)
        self.segment_kinds = list(segment_kinds)
        self.work_dir = Path(work_dir)
        self.on_progress = on_progress
        self.execution_id = next(_COUNTERS)
        self.start_not_before_s = 0.0
        self.fault: str | None = None
        self.counters = MotionCounters()
        self.events: list[ProgressEvent] = []
        self._state = ExecState.IDLE
        self._ended: EndedEvent | None = None
        self._done = asyncio.Event()
        self._sent = False
        self._pending: list[str] = []
        n_sweeps = sum(k in ("scan", "edge") for k in self.segment_kinds)
        self._last = ProgressEvent(
            state=ExecState.IDLE.value, segment="", pass_index=0, pass_count=n_sweeps, percent=0.0,
            time_left_s=round(trajectory.duration_s, 3), t_traj_s=0.0,
        )  # fmt: skip

    # ---- controls (from the event loop) ----------------------------------------------------------------

    def pause(self) -> None:
        self._control("pause")

    def resume(self) -> None:
        self._control("resume")

    def abort(self) -> None:
        self._control("abort")

    def fault_stop(self, reason: str) -> None:
        self._control("fault_stop", reason)

    def _control(self, action: str, reason: str = "") -> None:
        if self._done.is_set():
            return
        if not self._sent:  # before the plan went out: it goes right after it
            self._pending.append(action if not reason else f"{action}:{reason}")
            return
        cmd = ControlCommand(execution_id=self.execution_id, action=action, reason=reason)
        task = asyncio.get_running_loop().create_task(self._send_control(cmd))
        task.add_done_callback(lambda t: None if t.cancelled() else t.exception())

    async def _send_control(self, cmd: ControlCommand) -> None:
        try:
            await self.link._send(cmd)
        except (MotionLinkError, OSError) as exc:
            log.warning("motion_control_not_sent", action=cmd.action, error=str(exc))

    # ---- state ------------------------------------------------------------------------------------------

    @property
    def state(self) -> ExecState:
        """The execution's state: from the shared ring's status (every cycle) while it runs."""
        if self._ended is not None:
            return ExecState(self._ended.state)
        ring = self.link._ring
        if ring is not None and self._sent:
            eid, _tau, code = ring.status()
            if int(eid) == self.execution_id:
                return _CODE_STATES.get(int(code), self._state)
        return self._state

    def progress(self) -> ProgressEvent:
        """The current progress; its playback time from the shared ring (every cycle)."""
        ev = self._last
        ring = self.link._ring
        if ring is not None and self._sent and self._ended is None:
            eid, tau, _code = ring.status()
            if int(eid) == self.execution_id:
                ev = dataclasses.replace(ev, t_traj_s=round(tau, 4), state=self.state.value)
        return ev

    def _on_event(self, ev: ProgressMsg | EndedEvent) -> None:
        self.counters = ev.counters
        if isinstance(ev, EndedEvent):
            self._ended = ev
            self.fault = ev.fault
            self._state = ExecState(ev.state)
            self._last = dataclasses.replace(self._last, state=ev.state, fault=ev.fault)
            self._done.set()
            return
        pe = ProgressEvent(
            state=ev.state, segment=ev.segment, pass_index=ev.pass_index, pass_count=ev.pass_count,
            percent=ev.percent, time_left_s=ev.time_left_s, t_traj_s=ev.t_traj_s, fault=ev.fault,
        )  # fmt: skip
        self._state = ExecState(ev.state)
        self._last = pe
        self.events.append(pe)
        if self.on_progress is not None:
            try:
                self.on_progress(pe)
            except Exception:
                log.exception("executor_progress_callback_failed")

    def _on_death(self, why: str) -> None:
        if self._done.is_set():
            return
        self.fault = why
        self._state = ExecState.FAULTED
        self._ended = EndedEvent(
            execution_id=self.execution_id, state="faulted", fault=why, cycles=self.counters.cycles,
            lost_cycles=self.counters.egm_lost_cycles, max_tracking_error_mm=self.counters.max_tracking_error_mm,
            move_to_start_s=0.0, start_settle_s=0.0, counters=self.counters,
        )  # fmt: skip
        self._done.set()

    # ---- the run ----------------------------------------------------------------------------------------

    async def run(self) -> ExecutionResult:
        """Send the plan and wait for its end (FINISHED, ABORTED or FAULTED; never raises for faults,
        a motion process that dies is a fault with the reason)."""
        traj = self.trajectory
        plan_file = self.work_dir / "motion-plan.npz"
        record_file = self.work_dir / "motion-record.npz"

        def write_plan() -> None:
            self.work_dir.mkdir(parents=True, exist_ok=True)
            tmp = plan_file.with_name(plan_file.name + ".tmp")
            with tmp.open("wb") as fh:
                np.savez(fh, t_s=traj.t_s, q_deg=traj.q_deg, qd_deg_s=traj.qd_deg_s,
                         qdd_deg_s2=traj.qdd_deg_s2, segment=traj.segment)  # fmt: skip
            os.replace(tmp, plan_file)

        try:
            await asyncio.to_thread(write_plan)
            self.link._executions[self.execution_id] = self
            await self.link._send(
                ExecuteCommand(
                    execution_id=self.execution_id, plan_file=str(plan_file),
                    segment_labels=self.segment_labels, segment_kinds=self.segment_kinds, executor=self.config,
                    start_not_before_s=self.start_not_before_s, record_file=str(record_file),
                )
            )  # fmt: skip
            self._sent = True
            for p in self._pending:
                action, _, reason = p.partition(":")
                self._control(action, reason)
            self._pending.clear()
            await self._done.wait()
        except (MotionLinkError, OSError) as exc:
            self._on_death(f"the motion process could not run the plan: {exc}")
        finally:
            self.link._executions.pop(self.execution_id, None)
        end = self._ended
        assert end is not None
        return ExecutionResult(
            state=ExecState(end.state),
            fault=end.fault,
            cycles=end.cycles,
            max_tracking_error_mm=end.max_tracking_error_mm,
            t_host_s=np.zeros(0),
            q_ref_deg=np.zeros((0, traj.q_deg.shape[1])),
            qd_ref_deg_s=np.zeros((0, traj.q_deg.shape[1])),
            t_traj_s=np.zeros(0),
            cycle=np.zeros(0, dtype=np.int64),
            lost_cycles=end.lost_cycles,
            events=list(self.events),
            move_to_start_s=end.move_to_start_s,
            start_settle_s=end.start_settle_s,
        )

    @property
    def done(self) -> bool:
        return self.state in TERMINAL_STATES

    def record(self) -> ExecutionResult | None:
        """The record of what was commanded (the arrays), once ended, when the motion process wrote it."""
        end = self._ended
        if end is None or not end.record_file:
            return None
        with np.load(end.record_file) as z:
            return dataclasses.replace(
                ExecutionResult(
                    state=ExecState(end.state), fault=end.fault, cycles=end.cycles,
                    max_tracking_error_mm=end.max_tracking_error_mm, t_host_s=z["t_host_s"],
                    q_ref_deg=z["q_ref_deg"], qd_ref_deg_s=z["qd_ref_deg_s"], t_traj_s=z["t_traj_s"],
                    cycle=z["cycle"], lost_cycles=end.lost_cycles,
                    max_tracking_t_traj_s=end.counters.max_tracking_t_traj_s or 0.0,
                    track_mm=z["track_mm"] if "track_mm" in z.files else np.zeros(0, dtype=np.float32),
                ),
                events=list(self.events), move_to_start_s=end.move_to_start_s, start_settle_s=end.start_settle_s,
            )  # fmt: skip
