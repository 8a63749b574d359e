"""Append-only raw acquisition files: what arrives goes to disk first, in CRC-checked chunks.

A job directory holds ``job.json`` (the acquisition settings, written and fsync'ed before the first
byte of data) and one file per stream: ``profiles.craw`` (profile batches), ``robot.craw`` (joint
feedback samples), ``clock.craw`` (every clock fit the live assembly used) and ``events.craw``
(pass begin/end markers). Every *record* carries a job-wide sequence number, so a reader can replay
all streams in the exact order the live pipeline saw them.

File layout (little-endian)::

    file   := FILE_MAGIC(8) version u32 stream_len u32 stream_name  chunk*
    chunk  := CHUNK_MAGIC u32, payload_len u32, crc32(payload) u32, n_records u32, payload
    payload:= record*
    record := seq u64, kind u16, n_arrays u16, body_len u32, array*
    array  := name_len u8, name, dtype_len u8, dtype, ndim u8, shape u64*ndim, data

Crash bound: records are buffered in memory and, when ``flush_interval_s`` (default 0.2 s) has
passed since the oldest buffered record or ``chunk_bytes`` (default 4 MiB) are buffered, handed as
one chunk per stream to a writer thread that writes and ``fsync``s them. A ``kill -9`` therefore
loses at most the records of the last ``flush_interval_s`` plus the chunks still queued for the
disk (one write + fsync, milliseconds): at 200 profiles/s about 40 to 50 profiles, 25 mm of scan at
100 mm/s. A torn last chunk fails its length or CRC check and the reader stops there, keeping
everything before it. :attr:`RawWriter.durable_seq` tells which records are already on disk.
"""

from __future__ import annotations

import functools
import json
import math
import os
import queue
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

__all__ = [
    "STREAMS",
    "RawFormatError",
    "RawReader",
    "RawRecord",
    "RawWriter",
    "ReadReport",
    "pack_arrays",
    "read_job_meta",
    "unpack_arrays",
]

log = structlog.get_logger(__name__)

FILE_MAGIC = b"CELLRAW\x00"
VERSION = 1
CHUNK = struct.Struct("<IIII")  # magic, payload_len, crc32, n_records
CHUNK_MAGIC = 0x4B4E4843  # "CHNK"
RECORD = struct.Struct("<QHHI")  # seq, kind, n_arrays, body_len
MAX_CHUNK_BYTES = 1 << 30
STREAMS = ("profiles", "robot", "clock", "events")
JOB_META = "job.json"


class RawFormatError(ValueError):
    """A raw file or record cannot be parsed; names the file, the offset and the field."""


@functools.lru_cache(maxsize=1024)
def _array_header_of(name: str, dtype_str: str, shape: tuple[int, ...]) -> bytes:
    # cached: a job repeats the same few (name, dtype, shape) combinations thousands of times
    nb = name.encode()
    dt = dtype_str.encode()
    return (
        struct.pack("<B", len(nb))
        + nb
        + struct.pack("<B", len(dt))
        + dt
        + struct.pack(f"<B{len(shape)}Q", len(shape), *shape)
    )


def _array_header(name: str, arr: np.ndarray) -> bytes:
    return _array_header_of(name, arr.dtype.str, arr.shape)


def pack_arrays(arrays: dict[str, np.ndarray]) -> tuple[list[bytes | memoryview], int]:
    """Serialise named arrays without copying their data: ``(parts, total_bytes)``."""
    parts: list[bytes | memoryview] = []
    total = 0
    for name, a in arrays.items():
        arr = np.asarray(a)
        if not arr.flags.c_contiguous:  # (ascontiguousarray would turn a 0-d array into 1-d)
            arr = arr.copy(order="C")
        if arr.dtype.hasobject:
            raise RawFormatError(f"array {name!r} has dtype object, which cannot be stored")
        h = _array_header(name, arr)
        data = memoryview(arr).cast("B") if arr.size else b""
        parts += [h, data]
        total += len(h) + arr.nbytes
    return parts, total


def unpack_arrays(buf: memoryview, n_arrays: int, where: str = "") -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_arrays` (arrays are copied out of ``buf``)."""
    out: dict[str, np.ndarray] = {}
    pos = 0
    try:
        for _ in range(n_arrays):
            ln = buf[pos]
            name = bytes(buf[pos + 1 : pos + 1 + ln]).decode()
            pos += 1 + ln
            ld = buf[pos]
            dtype = np.dtype(bytes(buf[pos + 1 : pos + 1 + ld]).decode())
            pos += 1 + ld
            ndim = buf[pos]
            shape = struct.unpack_from(f"<{ndim}Q", buf, pos + 1)
            pos += 1 + 8 * ndim
            # math.prod: exact for any shape (np.prod costs ~10 us a call: a replay calls it per array)
            count = math.prod(shape)
            nbytes = count * dtype.itemsize
            if pos + nbytes > len(buf):
                raise RawFormatError(f"{where}: array {name!r} runs past the record end")
            out[name] = np.frombuffer(buf, dtype=dtype, count=count, offset=pos).reshape(shape).copy()
            pos += nbytes
    except (IndexError, struct.error, TypeError, UnicodeDecodeError) as exc:
        raise RawFormatError(f"{where}: malformed array table at byte {pos}: {exc}") from None
    return out


@dataclass(frozen=True, slots=True)
class RawRecord:
    """One stored record: job-wide ``seq``, ``stream`` name, ``kind`` code and its arrays."""

    seq: int
    stream: str
    kind: int
    arrays: dict[str, np.ndarray]


@dataclass
class _StreamBuffer:
    fd: int
    parts: list[bytes | memoryview] = field(default_factory=list)
    n_records: int = 0
    n_bytes: int = 0
    crc: int = 0
    max_seq: int = -1
    n_items: int = 0  # what the records hold (profiles of a profile batch), buffered


#: modes of a job's raw directory and files (group-readable for QA and backup, nobody else)
RAW_DIR_MODE = 0o750
RAW_FILE_MODE = 0o640


class RawWriter:
    """Appends records to a job's raw files with chunked, fsync'ed writes.

    Args:
        job_dir: created if missing; must not already hold raw files (append-only, never overwrite).
        meta: JSON-able acquisition settings, stored as ``job.json`` before any data.
        flush_interval_s: longest time a record stays in memory (the crash-loss bound).
        chunk_bytes: flush earlier when this much is buffered.
        fsync: False only for benchmarks of the pure encoding cost.
        clock_s: time source for the flush age (``time.monotonic``).
        max_queued_chunks: flushes waiting for the writer thread before :meth:`flush` blocks.
    """

    def __init__(
        self,
        job_dir: str | Path,
        meta: dict[str, Any],
        *,
        flush_interval_s: float = 0.2,
        chunk_bytes: int = 4 << 20,
        fsync: bool = True,
        clock_s=time.monotonic,
        max_queued_chunks: int = 8,
    ) -> None:
        self.job_dir = Path(job_dir)
        # a shipyard's raw scans are confidential: owner read/write, group read, nobody else (as the
        # job store's directories, cellctl/jobstore/jobs.py DIR_MODE), whatever the umask
        self.job_dir.mkdir(mode=RAW_DIR_MODE, parents=True, exist_ok=True)
        os.chmod(self.job_dir, RAW_DIR_MODE)
        if any((self.job_dir / f"{s}.craw").exists() for s in STREAMS):
            raise FileExistsError(
                f"{self.job_dir} already holds raw files; a job's raw data is never overwritten"
            )
        self.flush_interval_s = flush_interval_s
        self.chunk_bytes = chunk_bytes
        self._fsync = fsync
        self._clock_s = clock_s
        self._seq = 0
        self._oldest_s: float | None = None
        self.chunks_written = 0
        # items (profiles of the "profiles" stream) taken in and on disk (written and fsync'ed), per
        # stream: after a failed write the difference is what never reached the disk
        self.items_in: dict[str, int] = dict.fromkeys(STREAMS, 0)
        self.items_written: dict[str, int] = dict.fromkeys(STREAMS, 0)
        self.bytes_written = 0
        tmp = self.job_dir / (JOB_META + ".tmp")
        tmp.write_text(json.dumps(meta, indent=2, sort_keys=True))
        os.chmod(tmp, RAW_FILE_MODE)
        self._sync_path(tmp)
        os.replace(tmp, self.job_dir / JOB_META)
        self._streams: dict[str, _StreamBuffer] = {}
        for s in STREAMS:
            fd = os.open(
                self.job_dir / f"{s}.craw", os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, RAW_FILE_MODE
            )
            os.fchmod(fd, RAW_FILE_MODE)  # the umask may have taken more
            name = s.encode()
            os.write(fd, FILE_MAGIC + struct.pack("<II", VERSION, len(name)) + name)
            if fsync:
                os.fsync(fd)
            self._streams[s] = _StreamBuffer(fd)
        self._sync_dir()
        self._closed = False
        self.durable_seq = -1  # every record up to this sequence number is fsync'ed
        self._thread_error: OSError | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=max_queued_chunks)
        self._thread = threading.Thread(target=self._write_loop, name="rawstore-writer", daemon=True)
        self._thread.start()

    def _sync_path(self, path: Path) -> None:
        if not self._fsync:
            return
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _sync_dir(self) -> None:
        # the new directory entries must be durable too, or a crash can lose whole files
        if self._fsync:
            self._sync_path(self.job_dir)

    @property
    def next_seq(self) -> int:
        """Sequence number the next record gets."""
        return self._seq

    def append(self, stream: str, kind: int, arrays: dict[str, np.ndarray], items: int = 1) -> int:
        """Buffer one record (holding ``items`` items: the profiles of a batch); flushes when due.
        Returns the record's sequence number."""
        if self._closed:
            raise RawFormatError(f"{self.job_dir}: writer is closed")
        buf = self._streams.get(stream)
        if buf is None:
            raise RawFormatError(f"unknown stream {stream!r}; known: {STREAMS}")
        parts, nbytes = pack_arrays(arrays)
        seq = self._seq
        self._seq += 1
        # one copy: the caller may reuse its arrays once append returns, the writer thread may not
        record = b"".join([RECORD.pack(seq, kind, len(arrays), nbytes), *parts])
        buf.crc = zlib.crc32(record, buf.crc)
        buf.parts.append(record)
        buf.n_records += 1
        buf.n_bytes += len(record)
        buf.n_items += items
        self.items_in[stream] += items
        buf.max_seq = seq
        now = self._clock_s()
        if self._oldest_s is None:
            self._oldest_s = now
        if buf.n_bytes >= self.chunk_bytes or now - self._oldest_s >= self.flush_interval_s:
            self.flush()
        return seq

    def maybe_flush(self) -> None:
        """Flush if the oldest buffered record is older than ``flush_interval_s`` (call when idle)."""
        if self._oldest_s is not None and self._clock_s() - self._oldest_s >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Hand every buffered record, as one chunk per stream, to the writer thread (write + fsync).

        Blocks only when ``max_queued_chunks`` chunks are already waiting for the disk.
        """
        self._raise_thread_error()
        jobs = []
        for name, buf in self._streams.items():
            if not buf.n_records:
                continue
            header = CHUNK.pack(CHUNK_MAGIC, buf.n_bytes, buf.crc, buf.n_records)
            jobs.append(
                (buf.fd, [header, *buf.parts], len(header) + buf.n_bytes, buf.max_seq, name, buf.n_items)
            )
            buf.parts, buf.n_records, buf.n_bytes, buf.crc, buf.n_items = [], 0, 0, 0, 0
        self._oldest_s = None
        if jobs:
            self._queue.put(jobs)

    def _write_loop(self) -> None:
        # Runs in the writer thread: the fsync (milliseconds on a real disk) stays off the ingest path.
        while True:
            jobs = self._queue.get()
            if jobs is None:
                return
            try:
                for fd, iov, total, max_seq, name, n_items in jobs:
                    written = os.writev(fd, iov) if len(iov) <= 1024 else 0
                    if written < total:  # short write (large chunk, signal): finish plainly
                        rest = memoryview(b"".join(iov))[written:]
                        while rest:
                            rest = rest[os.write(fd, rest) :]
                    if self._fsync:
                        os.fsync(fd)
                    self.chunks_written += 1
                    self.bytes_written += total
                    self.items_written[name] += n_items
                    self.durable_seq = max(self.durable_seq, max_seq)
            except OSError as exc:
                self._thread_error = exc
                log.error("rawstore_write_failed", job=str(self.job_dir), error=str(exc))
                return

    def _raise_thread_error(self) -> None:
        if self._thread_error is not None:
            written, taken = self.items_written["profiles"], self.items_in["profiles"]
            err = OSError(
                f"{self.job_dir}: writing raw data failed: {self._thread_error}; {written} profiles are "
                f"on disk, {taken - written} taken in after them were lost"
            )
            err.profiles_written, err.profiles_lost = written, taken - written  # type: ignore[attr-defined]
            raise err from self._thread_error

    def close(self) -> None:
        """Flush, wait until everything is on disk, and close every file."""
        if self._closed:
            return
        self.flush()
        self._queue.put(None)
        self._thread.join()
        for buf in self._streams.values():
            os.close(buf.fd)
        self._closed = True
        self._raise_thread_error()

    def __enter__(self) -> RawWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class ReadReport:
    """What a reader found: per stream ``chunks``, ``records`` and ``torn_bytes`` ignored at the end;
    ``records_used`` in the gap-free prefix; readable ``problems``."""

    chunks: dict[str, int] = field(default_factory=dict)
    records: dict[str, int] = field(default_factory=dict)
    torn_bytes: dict[str, int] = field(default_factory=dict)
    records_used: int = 0
    problems: list[str] = field(default_factory=list)


def read_job_meta(job_dir: str | Path) -> dict[str, Any]:
    """The job's ``job.json``."""
    path = Path(job_dir) / JOB_META
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise RawFormatError(f"{path}: missing; not a job directory") from None
    except json.JSONDecodeError as exc:
        raise RawFormatError(f"{path}: not valid JSON ({exc})") from None


def _first_valid_chunk(data: memoryview, start: int) -> int:
    """Byte offset of the first chunk at or after ``start`` whose magic, length and CRC hold (-1: none)."""
    raw = bytes(data)
    magic = struct.pack("<I", CHUNK_MAGIC)
    pos = raw.find(magic, start)
    while pos >= 0:
        if len(raw) - pos >= CHUNK.size:
            _m, plen, crc, _n = CHUNK.unpack_from(raw, pos)
            body = pos + CHUNK.size
            if (
                plen <= MAX_CHUNK_BYTES
                and body + plen <= len(raw)
                and zlib.crc32(raw[body : body + plen]) == crc
            ):
                return pos
        pos = raw.find(magic, pos + 1)
    return -1


class RawReader:
    """Reads a job's raw files; stops each stream at the first incomplete or corrupt chunk."""

    def __init__(self, job_dir: str | Path) -> None:
        self.job_dir = Path(job_dir)
        self.meta = read_job_meta(self.job_dir)
        self.report = ReadReport()

    def _stream_records(self, stream: str) -> list[RawRecord]:
        path = self.job_dir / f"{stream}.craw"
        try:
            data = memoryview(path.read_bytes())
        except FileNotFoundError:
            self.report.problems.append(f"{path.name}: missing")
            return []
        name = stream.encode()
        head = FILE_MAGIC + struct.pack("<II", VERSION, len(name)) + name
        pos = len(head)
        if bytes(data[: len(head)]) != head:
            # A damaged header loses nothing else: the chunks carry their own magic and CRC, so the
            # reader resumes at the first chunk whose CRC holds (and the other streams are unaffected).
            found = _first_valid_chunk(data, 0)
            self.report.problems.append(
                f"{path.name}: bad file header {bytes(data[: len(head)]).hex()}"
                + (f"; resumed at the chunk at byte {found}" if found >= 0 else "; no chunk found after it")
            )
            if found < 0:
                self.report.chunks[stream] = 0
                self.report.records[stream] = 0
                self.report.torn_bytes[stream] = len(data)
                return []
            pos = found
        out: list[RawRecord] = []
        chunks = 0
        while pos < len(data):
            if len(data) - pos < CHUNK.size:
                self.report.problems.append(f"{path.name}: torn chunk header at byte {pos}")
                break
            magic, plen, crc, nrec = CHUNK.unpack_from(data, pos)
            if magic != CHUNK_MAGIC or plen > MAX_CHUNK_BYTES:
                self.report.problems.append(f"{path.name}: bad chunk magic/length at byte {pos}")
                break
            start = pos + CHUNK.size
            if start + plen > len(data):
                self.report.problems.append(
                    f"{path.name}: torn chunk at byte {pos} ({len(data) - start} of {plen} bytes)"
                )
                break
            payload = data[start : start + plen]
            if zlib.crc32(payload) != crc:
                self.report.problems.append(f"{path.name}: CRC mismatch in chunk at byte {pos}")
                break
            out.extend(self._records(payload, nrec, stream, f"{path.name}@{pos}"))
            chunks += 1
            pos = start + plen
        self.report.chunks[stream] = chunks
        self.report.records[stream] = len(out)
        self.report.torn_bytes[stream] = len(data) - pos
        return out

    @staticmethod
    def _records(payload: memoryview, nrec: int, stream: str, where: str) -> Iterator[RawRecord]:
        pos = 0
        for _ in range(nrec):
            if pos + RECORD.size > len(payload):
                raise RawFormatError(f"{where}: record header past the chunk end")
            seq, kind, n_arrays, blen = RECORD.unpack_from(payload, pos)
            body = payload[pos + RECORD.size : pos + RECORD.size + blen]
            if len(body) != blen:
                raise RawFormatError(f"{where}: record {seq} body_len {blen} past the chunk end")
            yield RawRecord(seq, stream, kind, unpack_arrays(body, n_arrays, f"{where} record {seq}"))
            pos += RECORD.size + blen

    def records(self) -> list[RawRecord]:
        """The intact records of every stream in job-wide sequence order, up to the first missing one.

        A crash during a flush can leave one stream's chunk on disk and another's not; keeping only
        the gap-free prefix makes the replay exactly what the live pipeline had processed by then.
        """
        allrec: list[RawRecord] = []
        for s in STREAMS:
            allrec.extend(self._stream_records(s))
        allrec.sort(key=lambda r: r.seq)
        seqs = np.fromiter((r.seq for r in allrec), dtype=np.int64, count=len(allrec))
        gap = np.nonzero(seqs != np.arange(len(seqs)))[0]
        if gap.size:
            cut = int(gap[0])
            self.report.problems.append(
                f"record {cut} missing (lost in the crash); {len(allrec) - cut} later records ignored"
            )
            allrec = allrec[:cut]
        self.report.records_used = len(allrec)
        return allrec
