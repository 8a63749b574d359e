"""Binary search in a ring buffer of non-decreasing times (the feedback and trajectory records).

A full ring holds its samples in two sorted runs: ``[start, capacity)`` (the older) then
``[0, start)``. Searching the runs and copying only the slice a caller needs costs O(log n + k);
copying the whole ring per query cost milliseconds at 30k-130k samples, many times a second.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ring_indices", "ring_search", "ring_start"]


def ring_start(next_slot: int, count: int, capacity: int) -> int:
    """Slot of the oldest sample."""
    return 0 if count < capacity else next_slot


def ring_search(t: np.ndarray, start: int, count: int, x: float, side: str = "left") -> int:
    """``np.searchsorted`` of ``x`` in the ring's samples taken oldest first -> a position 0..count."""
    cap = t.shape[0]
    run1 = t[start : start + min(count, cap - start)]
    i = int(np.searchsorted(run1, x, side=side))  # type: ignore[call-overload]
    if i < run1.shape[0] or run1.shape[0] == count:
        return i
    return run1.shape[0] + int(np.searchsorted(t[: count - run1.shape[0]], x, side=side))  # type: ignore[call-overload]


def ring_indices(start: int, v0: int, v1: int, capacity: int) -> np.ndarray:
    """Slots of the samples at positions ``v0..v1-1`` (oldest first)."""
    return (start + np.arange(v0, v1)) % capacity
