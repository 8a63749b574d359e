"""The analysis child's heap: what it frees stays in the process, and is touched before it is needed.

On the cell PC's class of machine (this VM: a page's first touch costs about 25 us, 2 ms a MB) the
analysis of the sail plate's 2.6 M points spent half its time in the kernel. Its working arrays
(tens of MB each) are allocated and freed over and over; glibc hands large blocks back to the kernel
when they are freed (``mmap`` above its threshold, the heap's top trimmed), each thread of the
gaps' pool has an arena of its own, and the next array faults every page again. Measured on the
cloud of an end-to-end run (``benchmarks/end_to_end.py``, 2.65 M points, the analysis ahead of the
stream's end): 56-72 k minor faults and 1.8-1.9 s of system time in a 3.1-3.8 s analysis; with the
heap kept and 1 GB touched beforehand, about 400 faults, 0.02 s, and the analysis 2.0-2.3 s.

So the analysis child -- one process, one job at a time, nothing else in it -- runs on one malloc
arena (:func:`single_arena`) and, for a streamed job, asks glibc to keep what it frees (no ``mmap``
for large blocks, no trim) and tops up a reserve of touched free heap as the chunks arrive
(:class:`HeapReserve`: the child is idle then, waiting for the next pass); when the job ends the
usual policy returns and the free heap goes back to the system, so an idle worker does not hold its
last job's peak.

glibc only (the cell PC's Debian); elsewhere every call here does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math

import numpy as np

from drivers.runtime import release_freed_memory

__all__ = [
    "RESERVE_BYTES_PER_POINT",
    "HeapReserve",
    "free_heap_bytes",
    "single_arena",
]

#: the touched free heap kept ready per point of the cloud received so far: the analysis' working
#: set beyond the cloud itself measured 0.6-1.0 GB for 2.65 M points (250-380 B a point)
RESERVE_BYTES_PER_POINT = 400

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
_PAGE = 4096
# glibc's defaults: at most this many mmap'd blocks; the mmap threshold adapts up to 32 MiB on 64 bits
_DEFAULT_MMAP_MAX = 65536
_MMAP_CEILING = 32 << 20


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")
    ]  # fmt: skip


def _libc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.mallinfo2.restype = _Mallinfo2
    except (OSError, AttributeError):  # not glibc, or older than 2.33 (mallinfo2)
        return None
    return libc


_LIBC = _libc()


def _mallopt(*pairs: tuple[int, int]) -> bool:
    return _LIBC is not None and all(_LIBC.mallopt(param, value) == 1 for param, value in pairs)


def single_arena() -> bool:
    """One malloc arena for every thread of this process (the gaps' thread pool included), so the
    memory one thread frees serves the next: call before the process starts its threads."""
    return _mallopt((_M_ARENA_MAX, 1))


def free_heap_bytes() -> int | None:
    """Bytes the heap holds free (every one of them touched while it is kept), None without glibc."""
    return None if _LIBC is None else int(_LIBC.mallinfo2().fordblks)


class HeapReserve:
    """One job's kept heap: :meth:`start` makes the process keep what it frees (large blocks from
    the heap, not ``mmap``; no trim), :meth:`top_up` after each chunk of the stream keeps touched
    free heap at ``bytes_per_point`` x the points so far, :meth:`stop` restores glibc's usual
    policy and gives the free heap back.

    ``max_bytes`` below 2 GiB: glibc trims a free top larger than its trim threshold, an int.
    A job whose reserve would pass ``max_bytes`` (a 6 m plate: 31 M points) stops keeping at that
    point: a heap that never shrinks would add its fragmentation to that analysis' peak (12.75 GB),
    and on so long a scan the faults are a small share of the analysis anyway.
    """

    def __init__(self, max_bytes: int, bytes_per_point: int = RESERVE_BYTES_PER_POINT) -> None:
        self.max_bytes = max(int(max_bytes), 0)
        self.bytes_per_point = bytes_per_point
        self.touched_bytes = 0
        self.active = False
        self.gave_up = False

    def target(self, points: int) -> int:
        return min(self.max_bytes, self.bytes_per_point * max(points, 0))

    def start(self) -> bool:
        """Keep what the process frees from now on; True when in effect (glibc)."""
        self.active = self.max_bytes > 0 and _mallopt((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1))
        return self.active

    def top_up(self, points: int) -> int:
        """Touch what the reserve for ``points`` lacks; returns the bytes the heap grew by (new pages
        touched)."""
        if not self.active or _LIBC is None:
            return 0
        if self.bytes_per_point * points > self.max_bytes:
            self.gave_up = True
            self.stop()
            return 0
        need = self.target(points) - int(_LIBC.mallinfo2().fordblks)
        if need < 64 * _PAGE:  # nothing worth a system call
            return 0
        grown_from = _LIBC.mallinfo2().arena
        # the whole target in one block: the free heap is in pieces none of which holds it (else
        # it would hold the target), so malloc grows the heap's top by what the pieces lack; a block
        # of just the lack fits in a piece and grows nothing
        block = np.empty(math.ceil(self.target(points) / _PAGE) * _PAGE, dtype=np.uint8)
        block[::_PAGE] = 0  # one write a page faults the new ones in
        del block
        grown = _LIBC.mallinfo2().arena - grown_from
        self.touched_bytes += grown
        return grown

    def stop(self) -> None:
        """glibc's usual policy again (at its adaptive thresholds' ceiling), the free heap given back."""
        if self.active:
            _mallopt(
                (_M_MMAP_MAX, _DEFAULT_MMAP_MAX),
                (_M_MMAP_THRESHOLD, _MMAP_CEILING),
                (_M_TRIM_THRESHOLD, 2 * _MMAP_CEILING),
            )
            self.active = False
        release_freed_memory()
