"""The typed channel between the daemon and the motion process.

One ``AF_UNIX`` ``SOCK_SEQPACKET`` socket pair: every message is one datagram (the kernel keeps the
boundaries and sends a message whole or not at all), a JSON object with a ``kind``, validated by the
pydantic models below on the side that receives it. Nothing per cycle crosses it: the plan goes once
(a file the message names), commands (pause, resume, abort) and the execution's progress, end and
counters a few times a second. The joint feedback goes the other way through the shared-memory
ring (:mod:`drivers.abb_egm.shared_history`).

The motion process sends from its real-time thread without ever blocking (``MSG_DONTWAIT``): a
progress or statistics message the daemon has no room for is dropped and counted, the end of an
execution is sent again from another thread until it goes.
"""

from __future__ import annotations

import socket
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

from cellctl.api.models import EgmStats, MotionCounters, MotionRealtime
from cellctl.motion.executor import ExecutorConfig
from drivers.abb_egm.endpoint import EgmEndpointConfig

__all__ = [
    "MAX_MESSAGE_BYTES",
    "Command",
    "ControlCommand",
    "EndedEvent",
    "EnvelopeSpec",
    "Event",
    "ExecuteCommand",
    "HelloCommand",
    "ProgressMsg",
    "ReadyEvent",
    "RealtimeSpec",
    "ShutdownCommand",
    "StatsEvent",
    "TrackSpec",
    "decode_command",
    "decode_event",
    "encode",
    "socket_pair",
]

#: a message larger than this is refused (the plan travels as a file, not through the channel)
MAX_MESSAGE_BYTES = 64 * 1024

_V3 = Annotated[list[float], Field(min_length=3, max_length=3)]
_V6 = Annotated[list[float], Field(min_length=6, max_length=6)]


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TrackSpec(_Msg):
    """A linear track's geometry and limits (mm, mm/s, mm/s^2, mm/s^3)."""

    origin_mm: _V3
    direction: _V3
    travel_min_mm: float
    travel_max_mm: float
    speed_max_mm_s: float
    accel_max_mm_s2: float
    jerk_max_mm_s3: float


class EnvelopeSpec(_Msg):
    """The safety envelope's limits (:class:`~cellctl.motion.envelope.EnvelopeLimits`), as cell.toml
    gives them to the daemon; the motion process checks every reference against them."""

    q_min_deg: _V6
    q_max_deg: _V6
    workspace_min_mm: _V3
    workspace_max_mm: _V3
    tcp_speed_max_mm_s: float = Field(gt=0)
    joint_speed_max_deg_s: _V6
    cycle_s: float = Field(gt=0, le=0.1)
    T_flange_tcp: Annotated[list[list[float]], Field(min_length=4, max_length=4)]
    track: TrackSpec | None = None
    joint_accel_max_deg_s2: _V6 | None = None


class RealtimeSpec(_Msg):
    """How the motion process runs (cell.toml ``[robot]`` motion_* and egm_reply_* keys).

    ``priority``: SCHED_FIFO priority of the cycle thread (0: normal scheduling); the control thread
    gets one less. ``cpus``: CPUs to pin the process to (empty: any). ``lock_memory``: mlockall, so
    no page of the process is ever paged out. ``required``: a refusal of any of these ends the
    process with the reason instead of running without it.
    """

    priority: int = Field(default=0, ge=0, le=99)
    cpus: list[int] = Field(default_factory=list, max_length=1024)
    lock_memory: bool = True
    required: bool = False


class HelloCommand(_Msg):
    """The first message: everything the motion process needs before it binds the EGM port."""

    kind: Literal["hello"] = "hello"
    endpoint: EgmEndpointConfig
    envelope: EnvelopeSpec
    realtime: RealtimeSpec
    shm_name: str = Field(min_length=1, max_length=200)
    log_format: str = "json"
    log_level: str = "info"
    cell_id: str = ""


class ExecuteCommand(_Msg):
    """Run a plan: its trajectory in ``plan_file`` (npz: t_s, q_deg, qd_deg_s, qdd_deg_s2, segment),
    its segments' labels and kinds, the executor's settings (ExecutorConfig's fields), the host
    monotonic time before which the plan may not start, and where to write the record of what was
    commanded (npz), if anywhere."""

    kind: Literal["execute"] = "execute"
    execution_id: int = Field(ge=1)
    plan_file: str
    segment_labels: list[str]
    segment_kinds: list[str]
    executor: ExecutorConfig
    start_not_before_s: float = 0.0
    record_file: str | None = None


class ControlCommand(_Msg):
    """pause, resume, abort or fault_stop (with its reason) of the running execution."""

    kind: Literal["control"] = "control"
    execution_id: int = Field(ge=1)
    action: Literal["pause", "resume", "abort", "fault_stop"]
    reason: str = ""


class ShutdownCommand(_Msg):
    """Stop smoothly (an execution is aborted first) and exit."""

    kind: Literal["shutdown"] = "shutdown"


Command = Annotated[
    HelloCommand | ExecuteCommand | ControlCommand | ShutdownCommand, Field(discriminator="kind")
]


class ReadyEvent(_Msg):
    """The EGM port is bound and served; what the OS granted of the real-time settings."""

    kind: Literal["ready"] = "ready"
    pid: int
    host: str
    port: int
    realtime: MotionRealtime


class ProgressMsg(_Msg):
    """An execution's progress (:class:`~cellctl.motion.executor.ProgressEvent`) with its counters."""

    kind: Literal["progress"] = "progress"
    execution_id: int
    state: str
    segment: str
    pass_index: int
    pass_count: int
    percent: float
    time_left_s: float
    t_traj_s: float
    fault: str | None = None
    counters: MotionCounters


class EndedEvent(_Msg):
    """How an execution ended (:class:`~cellctl.motion.executor.ExecutionResult` without its arrays,
    which are in ``record_file`` when one was asked for)."""

    kind: Literal["ended"] = "ended"
    execution_id: int
    state: Literal["finished", "aborted", "faulted"]
    fault: str | None = None
    cycles: int
    lost_cycles: int
    max_tracking_error_mm: float
    move_to_start_s: float
    start_settle_s: float
    counters: MotionCounters
    record_file: str | None = None


class StatsEvent(_Msg):
    """The EGM endpoint's counters (``EgmStatistics.snapshot()``) and the channel's own drops."""

    kind: Literal["stats"] = "stats"
    egm: EgmStats
    dropped_messages: int = 0


Event = Annotated[ReadyEvent | ProgressMsg | EndedEvent | StatsEvent, Field(discriminator="kind")]

_COMMAND = TypeAdapter(Command)
_EVENT = TypeAdapter(Event)


def encode(msg: _Msg) -> bytes:
    """One message's bytes (refused above :data:`MAX_MESSAGE_BYTES`)."""
    data = msg.model_dump_json().encode()
    if len(data) > MAX_MESSAGE_BYTES:
        raise ValueError(f"{msg.__class__.__name__} of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    return data


def decode_command(data: bytes) -> HelloCommand | ExecuteCommand | ControlCommand | ShutdownCommand:
    """A command from its bytes (pydantic ValidationError when it is not one)."""
    return _COMMAND.validate_json(data)


def decode_event(data: bytes) -> ReadyEvent | ProgressMsg | EndedEvent | StatsEvent:
    """An event from its bytes (pydantic ValidationError when it is not one)."""
    return _EVENT.validate_json(data)


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """(the daemon's end, the motion process's end): a SOCK_SEQPACKET pair, neither inherited by
    other children (only the motion process gets its end, through ``pass_fds``)."""
    return socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
