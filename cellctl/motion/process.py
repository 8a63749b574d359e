"""The motion process: the EGM endpoint and the executor in a process of their own.

The daemon starts it (:class:`cellctl.motion.link.MotionLink`) with one end of a typed channel
(:mod:`cellctl.motion.channel`) and a name for the shared-memory feedback ring. It owns the EGM UDP
port from its start to its end; two threads share its interpreter and nothing else:

- the **cycle thread** (the process's main thread; SCHED_FIFO, pinned, memory locked where the OS
  allows): receive a controller packet, take its feedback into the state and the shared ring, run the
  executor's cycle for that very packet (the reference for the cycle it answers: never a stale one),
  check it against the envelope, reply; between packets, watch for a silent controller and send the
  progress and counters (never blocking on the channel);
- the **control thread** (one priority lower): read commands (execute a plan, pause, resume, abort,
  shutdown), set an execution up off the cycle, write the record of what was commanded and report
  an execution's end.

The collector never runs in a cycle: everything made at start-up is frozen out of its reach and
automatic collection is off; what an execution leaves is collected by the control thread once the
arm is at rest. A daemon that goes away (the channel closes) stops the arm smoothly along its path
and the process exits once it stands; a process that dies leaves the controller without answers,
and the controller ends the EGM session after its communication timeout.

Run as ``python -m cellctl.motion.process FD`` with FD the channel's descriptor (``pass_fds``).
"""

from __future__ import annotations

import dataclasses
import errno
import gc
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import structlog
from pydantic import ValidationError

from cellctl.api.models import MotionCounters, MotionRealtime
from cellctl.logging import bind_context, configure_logging
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
    decode_command,
    encode,
)
from cellctl.motion.envelope import EnvelopeLimits, SafetyEnvelope
from cellctl.motion.executor import (
    STATE_CODES,
    ExecutionResult,
    ExecutorConfig,
    MotionExecutor,
    ProgressEvent,
)
from cellctl.motion.trajectory import TimedTrajectory
from drivers.abb_egm.endpoint import (
    LATENCY_BIN_EDGES_US,
    EgmEndpoint,
    latency_percentile_us,
)
from drivers.abb_egm.limits import LinearTrack
from drivers.abb_egm.shared_history import SharedFeedbackHistory
from drivers.runtime import hold_cpu_wakeup_latency, lock_memory, set_thread_realtime

__all__ = ["MotionServer", "envelope_limits", "main", "realtime_setup"]

log = structlog.get_logger(__name__)

#: the cycle thread's receive timeout: how often, without packets, it looks at silence and the channel
_IDLE_S = 0.002
#: statistics go to the daemon this often
_STATS_PERIOD_NS = 500_000_000
#: a daemon gone during an execution: the smooth stop gets this long before the process exits anyway
_ORPHAN_STOP_S = 60.0
#: how long a new motion process waits for the EGM port an orphaned one still holds
_BIND_WAIT_S = 70.0


def envelope_limits(spec: EnvelopeSpec) -> EnvelopeLimits:
    """The :class:`EnvelopeLimits` of a channel's :class:`EnvelopeSpec`."""
    track = None
    if spec.track is not None:
        t = spec.track
        track = LinearTrack(
            origin_mm=np.asarray(t.origin_mm), direction=np.asarray(t.direction),
            travel_min_mm=t.travel_min_mm, travel_max_mm=t.travel_max_mm, speed_max_mm_s=t.speed_max_mm_s,
            accel_max_mm_s2=t.accel_max_mm_s2, jerk_max_mm_s3=t.jerk_max_mm_s3,
        )  # fmt: skip
    return EnvelopeLimits(
        q_min_deg=np.asarray(spec.q_min_deg),
        q_max_deg=np.asarray(spec.q_max_deg),
        workspace_min_mm=np.asarray(spec.workspace_min_mm),
        workspace_max_mm=np.asarray(spec.workspace_max_mm),
        tcp_speed_max_mm_s=spec.tcp_speed_max_mm_s,
        joint_speed_max_deg_s=np.asarray(spec.joint_speed_max_deg_s),
        cycle_s=spec.cycle_s,
        T_flange_tcp=np.asarray(spec.T_flange_tcp, dtype=np.float64),
        track=track,
        joint_accel_max_deg_s2=None
        if spec.joint_accel_max_deg_s2 is None
        else np.asarray(spec.joint_accel_max_deg_s2),
    )


def realtime_setup(spec: RealtimeSpec) -> MotionRealtime:
    """Apply ``spec`` to the calling thread (and, for memory, the process): what was granted and,
    one line each, what the OS refused (``refused``: empty when everything was granted)."""
    refused = set_thread_realtime(spec.priority, tuple(spec.cpus))
    locked = False
    if spec.lock_memory:
        why = lock_memory()
        if why is None:
            locked = True
        else:
            refused.append(why)
    granted_fifo = spec.priority > 0 and not any(r.startswith("SCHED_FIFO") for r in refused)
    return MotionRealtime(
        priority=spec.priority if granted_fifo else 0,
        sched_fifo=granted_fifo,
        cpus=sorted(os.sched_getaffinity(0)),
        memory_locked=locked,
        refused="; ".join(refused),
    )


class MotionServer:
    """The motion process's two threads' work around one :class:`EgmEndpoint` (see the module
    docstring). ``channel``: the SOCK_SEQPACKET end to the daemon."""

    def __init__(
        self,
        endpoint: EgmEndpoint,
        limits: EnvelopeLimits,
        channel: socket.socket,
        realtime: RealtimeSpec,
        ring: SharedFeedbackHistory,
    ) -> None:
        self.endpoint = endpoint
        self.ring = ring
        self.limits = limits
        self.channel = channel
        self.realtime = realtime
        self.execution: MotionExecutor | None = None
        self.execution_id = 0
        self._record_file: str | None = None
        self._reported = True
        self._stop = False
        self._stop_when_idle = False
        self._send_lock = threading.Lock()
        self.dropped_messages = 0
        self._next_stats_ns = 0
        self._base_stale = 0
        self._base_latency = np.zeros(LATENCY_BIN_EDGES_US.shape[0], dtype=np.int64)

    # ---- the channel ----------------------------------------------------------------------------

    def _send_nowait(self, msg) -> bool:
        """Send without blocking (the cycle thread's way): a message with no room is dropped."""
        try:
            data = encode(msg)
            with self._send_lock:
                self.channel.send(data, socket.MSG_DONTWAIT)
            return True
        except (BlockingIOError, InterruptedError):
            self.dropped_messages += 1
        except OSError:  # the daemon is gone: the control thread sees the end of the channel
            self.dropped_messages += 1
        return False

    def _send(self, msg, timeout_s: float = 10.0) -> bool:
        """Send, waiting for room up to ``timeout_s`` (the control thread's way)."""
        data = encode(msg)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with self._send_lock:
                    self.channel.send(data, socket.MSG_DONTWAIT)
                return True
            except (BlockingIOError, InterruptedError):
                if time.monotonic() > deadline:
                    log.warning("motion_channel_full", kind=msg.kind)
                    return False
                time.sleep(0.005)
            except OSError as exc:
                log.warning("motion_channel_send_failed", kind=msg.kind, error=str(exc))
                return False

    # ---- the cycle thread -----------------------------------------------------------------------

    def stopping(self) -> bool:
        return self._stop

    def idle(self) -> None:
        """After every packet and every receive timeout: silence, the end of an execution, statistics."""
        now = time.monotonic_ns()
        ex = self.execution
        if ex is not None and not self._reported:
            if not ex.done:
                ex.check_silence(now)
            if ex.done:
                self.endpoint.set_cycle_hook(None)
                self.ring.publish(self.execution_id, ex.playback_s, STATE_CODES[ex.state])
                self._reported = True
                counters = self.counters(ex)
                threading.Thread(
                    target=self._report_end, args=(ex, self.execution_id, counters, self._record_file),
                    name="motion-report", daemon=True,
                ).start()  # fmt: skip
        if now >= self._next_stats_ns:
            self._next_stats_ns = now + _STATS_PERIOD_NS
            self._send_nowait(
                StatsEvent(egm=self.endpoint.stats.snapshot(), dropped_messages=self.dropped_messages)
            )
        if self._stop_when_idle and (self.execution is None or self._reported):
            self._stop = True

    def counters(self, ex: MotionExecutor) -> MotionCounters:
        """The execution's counters so far (stale and latency since its first cycle)."""
        st = self.endpoint.stats
        lat = st.latency_counts - self._base_latency
        top = np.nonzero(lat)[0]
        return MotionCounters(
            cycles=ex.cycles,
            egm_stale_cycles=max(0, st.stale - self._base_stale),
            egm_lost_cycles=ex.lost_cycles,
            egm_reply_p50_us=latency_percentile_us(lat, 50),
            egm_reply_p99_us=latency_percentile_us(lat, 99),
            egm_reply_max_us=None
            if top.size == 0
            else float(LATENCY_BIN_EDGES_US[min(top[-1] + 1, LATENCY_BIN_EDGES_US.shape[0] - 1)]),
            max_tracking_error_mm=round(float(ex.max_tracking_error_mm), 4),
            max_tracking_t_traj_s=round(float(ex.max_tracking_t_traj_s), 3),
        )

    def _progress(self, ev: ProgressEvent | None) -> None:
        """The executor's progress sink (called on the cycle thread)."""
        ex = self.execution
        if ev is None or ex is None:
            return
        self._send_nowait(
            ProgressMsg(execution_id=self.execution_id, counters=self.counters(ex), **dataclasses.asdict(ev))
        )

    # ---- the control thread ---------------------------------------------------------------------

    def control_loop(self) -> None:
        """Read commands until the daemon closes the channel or says shutdown."""
        if self.realtime.priority > 1:
            set_thread_realtime(self.realtime.priority - 1)
        while not self._stop:
            try:
                data = self.channel.recv(MAX_MESSAGE_BYTES + 1)
            except OSError as exc:
                log.warning("motion_channel_failed", error=str(exc))
                data = b""
            if not data:
                self._orphaned("the daemon closed the channel")
                return
            try:
                cmd = decode_command(data)
            except (ValidationError, ValueError) as exc:
                log.warning("motion_command_invalid", error=str(exc)[:500], size=len(data))
                continue
            if isinstance(cmd, ExecuteCommand):
                self._execute(cmd)
            elif isinstance(cmd, ControlCommand):
                self._control(cmd)
            elif isinstance(cmd, ShutdownCommand):
                self._orphaned("shutdown")
                return
            else:
                log.warning("motion_command_unexpected", kind=cmd.kind)

    def _orphaned(self, why: str) -> None:
        """The daemon is gone or asked to stop: stop the arm smoothly (an execution is aborted), then
        let the cycle thread end."""
        ex = self.execution
        running = ex is not None and not ex.done
        log.warning("motion_stopping", reason=why, execution_running=running)
        if running:
            ex.abort()
            deadline = time.monotonic() + _ORPHAN_STOP_S
            while not ex.done and time.monotonic() < deadline:
                time.sleep(0.01)
            # the reference is at rest; the arm follows it through the controller's filter: wait
            # until it stands (or 3 s) before the process ends and the controller is left unanswered
            settle = time.monotonic() + 3.0
            while time.monotonic() < settle:
                time.sleep(0.05)
                recent = self.ring.arrays().q_deg[-25:]
                if recent.shape[0] >= 25 and float(np.max(np.ptp(recent, axis=0))) < 0.002:
                    break
        self._stop_when_idle = True

    def _control(self, cmd: ControlCommand) -> None:
        ex = self.execution
        if ex is None or cmd.execution_id != self.execution_id:
            log.info("motion_control_ignored", action=cmd.action, execution_id=cmd.execution_id)
            return
        if cmd.action == "pause":
            ex.pause()
        elif cmd.action == "resume":
            ex.resume()
        elif cmd.action == "abort":
            ex.abort()
        else:
            ex.fault_stop(cmd.reason or "fault stop requested")

    def _execute(self, cmd: ExecuteCommand) -> None:
        if self.execution is not None and not self._reported:
            log.warning(
                "motion_execute_refused", reason="an execution is running", execution_id=cmd.execution_id
            )
            return
        try:
            with np.load(cmd.plan_file) as z:
                traj = TimedTrajectory(
                    t_s=z["t_s"], q_deg=z["q_deg"], qd_deg_s=z["qd_deg_s"], qdd_deg_s2=z["qdd_deg_s2"],
                    segment=z["segment"],
                )  # fmt: skip
            cfg = cmd.executor
            ex = MotionExecutor(
                self.endpoint, traj, SafetyEnvelope(self.limits), cfg,
                segment_labels=cmd.segment_labels, segment_kinds=cmd.segment_kinds,
            )  # fmt: skip
        except Exception as exc:  # a plan that cannot be read or run: the job fails with the reason
            log.warning("motion_execute_failed", error=repr(exc), execution_id=cmd.execution_id)
            self._send(
                EndedEvent(
                    execution_id=cmd.execution_id, state="faulted", fault=f"the motion process refused the plan: {exc}",
                    cycles=0, lost_cycles=0, max_tracking_error_mm=0.0, move_to_start_s=0.0, start_settle_s=0.0,
                    counters=MotionCounters(),
                )
            )  # fmt: skip
            return
        ex.start_not_before_s = cmd.start_not_before_s
        ex.sink = self._progress
        self.execution_id = cmd.execution_id
        self._record_file = cmd.record_file
        self.execution = ex
        gc.collect()  # what the last execution left, now, with the arm at rest
        first = self._wait_commandable(cfg)
        if first is None:
            ex.fail(f"no commandable feedback from the controller within {cfg.start_timeout_s} s")
        elif ex.begin(first[1], first[0]):
            st = self.endpoint.stats
            self._base_stale = st.stale
            self._base_latency = st.latency_counts.copy()
            ring, eid, codes = self.ring, self.execution_id, STATE_CODES

            def cycle(msg, t_rx_ns: int, phase: str) -> None:
                ex.on_cycle(msg, t_rx_ns, phase)
                ring.publish(eid, ex.playback_s, codes[ex.state])

            ring.publish(eid, 0.0, codes[ex.state])
            self.endpoint.set_cycle_hook(cycle)
        self._reported = False  # from here the cycle thread reports the end

    def _wait_commandable(self, cfg: ExecutorConfig) -> tuple[int, np.ndarray] | None:
        """The newest feedback (host time, axes) once the controller is commandable and fresh."""
        n = self.limits.n_axes
        deadline = time.monotonic() + cfg.start_timeout_s
        while time.monotonic() < deadline and not self._stop:
            st = self.endpoint.latest
            if (
                st is not None
                and st.ok_to_command
                and st.axes_mm_deg.shape[0] >= n
                and time.monotonic_ns() - st.t_host_ns < cfg.feedback_timeout_s * 1e9
            ):
                return st.t_host_ns, np.asarray(st.axes_mm_deg[:n], dtype=np.float64)
            time.sleep(0.002)
        return None

    def _report_end(
        self, ex: MotionExecutor, execution_id: int, counters: MotionCounters, record_file: str | None
    ) -> None:
        result: ExecutionResult = ex.result()
        written = None
        if record_file:
            try:
                _write_record(Path(record_file), result, self.endpoint.stats.stale_events.copy())
                written = record_file
            except OSError as exc:
                log.warning("motion_record_not_written", path=record_file, error=str(exc))
        log.info("motion_execution_ended", execution_id=execution_id, state=result.state.value,
                 fault=result.fault, **counters.model_dump())  # fmt: skip
        self._send(
            EndedEvent(
                execution_id=execution_id,
                state=result.state.value,
                fault=result.fault,
                cycles=result.cycles,
                lost_cycles=result.lost_cycles,
                max_tracking_error_mm=float(result.max_tracking_error_mm),
                move_to_start_s=result.move_to_start_s,
                start_settle_s=result.start_settle_s,
                counters=counters,
                record_file=written,
            )
        )


def _write_record(path: Path, result: ExecutionResult, stale_events=()) -> None:
    """The record of what was commanded (:class:`ExecutionResult`'s arrays) and ``stale_ns`` (k, 2):
    each stale reply of the execution (the latest 4096) as host monotonic ns when it left and its
    latency in ns, so a stale cycle can be set against what else the machine did at that moment."""
    stale = np.asarray(list(stale_events), dtype=np.int64).reshape(-1, 2)
    if result.t_host_s.size:
        stale = stale[stale[:, 0] >= int(result.t_host_s[0] * 1e9)]
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("wb") as fh:
        np.savez(
            fh, t_host_s=result.t_host_s, q_ref_deg=result.q_ref_deg, qd_ref_deg_s=result.qd_ref_deg_s,
            t_traj_s=result.t_traj_s, cycle=result.cycle, track_mm=result.track_mm, stale_ns=stale,
        )  # fmt: skip
    os.replace(tmp, path)


def _bind(endpoint: EgmEndpoint) -> tuple[str, int]:
    """Bind the EGM port; while another process holds it (the motion process of a daemon that died,
    still stopping its arm: it exits once the arm stands) wait for it, up to ``_BIND_WAIT_S``."""
    deadline = time.monotonic() + _BIND_WAIT_S
    logged = False
    while True:
        try:
            return endpoint.bind_blocking(idle_timeout_s=_IDLE_S)
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE or time.monotonic() > deadline:
                raise
            if not logged:
                log.warning("egm_port_busy_waiting", port=endpoint.config.port, wait_s=_BIND_WAIT_S)
                logged = True
            time.sleep(0.1)


def main(argv: list[str] | None = None) -> int:
    """The motion process's entry: ``python -m cellctl.motion.process FD``."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not args[0].isdigit():
        print("usage: python -m cellctl.motion.process FD (started by the daemon)", file=sys.stderr)
        return 2
    channel = socket.socket(fileno=int(args[0]))
    try:
        hello = decode_command(channel.recv(MAX_MESSAGE_BYTES + 1))
    except (ValidationError, ValueError, OSError) as exc:
        print(f"motion process: no valid hello from the daemon: {exc}", file=sys.stderr)
        return 2
    if not isinstance(hello, HelloCommand):
        print(f"motion process: expected hello, got {hello.kind}", file=sys.stderr)
        return 2
    configure_logging("json" if hello.log_format == "json" else "console", hello.log_level)
    bind_context(cell_id=hello.cell_id, process="motion")
    ep_cfg = dataclasses.replace(hello.endpoint, reply_thread=False)
    limits = envelope_limits(hello.envelope)
    ring = SharedFeedbackHistory.create(hello.shm_name, ep_cfg.history_len, ep_cfg.n_external + ep_cfg.n_axes)
    try:
        endpoint = EgmEndpoint(ep_cfg, history=ring)
        try:
            host, port = _bind(endpoint)
        except OSError as exc:
            log.error("egm_bind_failed", host=ep_cfg.host, port=ep_cfg.port, error=str(exc))
            return 2
        if ep_cfg.switch_interval_s is not None:
            sys.setswitchinterval(ep_cfg.switch_interval_s)
        rt = realtime_setup(hello.realtime)
        hold_cpu_wakeup_latency(0)  # the cores answer a packet without waking from a deep idle state
        if rt.refused:
            log.warning("motion_realtime_refused", reason=rt.refused, required=hello.realtime.required)
        else:
            log.info("motion_realtime", **rt.model_dump(exclude={"refused"}))
        server = MotionServer(endpoint, limits, channel, hello.realtime, ring)
        # everything made so far (modules, the model, the envelope's kinematics) out of the collector's
        # reach, and no automatic collection: it would run inside a cycle
        gc.collect()
        gc.freeze()
        gc.disable()
        control = threading.Thread(target=server.control_loop, name="motion-control", daemon=True)
        control.start()
        server._send(ReadyEvent(pid=os.getpid(), host=host, port=port, realtime=rt))
        endpoint.serve_blocking(stop=server.stopping, idle=server.idle)
        log.info("motion_process_exit", dropped_messages=server.dropped_messages)
        return 0
    finally:
        ring.close()
        channel.close()


if __name__ == "__main__":
    sys.exit(main())
