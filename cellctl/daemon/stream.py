"""The scan's cloud streamed to the analysis pass by pass while the plate is scanned (issue 22).

:class:`ScanStream` follows the acquisition of a scan (:meth:`Acquisition.batches_since`, every
``poll_s``): when a pass has ended (a row of the pass followed by a row of transit or of another
pass, :func:`~cellctl.acquisition.publish.pass_end_cut`), the rows assembled since the previous cut
-- the transit before the pass and the pass itself -- are thinned and encoded like the whole cloud
(:func:`~cellctl.acquisition.publish.encode_scan`, exposure times from the scan's first profile) and
handed to the dispatcher as the next chunk (:meth:`Dispatcher.stream_chunk`), which sends it on to
the worker holding the job. The raw records of those rows are on disk (``RawWriter.durable_seq``)
before the chunk goes out. :meth:`finish` sends the rows after the last cut and ends the stream.

The chunks, concatenated in order, are point for point the cloud the whole-cloud hand-over would
have published (the same rows, the same thinning, the same times): the job's ``cloud.bin`` is
their concatenation, and a re-analysis (``control/reanalyse``) still publishes a cloud whole.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable

import numpy as np
import structlog

from cellctl.acquisition.assembly import AssembledBatch, AssembledScan
from cellctl.acquisition.pipeline import Acquisition
from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan, pass_end_cut
from cellctl.acquisition.spill import ByteSpill, release
from cellctl.api.cloud_codec import CloudMeta
from cellctl.api.models import ReportEnvelope
from cellctl.daemon.dispatch import Dispatcher
from cellctl.jobstore.rawstore import RawWriter

__all__ = ["ScanStream"]

log = structlog.get_logger(__name__)


class ScanStream:
    """One scan's cloud, chunk by chunk, to the dispatcher's streamed job ``job_id``.

    :meth:`follow` starts following an acquisition; :meth:`finish` (after the acquisition finished
    and its raw files closed) publishes the rest and ends the stream; :meth:`abandon` gives the job
    up (the scan ended early). ``future`` resolves with the worker's report.
    """

    def __init__(
        self,
        dispatcher: Dispatcher,
        future: asyncio.Future[ReportEnvelope],
        *,
        job_id: str,
        plate_id: str,
        settings: PublishSettings,
        first_edge_pass: int | None,
        meta: CloudMeta,
        last_pass: int | None = None,
        poll_s: float = 0.05,
        durable_timeout_s: float = 5.0,
        on_abandon: Callable[[], None] | None = None,
    ) -> None:
        self.dispatcher = dispatcher
        self.future = future
        self.payloads: list[bytes | bytearray | memoryview] = []  # the chunks sent, once the stream has ended
        self.job_id = job_id
        self.plate_id = plate_id
        self.settings = settings
        self.first_edge_pass = first_edge_pass
        self.last_pass = last_pass
        self.meta = meta
        self.poll_s = poll_s
        self.durable_timeout_s = durable_timeout_s
        self._on_abandon = on_abandon
        self.points = 0
        self.bytes = 0
        self.chunks = 0
        self.encode_s = 0.0
        self.finished = False
        self._acq: Acquisition | None = None
        self._writer: RawWriter | None = None
        self._spill: ByteSpill | None = None
        self._taken = 0
        self._pending: list[AssembledBatch] = []
        self._t0_ns: int | None = None
        self._width = 0
        self._task: asyncio.Task[None] | None = None
        self._lock = asyncio.Lock()

    def follow(self, acq: Acquisition, writer: RawWriter | None) -> None:
        """Follow ``acq`` (its raw files written by ``writer``) until :meth:`finish`."""
        self._acq, self._writer = acq, writer
        # the chunks sent are kept (a new worker gets them all, cloud.bin is made of them) in a file
        # beside the raw ones, not in memory: a 6 m plate's 0.93 GB, a 12 m plate's 2.8 GB
        if writer is not None:
            try:
                self._spill = ByteSpill(writer.job_dir)
            except OSError as exc:
                log.warning("stream_spill_unavailable", job_id=self.job_id, error=str(exc))
        self._task = asyncio.get_running_loop().create_task(self._follow(), name=f"stream-{self.job_id}")

    async def _follow(self) -> None:
        # every poll_s: the last pass's chunk starts the analysis, so its wait counts in the time to
        # the report (at 0.2 s the chunk went out 0.14 s after the pass on the sail); a poll looks
        # at the new rows' pass ids only (a pass is about 1 400 rows), well under a millisecond
        while True:
            await asyncio.sleep(self.poll_s)
            try:
                await self._cut(final=False)
            except asyncio.CancelledError:
                raise
            except Exception:  # a chunk that cannot be made: finish() sends those rows at the end
                log.exception("stream_chunk_failed", job_id=self.job_id)

    def _take(self) -> None:
        assert self._acq is not None
        new = self._acq.batches_since(self._taken)
        self._taken += len(new)
        self._pending.extend(new)

    async def _cut(self, *, final: bool) -> None:
        async with self._lock:
            self._take()
            if not self._pending:
                return
            # only the pass ids are looked at until a pass has ended: no copy of the points
            pass_id = np.concatenate([b.pass_id for b in self._pending])
            cut = (len(pass_id), -1) if final else pass_end_cut(pass_id)
            if cut is None:
                return
            n, pass_index = cut
            if self._writer is not None and not final:
                await self._durable()
            head, self._pending = _split(self._pending, n)  # a cut inside a batch splits it
            await self._publish(AssembledScan.concat(head), pass_index)
            # a spilled scan's rows read for the chunk go out of memory again (cellctl.acquisition.spill)
            release(*(a for b in head for a in (b.xyz_mm, b.valid)))

    async def _durable(self) -> None:
        """Wait until every raw record written so far is fsync'ed (acquired data reaches disk first)."""
        w = self._writer
        assert w is not None
        target = w.next_seq - 1
        w.flush()
        t0 = time.monotonic()
        while w.durable_seq < target:
            if time.monotonic() - t0 > self.durable_timeout_s:
                log.warning("stream_raw_not_durable", job_id=self.job_id, seq=target, durable=w.durable_seq)
                return
            await asyncio.sleep(0.005)

    async def _publish(self, rows: AssembledScan, pass_index: int) -> None:
        if not len(rows):
            return
        if self._t0_ns is None:
            self._t0_ns = int(rows.t_ns.min())  # the scan's first profile: times as in the whole cloud
        t0 = time.perf_counter()
        steps = column_steps(rows.pass_id, self.first_edge_pass, self.settings)
        payload, n = await asyncio.to_thread(
            encode_scan, rows, job_id=self.job_id, plate_id=self.plate_id, column_step=steps,
            meta=self.meta, t0_ns=self._t0_ns,
        )  # fmt: skip
        self.encode_s += time.perf_counter() - t0
        if self._spill is not None:
            try:
                payload = await asyncio.to_thread(self._spill.keep, payload)
            except OSError as exc:  # a full disk: this chunk stays in memory (the raw files say the rest)
                log.warning("stream_chunk_not_spilled", job_id=self.job_id, error=str(exc))
        seq = self.dispatcher.stream_chunk(
            self.job_id,
            pass_index,
            payload,
            n,
            last_pass=self.last_pass is not None and pass_index == self.last_pass,
        )
        release(payload)  # read once for its digest; the dispatcher's send reads it again
        self.points += n
        self.bytes += len(payload)
        self.chunks += 1
        log.info("stream_chunk", job_id=self.job_id, seq=seq, pass_index=pass_index, rows=len(rows), points=n)

    async def finish(self) -> None:
        """The scan is complete (acquisition finished, raw files closed): the rows after the last cut
        go out as the last chunk and the stream ends."""
        await self._stop_following()
        await self._cut(final=True)
        # the chunks as sent, kept here for cloud.bin: once the stream has ended the worker may
        # report (and the dispatcher forget the job) before the handover asks for them
        self.payloads = self.dispatcher.stream_payloads(self.job_id)
        self.dispatcher.end_stream(self.job_id)
        self.finished = True

    async def abandon(self, reason: str) -> None:
        """The scan ended early: no report will come from this stream."""
        await self._stop_following()
        if not self.finished:
            self.dispatcher.abandon(self.job_id, reason)
            self.finished = True
            if self.future.done() and not self.future.cancelled():
                self.future.exception()  # retrieved: nobody awaits an abandoned stream
            if self._on_abandon is not None:
                self._on_abandon()
            log.info("stream_abandoned", job_id=self.job_id, reason=reason, chunks=self.chunks)

    async def _stop_following(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None


def _split(batches: list[AssembledBatch], n: int) -> tuple[list[AssembledBatch], list[AssembledBatch]]:
    """The batches' first ``n`` rows and the rest, as batches (one split where ``n`` falls inside)."""
    head: list[AssembledBatch] = []
    tail: list[AssembledBatch] = []
    seen = 0
    for b in batches:
        size = len(b.t_ns)
        if seen + size <= n:
            head.append(b)
        elif seen >= n:
            tail.append(b)
        else:
            k = n - seen
            head.append(AssembledBatch(*(getattr(b, f)[:k] for f in AssembledBatch.__slots__)))
            tail.append(AssembledBatch(*(getattr(b, f)[k:] for f in AssembledBatch.__slots__)))
        seen += size
    return head, tail
