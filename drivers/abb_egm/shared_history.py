"""The EGM feedback history in shared memory: written by the motion process alone, read by others.

The motion process (the only one that talks EGM) appends every in-order feedback sample; the daemon's
acquisition reads the samples to pose its profiles. The reader never takes a lock the writer could
wait on: the writer fills a row, then publishes it by advancing one 64-bit counter; a reader reads
the counter, copies the rows it wants, reads the counter again and drops every row the writer may
have overwritten meanwhile (a ring of ``capacity`` rows: the row ``count - capacity`` is the next to
go). A reader that falls more than a ring behind loses the oldest rows, never gets a torn one.

The layout (one ``SharedMemory`` block, native byte order, 64-byte aligned arrays):

``header`` int64[8]: magic, capacity, n_axes, count (rows ever appended), writer pid, 3 spare;
``status`` float64[4]: what the writer's user publishes beside the feedback (the motion process:
execution id, its playback time and state code, written after each cycle; see :meth:`publish`);
then ``capacity`` rows of ``t_host_ns`` int64, ``t_ctrl_us`` int64 (-1: none), ``seqno`` int64 (-1:
none), ``index`` int64 (the row's number since the start, a check), ``state`` int16[3] (motor, EGM,
RAPID states as the codec's enum values, -1: not sent), ``q_deg`` float64[n_axes] (with a track its mm
first), ``pos_mm`` float64[3], ``quat_wxyz`` float64[4] (NaN: not sent).
"""

from __future__ import annotations

import contextlib
from multiprocessing import resource_tracker, shared_memory

import numpy as np

from drivers.abb_egm.codec import MciState, MotorState, RapidState
from drivers.abb_egm.endpoint import FeedbackArrays, interpolate_q_deg, ok_to_command

__all__ = ["SharedFeedbackHistory"]

_MAGIC = 0x45474D_46_42_52  # "EGMFBR"
_HEADER = 8
_ALIGN = 64


def _layout(capacity: int, n_axes: int) -> tuple[dict[str, tuple[int, tuple[int, ...], type]], int]:
    fields = [
        ("header", (_HEADER,), np.int64),
        ("status", (4,), np.float64),
        ("t_host_ns", (capacity,), np.int64),
        ("t_ctrl_us", (capacity,), np.int64),
        ("seqno", (capacity,), np.int64),
        ("index", (capacity,), np.int64),
        ("state", (capacity, 3), np.int16),
        ("q_deg", (capacity, n_axes), np.float64),
        ("pos_mm", (capacity, 3), np.float64),
        ("quat_wxyz", (capacity, 4), np.float64),
    ]
    out, offset = {}, 0
    for name, shape, dtype in fields:
        out[name] = (offset, shape, dtype)
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        offset += -(-size // _ALIGN) * _ALIGN
    return out, offset


class SharedFeedbackHistory:
    """A feedback ring in shared memory (see the module docstring).

    ``SharedFeedbackHistory.create(name, capacity, n_axes)`` in the writer (it owns and unlinks the
    block); ``SharedFeedbackHistory.attach(name)`` in a reader. The writer's ``append`` has
    :class:`~drivers.abb_egm.endpoint.FeedbackHistory`'s signature (the endpoint takes it as its
    history); the reader has its ``arrays``, ``since``, ``q_deg_at`` and ``len``.
    """

    def __init__(self, shm: shared_memory.SharedMemory, *, owner: bool) -> None:
        self._shm = shm
        self._owner = owner
        head = np.ndarray((_HEADER,), dtype=np.int64, buffer=shm.buf)
        if owner:
            capacity, n_axes = int(head[1]), int(head[2])
        else:
            if int(head[0]) != _MAGIC:
                raise ValueError(f"shared memory {shm.name!r} holds no EGM feedback ring")
            capacity, n_axes = int(head[1]), int(head[2])
        self.capacity, self.n_axes = capacity, n_axes
        layout, _size = _layout(capacity, n_axes)
        self._a = {
            name: np.ndarray(shape, dtype=dtype, buffer=shm.buf, offset=off)
            for name, (off, shape, dtype) in layout.items()
        }
        self._head = self._a["header"]

    # ---- the two ends ---------------------------------------------------------------------------

    @classmethod
    def create(cls, name: str, capacity: int, n_axes: int) -> SharedFeedbackHistory:
        """The writer's end: a new block ``name`` (fails if it exists)."""
        if capacity < 2:
            raise ValueError(f"history capacity must be >= 2, got {capacity}")
        size = _layout(capacity, n_axes)[1]
        shm = shared_memory.SharedMemory(name=name, create=True, size=size)
        head = np.ndarray((_HEADER,), dtype=np.int64, buffer=shm.buf)
        head[:] = 0
        head[1], head[2] = capacity, n_axes
        self = cls(shm, owner=True)
        self._a["t_ctrl_us"][:] = -1
        self._a["seqno"][:] = -1
        self._a["index"][:] = -1
        head[0] = _MAGIC  # last: a reader attaching meanwhile sees no ring until it is whole
        return self

    @classmethod
    def attach(cls, name: str) -> SharedFeedbackHistory:
        """A reader's end of the block ``name`` (FileNotFoundError if there is none)."""
        shm = shared_memory.SharedMemory(name=name, create=False)
        # the reader does not own the block: keep Python's resource tracker from unlinking it when
        # this process ends (the writer unlinks it)
        with contextlib.suppress(Exception):  # a tracker that never saw it: nothing to undo
            resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        return cls(shm, owner=False)

    @property
    def name(self) -> str:
        return self._shm.name

    def close(self) -> None:
        """Let go of the block (the writer also removes it)."""
        self._a.clear()
        self._head = None  # type: ignore[assignment]
        with contextlib.suppress(BufferError):  # a view still held: the mapping goes with the process
            self._shm.close()
        if self._owner:
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()

    # ---- writing (the motion process) -----------------------------------------------------------

    def append(
        self,
        t_host_ns: int,
        t_ctrl_us: int | None,
        seqno: int | None,
        q_deg: np.ndarray,
        pos_mm: np.ndarray | None,
        quat_wxyz: np.ndarray | None,
        states: tuple[object, object, object] | None = None,
    ) -> None:
        """Add one sample, then publish it (the counter moves last)."""
        a = self._a
        k = int(self._head[3])
        i = k % self.capacity
        a["t_host_ns"][i] = t_host_ns
        a["t_ctrl_us"][i] = -1 if t_ctrl_us is None else t_ctrl_us
        a["seqno"][i] = -1 if seqno is None else seqno
        n = min(q_deg.shape[0], self.n_axes)
        a["q_deg"][i, :n] = q_deg[:n]
        a["pos_mm"][i] = np.nan if pos_mm is None else pos_mm
        a["quat_wxyz"][i] = np.nan if quat_wxyz is None else quat_wxyz
        st = a["state"][i]
        for j in range(3):
            v = None if states is None else states[j]
            st[j] = -1 if v is None else int(v)
        a["index"][i] = k
        self._head[3] = k + 1

    def publish(self, a: float, b: float, c: float) -> None:
        """Set the status words (the motion process: execution id, playback time s, state code);
        the id goes last so a reader that sees it sees the rest of the same cycle or a newer one."""
        st = self._a["status"]
        st[1] = b
        st[2] = c
        st[0] = a

    def status(self) -> tuple[float, float, float]:
        """The status words as :meth:`publish` left them (zeros before the first)."""
        st = self._a["status"]
        return float(st[0]), float(st[1]), float(st[2])

    def clear(self) -> None:
        """Forget every sample (readers see an empty ring)."""
        self._head[3] = 0
        self._a["index"][:] = -1

    # ---- reading (any process) ----------------------------------------------------------------

    @property
    def count(self) -> int:
        """Samples appended since the start (not capped by the capacity)."""
        return int(self._head[3])

    def __len__(self) -> int:
        return min(self.count, self.capacity)

    def _rows(self, first: int, end: int) -> FeedbackArrays:
        """Rows ``first .. end - 1`` (absolute numbers) that survived the copy, oldest first."""
        a = self._a
        k = np.arange(first, end, dtype=np.int64)
        idx = k % self.capacity
        out = FeedbackArrays(
            t_host_ns=a["t_host_ns"][idx],
            t_ctrl_us=a["t_ctrl_us"][idx],
            seqno=a["seqno"][idx],
            q_deg=a["q_deg"][idx],
            pos_mm=a["pos_mm"][idx],
            quat_wxyz=a["quat_wxyz"][idx],
        )
        stamp = a["index"][idx]
        after = self.count
        # the writer may be filling row ``after`` (which overwrites ``after - capacity``) right now
        keep = (k >= after - self.capacity + 1) & (stamp == k)
        if keep.all():
            return out
        return FeedbackArrays(*(getattr(out, f)[keep] for f in FeedbackArrays.__dataclass_fields__))

    def arrays(self) -> FeedbackArrays:
        """All kept samples, oldest first, as numpy copies."""
        end = self.count
        return self._rows(max(0, end - self.capacity + 1), end)

    def since(self, t_host_ns: int) -> FeedbackArrays:
        """The samples received after ``t_host_ns`` (host clock), oldest first; costs what it returns."""
        end = self.count
        first = max(0, end - self.capacity + 1)
        if end <= first:
            return self._rows(first, end)
        # binary search on the ring's chronological view (rows are appended in time order)
        t = self._a["t_host_ns"]
        lo, hi = first, end
        while lo < hi:
            mid = (lo + hi) // 2
            if t[mid % self.capacity] <= t_host_ns:
                lo = mid + 1
            else:
                hi = mid
        return self._rows(lo, end)

    def q_deg_at(self, t: np.ndarray, *, time_base: str = "host") -> np.ndarray:
        """Joint angles interpolated at ``t`` (as :meth:`FeedbackHistory.q_deg_at`)."""
        return interpolate_q_deg(self.arrays(), t, time_base)

    def latest(self) -> tuple[int, np.ndarray, bool] | None:
        """The newest sample as (t_host_ns, axes (n_axes,), ok to command), or None before the first."""
        end = self.count
        if end == 0:
            return None
        i = (end - 1) % self.capacity
        t = int(self._a["t_host_ns"][i])
        q = self._a["q_deg"][i].copy()
        m, c, r = (int(v) for v in self._a["state"][i])
        ok = ok_to_command(
            MotorState(m) if m >= 0 else None,
            MciState(c) if c >= 0 else None,
            RapidState(r) if r >= 0 else None,
        )
        return t, q, ok
