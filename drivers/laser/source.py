"""The sensor-agnostic profile source interface and the batch type every source delivers.

Shape borrowed from python-can's ``BusABC``: one small abstract interface (connect, configure, start,
stop, close, async iteration), with the HD8 TCP client (:mod:`drivers.laser.client`) as one
implementation. A vendor shim speaking another protocol, or another sensor family, plugs in beside it.

Everything a consumer needs travels in :class:`ProfileBatch`: whole numpy arrays for a run of
consecutive profiles, never one Python object per profile or point.
"""

from __future__ import annotations

import abc
import asyncio
import enum
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "ProfileBatch",
    "ProfileSource",
    "SourceEvent",
    "SourceEventKind",
    "SourceStats",
]


@dataclass(frozen=True, eq=False)
class ProfileBatch:
    """``n`` consecutive profiles of ``w`` points each, in the sensor frame.

    Sensor frame: the laser plane is the sensor's x-z plane; rays leave the sensor origin towards +z,
    x runs across the line. ``y`` is always 0 for a profile point.

    Attributes:
        frame_index: (n,) uint64, the sensor's frame counter (counts from 0, strictly increasing within
            a stream; a jump > 1 means frames were lost).
        sensor_time_us: (n,) uint64, mid-exposure time in the sensor's clock, microseconds.
        hd8_ms: (n,) uint32, the HD8's own 32-bit millisecond counter (wraps after ~49.7 days).
        encoder: (n,) int64, encoder ticks latched at exposure.
        status: (n,) uint32, status bits (see :class:`drivers.laser.protocol.StatusBits`).
        exposure_ns: (n,) uint32, exposure time, nanoseconds.
        x_mm: (n, w) float32, x of each point in the sensor frame, mm.
        z_mm: (n, w) float32, z (range along the laser axis) of each point, mm; NaN where not valid.
        valid: (n, w) bool, True where the sensor returned a point.
        host_recv_ns: (n,) int64, ``time.monotonic_ns()`` on the host when the profile's frame group
            was received (all profiles of one group share it); for clock synchronisation.
    """

    frame_index: np.ndarray
    sensor_time_us: np.ndarray
    hd8_ms: np.ndarray
    encoder: np.ndarray
    status: np.ndarray
    exposure_ns: np.ndarray
    x_mm: np.ndarray
    z_mm: np.ndarray
    valid: np.ndarray
    host_recv_ns: np.ndarray

    def __post_init__(self) -> None:
        n = self.frame_index.shape[0]
        for name in ("sensor_time_us", "hd8_ms", "encoder", "status", "exposure_ns", "host_recv_ns"):
            arr = getattr(self, name)
            if arr.shape != (n,):
                raise ValueError(f"ProfileBatch.{name} has shape {arr.shape}, expected ({n},)")
        if self.x_mm.ndim != 2 or self.x_mm.shape[0] != n:
            raise ValueError(f"ProfileBatch.x_mm has shape {self.x_mm.shape}, expected ({n}, w)")
        for name in ("z_mm", "valid"):
            arr = getattr(self, name)
            if arr.shape != self.x_mm.shape:
                raise ValueError(f"ProfileBatch.{name} has shape {arr.shape}, expected {self.x_mm.shape}")

    def __len__(self) -> int:
        return int(self.frame_index.shape[0])

    @property
    def width(self) -> int:
        """Points per profile."""
        return int(self.x_mm.shape[1])

    @property
    def n_points(self) -> int:
        """Total number of points (valid or not) in the batch."""
        return int(self.x_mm.size)

    def select(self, mask_or_index: np.ndarray | slice) -> ProfileBatch:
        """Return the profiles picked by a boolean mask, an index array or a slice (copies arrays)."""
        return ProfileBatch(
            **{name: np.ascontiguousarray(getattr(self, name)[mask_or_index]) for name in _FIELDS}
        )

    @classmethod
    def concat(cls, batches: Sequence[ProfileBatch]) -> ProfileBatch:
        """Concatenate batches of equal width along the profile axis."""
        if not batches:
            raise ValueError("ProfileBatch.concat needs at least one batch")
        widths = {b.width for b in batches}
        if len(widths) != 1:
            raise ValueError(f"ProfileBatch.concat: batches have different widths {sorted(widths)}")
        return cls(**{name: np.concatenate([getattr(b, name) for b in batches]) for name in _FIELDS})


_FIELDS = tuple(ProfileBatch.__dataclass_fields__)


class SourceEventKind(enum.StrEnum):
    """What a :class:`SourceEvent` reports."""

    STALLED = "stalled"  # no frame for longer than the watchdog timeout while running
    RESUMED = "resumed"  # frames arrive again after a stall
    DISCONNECTED = "disconnected"
    RECONNECTED = "reconnected"
    OVERFLOW = "overflow"  # the bounded buffer was full and frames were dropped
    GAP = "gap"  # the frame index jumped: the sensor lost frames
    RESTARTED = "restarted"  # the sensor restarted: frame index and sensor clock start afresh


@dataclass(frozen=True)
class SourceEvent:
    """A watchdog / health event of a source.

    Attributes:
        kind: what happened.
        t_ns: ``time.monotonic_ns()`` when it was noticed.
        detail: free-form key/values (e.g. ``silent_s``, ``missing_frames``, ``dropped_frames``).
    """

    kind: SourceEventKind
    t_ns: int
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass
class SourceStats:
    """Running statistics of a source; read it any time (it is updated in place).

    Attributes:
        frames: profiles delivered to the consumer's buffer.
        batches: batches delivered.
        rate_hz: profile rate over the last measurement window (about 1 s).
        gaps: number of frame-index jumps (each jump may hide many frames).
        missing_frames: total frames missing according to the frame index.
        duplicates_dropped: profiles discarded because their frame index was already delivered
            (e.g. replayed after a reconnect).
        decode_errors: messages or groups that failed validation and were skipped.
        reconnects: successful reconnections after a lost connection.
        overflow_batches: batches dropped because the bounded buffer was full.
        overflow_frames: profiles in those batches.
        bytes_received: bytes read from the data channel.
        last_frame_index: frame index of the newest delivered profile, or -1.
    """

    frames: int = 0
    batches: int = 0
    rate_hz: float = 0.0
    gaps: int = 0
    missing_frames: int = 0
    duplicates_dropped: int = 0
    decode_errors: int = 0
    reconnects: int = 0
    overflow_batches: int = 0
    overflow_frames: int = 0
    bytes_received: int = 0
    last_frame_index: int = -1
    _window_start_ns: int = field(default=0, repr=False)
    _window_frames: int = field(default=0, repr=False)

    def count_frames(self, n: int, now_ns: int | None = None) -> None:
        """Account ``n`` delivered profiles and refresh :attr:`rate_hz` once per second."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        if self._window_start_ns == 0:
            self._window_start_ns = now_ns
        self._window_frames += n
        elapsed_ns = now_ns - self._window_start_ns
        if elapsed_ns >= 1_000_000_000:
            self.rate_hz = self._window_frames * 1e9 / elapsed_ns
            self._window_start_ns = now_ns
            self._window_frames = 0

    def reset_rate(self) -> None:
        """Set :attr:`rate_hz` to 0 and restart its window (the source went silent)."""
        self.rate_hz = 0.0
        self._window_start_ns = 0
        self._window_frames = 0

    def as_dict(self) -> dict[str, Any]:
        """Public counters as a plain dict (for logs and status publications)."""
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_")}


EventListener = Callable[[SourceEvent], None]


class ProfileSource(abc.ABC):
    """A stream of stamped profiles: connect, configure, start, iterate, stop, close.

    Usage::

        src = HD8Client(host, control_port, data_port)
        await src.connect()
        await src.configure(rate_hz=200.0, exposure_ns=500_000)
        await src.start()
        async for batch in src:       # ProfileBatch, in frame-index order, no duplicates
            ...
        await src.stop(); await src.close()

    Iteration ends after :meth:`close`. Health is reported two ways: :attr:`stats` (counters) and
    events (:class:`SourceEvent`) which are both put on :attr:`events` (a bounded queue; the oldest
    event is dropped if nobody reads it) and passed to every listener added with
    :meth:`add_listener` (called in the event loop; must not block).
    """

    def __init__(self, *, event_queue_size: int = 256) -> None:
        self.stats = SourceStats()
        self.events: asyncio.Queue[SourceEvent] = asyncio.Queue(maxsize=event_queue_size)
        self._listeners: list[EventListener] = []

    @abc.abstractmethod
    async def connect(self) -> None:
        """Open the connection(s) to the sensor and read its identity."""

    @abc.abstractmethod
    async def configure(self, **settings: Any) -> None:
        """Apply acquisition settings (names are source specific, e.g. ``rate_hz``, ``exposure_ns``)."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Start acquisition; batches then become available through async iteration."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Stop acquisition; batches already buffered can still be read."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Release all connections; ends any running iteration."""

    @abc.abstractmethod
    def __aiter__(self) -> AsyncIterator[ProfileBatch]:
        """Iterate over batches in frame-index order."""

    def add_listener(self, listener: EventListener) -> None:
        """Call ``listener(event)`` for every future :class:`SourceEvent` (in the event loop)."""
        self._listeners.append(listener)

    def _emit(self, kind: SourceEventKind, **detail: Any) -> SourceEvent:
        event = SourceEvent(kind=kind, t_ns=time.monotonic_ns(), detail=detail)
        if self.events.full():
            # Losing an old health event is better than blocking the acquisition path.
            self.events.get_nowait()
        self.events.put_nowait(event)
        for listener in self._listeners:
            listener(event)
        return event
