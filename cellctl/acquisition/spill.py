"""Whole-scan arrays kept in a file instead of the process' memory (issue 42, bounded memory).

A 6000 x 2000 mm plate is about 340 000 profiles of 500 points: 170 M points, 2.2 GB of base-frame
``xyz_mm`` (float32) and ``valid``; a 12 000 x 3000 mm plate three times that. The daemon needs those
rows a pass at a time (the streamed publication) or a block of rows at a time (the whole-cloud
publication, the cloud files), never all at once, so :class:`SpillArray` keeps them in an unlinked
temporary file beside the job's raw files, memory-mapped: writing a row puts it in the page cache,
:func:`release` takes the pages of rows already written or read out of the process (``MADV_DONTNEED``
on a shared file mapping: the data stays in the file and the page cache, a later read maps it back),
and the kernel writes them back when it likes. The file is unlinked from its creation: nothing is left
behind when the process ends, whatever way it ends.

Precision: ``xyz_mm`` stays float32 on absolute base-frame coordinates. Its spacing is 2^-10 mm
(0.98 um) from 8192 to 16 384 mm, so a point of a 12 m plate (|x| < 16 384 mm) is within 0.49 um of
its float64 value, 1/20 of the 0.01 mm the acquisition's figures are stated in; under 8192 mm it is
within 0.24 um. No offset from a per-pass origin is needed.

The spill directory must be on a disk (the job store), not a tmpfs: there the pages would be memory.
"""

from __future__ import annotations

import mmap
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["ByteSpill", "SpillArray", "release"]

_PAGE = mmap.PAGESIZE


class SpillArray:
    """Rows of ``row_shape`` / ``dtype`` in an unlinked, memory-mapped temporary file in ``directory``.

    :attr:`array` is an ndarray of :attr:`capacity` rows over the mapping; :meth:`reserve` grows the
    file without copying anything (views of the previous mapping stay valid: the same file's pages).
    The file's blocks are allocated when it grows (``posix_fallocate``: a full disk raises
    ``OSError`` then, as a raw write does); rows never written cost no memory.
    """

    def __init__(self, directory: str | Path, row_shape: tuple[int, ...], dtype, rows: int) -> None:
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(int(s) for s in row_shape)
        self.row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * self.dtype.itemsize
        # open as long as the array: its mappings keep the data, the unlinked file's space goes with them
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".spill-")  # noqa: SIM115
        self.capacity = 0
        self.array = np.empty((0, *self.row_shape), self.dtype)
        self.reserve(rows)

    def reserve(self, rows: int) -> None:
        """At least ``rows`` rows of capacity (the file extended, mapped again; nothing copied)."""
        rows = max(int(rows), 1)
        if rows <= self.capacity:
            return
        size = max(rows * self.row_bytes, 1)
        # the blocks allocated now: a full disk is an OSError here (the raw files' disk-full path),
        # never a SIGBUS when a page of the mapping is written later
        os.posix_fallocate(self._file.fileno(), 0, size)
        mm = mmap.mmap(self._file.fileno(), size)
        self.array = np.frombuffer(
            mm, self.dtype, count=rows * self.row_bytes // self.dtype.itemsize
        ).reshape(rows, *self.row_shape)
        self.capacity = rows


class ByteSpill:
    """Byte strings (a streamed scan's encoded chunks) kept in an unlinked file in ``directory``:
    :meth:`keep` writes one and hands back a read-only memory-mapped view of it, which reads as the
    bytes did and costs memory only while read (:func:`release` after the read)."""

    def __init__(self, directory: str | Path) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".spill-")  # noqa: SIM115 (as SpillArray's)
        self._end = 0

    def keep(self, data: bytes | bytearray | memoryview) -> memoryview:
        """``data`` written to the file (OSError when the disk refuses it) and mapped back."""
        mv = memoryview(data).cast("B")
        n = mv.nbytes
        if not n:
            return memoryview(b"")
        at, fd = self._end, self._file.fileno()
        done = 0
        while done < n:
            done += os.pwrite(fd, mv[done:], at + done)
        self._end = at + -(-n // _PAGE) * _PAGE  # the next one page-aligned: a mapping starts on a page
        return memoryview(mmap.mmap(fd, n, access=mmap.ACCESS_READ, offset=at))


def _mapping(view: np.ndarray) -> tuple[mmap.mmap, int] | None:
    """The memory map under ``view`` and the address of its first byte, or None (an array in memory)."""
    root = view
    while isinstance(root.base, np.ndarray):
        root = root.base
    base = root.base
    if isinstance(base, memoryview):
        base = base.obj
    if not isinstance(base, mmap.mmap) or not len(base):
        return None
    # the mapping's own first byte (the root array may start further in: a decoded message's field)
    return base, np.frombuffer(base, np.uint8, count=1).__array_interface__["data"][0]


def release(*views: np.ndarray | memoryview) -> None:
    """Take the pages under each view out of the process' memory when it is a view of a
    :class:`SpillArray` or a :class:`ByteSpill`'s bytes (no-op for anything in memory). The data is
    kept: the next read maps it back."""
    for view in views:
        if isinstance(view, memoryview):
            view = np.frombuffer(view, np.uint8) if view.nbytes else None
        if not isinstance(view, np.ndarray) or not view.size:
            continue  # bytes, a bytearray, an empty view: in memory or nothing
        found = _mapping(view)
        if found is None:
            continue
        mm, start = found
        lo, hi = np.lib.array_utils.byte_bounds(view)
        lo = (lo - start) // _PAGE * _PAGE
        hi = min(-(-(hi - start) // _PAGE) * _PAGE, len(mm))
        if hi > lo:
            mm.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
