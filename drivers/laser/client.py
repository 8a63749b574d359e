"""asyncio client of the HD8 profile protocol: the HD8's :class:`ProfileSource` implementation.

Two TCP connections, as in docs/hd8-protocol.md: control (request/reply commands) and data (frame
groups pushed by the sensor). The data connection is supervised: when it breaks (EOF, reset, a framing
error) the client reconnects with exponential backoff and SUBSCRIBEs from the frame after the last one
it delivered, so the sensor's ring buffer fills the hole and nothing is duplicated or reordered
(anything older that still arrives is dropped by frame index and counted).

Decoding is whole-batch numpy (:func:`drivers.laser.protocol.decode_groups`); a group that fails
validation is skipped, counted and logged (rate limited), and the stream carries on.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.laser import protocol as P
from drivers.laser.source import ProfileBatch, ProfileSource, SourceEventKind
from drivers.runtime import RateLimitedLog

__all__ = ["HD8Client", "HD8ClientConfig"]

log = structlog.get_logger(__name__)

#: how long close() waits for its tasks to end after cancelling them
_CLOSE_TIMEOUT_S = 2.0

_CLOSED = object()


class HD8ClientConfig(BaseModel):
    """Tuning of the HD8 client (all optional)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: profiles held for the consumer; a batch that would exceed it is dropped and counted (overflow)
    buffer_profiles: int = Field(20_000, gt=0)
    connect_timeout_s: float = Field(2.0, gt=0)
    command_timeout_s: float = Field(2.0, gt=0)
    reconnect_initial_s: float = Field(0.05, gt=0)
    reconnect_max_s: float = Field(2.0, gt=0)
    #: no frame for this long while running -> a STALLED event (RESUMED when frames return)
    watchdog_timeout_s: float = Field(0.5, gt=0)
    keepalive_interval_s: float = Field(1.0, gt=0)
    read_chunk_bytes: int = Field(1 << 20, gt=0)
    #: after a reconnect, ask the sensor to replay from the next undelivered frame
    resume: bool = True


class HD8Client(ProfileSource):
    """Client of one HD8 (or anything speaking the HD8 profile protocol).

    Args:
        host: sensor (or shim / simulator) address.
        control_port, data_port: its TCP ports.
        config: see :class:`HD8ClientConfig`.

    After :meth:`connect`, :attr:`info` holds the sensor's :class:`~drivers.laser.protocol.SensorInfo`.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        control_port: int = 3190,
        data_port: int = 3196,
        *,
        config: HD8ClientConfig | None = None,
    ) -> None:
        super().__init__()
        self.host = host
        self.control_port = control_port
        self.data_port = data_port
        self.config = config or HD8ClientConfig()
        self.info: P.SensorInfo | None = None
        self._queue: asyncio.Queue[Any] = asyncio.Queue()
        self._queued_profiles = 0
        self._ctl: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._ctl_framer = P.MessageFramer(max_message_size=4096)
        self._ctl_lock = asyncio.Lock()
        self._want_running = False
        self._closed = False
        self._tasks: list[asyncio.Task[None]] = []
        self._data_writer: asyncio.StreamWriter | None = None
        self._data_reader: asyncio.StreamReader | None = None
        self._data_seen = False
        self._last_frame_ns = 0
        self._stalled = False
        self._ratelog = RateLimitedLog(log)

    # ------------------------------------------------------------------------------- control

    async def connect(self) -> None:
        """Open the control connection and read the sensor's identity (GET_INFO)."""
        await self._open_control()
        self.info = P.SensorInfo.from_bytes(await self.command(P.CommandId.GET_INFO))
        log.info("hd8_connected", host=self.host, model=self.info.model, serial=self.info.serial)

    async def _open_control(self) -> None:
        await self._close_control()
        try:
            self._ctl = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.control_port), self.config.connect_timeout_s
            )
        except TimeoutError:
            raise P.ProtocolTimeout(f"control connect to {self.host}:{self.control_port} timed out") from None
        self._ctl_framer = P.MessageFramer(max_message_size=4096)

    async def _close_control(self) -> None:
        if self._ctl is not None:
            self._ctl[1].transport.abort()
            self._ctl = None

    async def command(self, command: P.CommandId, payload: bytes = b"") -> bytes:
        """Send one control command and return the reply payload.

        Raises:
            CommandError: the sensor replied with a status other than OK (the message names it).
            ProtocolTimeout: no reply within ``command_timeout_s``.
            ConnectionError: the control connection is not open or broke.
        """
        async with self._ctl_lock:
            if self._ctl is None:
                raise ConnectionError("HD8 control connection is not open")
            reader, writer = self._ctl
            writer.write(P.encode_command(command, payload))
            try:
                async with asyncio.timeout(self.config.command_timeout_s):
                    msg = await self._read_reply(reader)
            except TimeoutError:
                await self._close_control()
                raise P.ProtocolTimeout(
                    f"no reply to {command.name} within {self.config.command_timeout_s} s"
                ) from None
            except (ConnectionError, P.FramingError, asyncio.IncompleteReadError):
                await self._close_control()
                raise
        reply = P.decode_reply(msg)
        if reply.command != command:
            raise P.DecodeError(
                f"reply to 0x{reply.command:04x} while waiting for {command.name}",
                field="command",
                data=msg.data,
            )
        if reply.status != P.Status.OK:
            raise P.CommandError(command, reply.status, reply.payload.decode("ascii", "replace"))
        return reply.payload

    async def _read_reply(self, reader: asyncio.StreamReader) -> P.Message:
        while True:
            chunk = await reader.read(4096)
            if not chunk:
                raise ConnectionError("HD8 control connection closed by the sensor")
            msgs = self._ctl_framer.feed(chunk)
            if msgs:
                if len(msgs) > 1:
                    raise P.DecodeError(
                        f"{len(msgs)} replies to one command", field="reply", data=msgs[1].data
                    )
                return msgs[0]

    async def configure(
        self,
        *,
        rate_hz: float | None = None,
        exposure_ns: int | None = None,
        trigger_mode: P.TriggerMode | int | None = None,
        profile_format: P.ProfileFormat | str | None = None,
    ) -> None:
        """Apply settings; those left None are not touched. The sensor must be stopped for all but exposure.

        Args:
            rate_hz: profile rate (sent in mHz).
            exposure_ns: exposure time.
            trigger_mode: :class:`~drivers.laser.protocol.TriggerMode`.
            profile_format: ``"uniform"`` / ``"points"`` or a :class:`~drivers.laser.protocol.ProfileFormat`.
        """
        u32 = P.U32.pack
        if rate_hz is not None and exposure_ns is not None:
            # The sensor checks exposure < period at each step: a shorter period needs the shorter
            # exposure first, a longer exposure needs the longer period first.
            try:
                await self.command(P.CommandId.SET_EXPOSURE, u32(int(exposure_ns)))
            except P.CommandError as exc:
                if exc.status != P.Status.INVALID_PARAMETER:
                    raise
                await self.command(P.CommandId.SET_RATE, u32(round(rate_hz * 1000)))
                await self.command(P.CommandId.SET_EXPOSURE, u32(int(exposure_ns)))
            else:
                await self.command(P.CommandId.SET_RATE, u32(round(rate_hz * 1000)))
        elif rate_hz is not None:
            await self.command(P.CommandId.SET_RATE, u32(round(rate_hz * 1000)))
        elif exposure_ns is not None:
            await self.command(P.CommandId.SET_EXPOSURE, u32(int(exposure_ns)))
        if trigger_mode is not None:
            await self.command(P.CommandId.SET_TRIGGER_MODE, u32(int(trigger_mode)))
        if profile_format is not None:
            fmt = (
                P.ProfileFormat[profile_format.upper()] if isinstance(profile_format, str) else profile_format
            )
            await self.command(P.CommandId.SET_PROFILE_FORMAT, u32(int(fmt)))

    async def get_timestamp(self) -> P.TimestampReply:
        """The sensor clock now (for an initial clock-offset guess)."""
        return P.TimestampReply.from_bytes(await self.command(P.CommandId.GET_TIMESTAMP))

    async def reset_timestamp(self) -> None:
        """Zero the HD8 millisecond counter (``LSHD6_ReSetTimeStamp`` on the real sensor)."""
        await self.command(P.CommandId.RESET_TIMESTAMP)

    async def get_state(self) -> P.StateReply:
        """Run state, next frame index and oldest replayable frame."""
        return P.StateReply.from_bytes(await self.command(P.CommandId.GET_STATE))

    # ------------------------------------------------------------------------------ streaming

    async def start(self) -> None:
        """Open the data connection, START the sensor and begin delivering batches."""
        if self._closed:
            raise RuntimeError("HD8Client is closed")
        self._want_running = True
        self._last_frame_ns = time.monotonic_ns()
        if not self._tasks:
            opened = asyncio.get_running_loop().create_future()
            self._tasks = [
                asyncio.create_task(self._data_supervisor(opened), name="hd8-data"),
                asyncio.create_task(self._watchdog(), name="hd8-watchdog"),
                asyncio.create_task(self._keepalive(), name="hd8-keepalive"),
            ]
            try:
                await opened  # subscribe before START, so the first frame is not missed
            except BaseException:
                for t in self._tasks:
                    t.cancel()
                await asyncio.gather(*self._tasks, return_exceptions=True)
                self._tasks = []
                raise
        await self.command(P.CommandId.START)

    async def stop(self) -> None:
        """STOP the sensor. Frames in flight are still delivered; the data connection stays open."""
        self._want_running = False
        if self._ctl is not None:
            await self.command(P.CommandId.STOP)

    async def close(self) -> None:
        """Close both connections and end every iteration (buffered batches are still yielded first)."""
        if self._closed:
            return
        self._closed = True
        self._want_running = False
        for t in self._tasks:
            t.cancel()
        if self._tasks:
            # Bounded: a task that ignores its cancellation is logged, never waited for forever.
            ended, stuck = await asyncio.wait(self._tasks, timeout=_CLOSE_TIMEOUT_S)
            for t in ended:
                if not t.cancelled() and t.exception() is not None:
                    log.warning("hd8_task_failed_at_close", task=t.get_name(), error=repr(t.exception()))
            if stuck:
                log.error("hd8_close_tasks_stuck", tasks=sorted(t.get_name() for t in stuck))
        self._tasks = []
        if self._data_writer is not None:
            self._data_writer.transport.abort()
        await self._close_control()
        self._queue.put_nowait(_CLOSED)

    async def __aiter__(self) -> AsyncIterator[ProfileBatch]:
        """Yield batches in frame-index order until :meth:`close`."""
        while True:
            item = await self._queue.get()
            if item is _CLOSED:
                self._queue.put_nowait(_CLOSED)  # let other iterators end too
                return
            self._queued_profiles -= len(item)
            yield item

    # -------------------------------------------------------------------------------- tasks

    async def _data_supervisor(self, opened: asyncio.Future[None]) -> None:
        cfg = self.config
        backoff = cfg.reconnect_initial_s
        outage = False
        while not self._closed:
            try:
                await self._open_data()
                if not opened.done():
                    opened.set_result(None)
                if outage:
                    await self._restart_if_needed()  # raises if control is unreachable: retry later
                    self.stats.reconnects += 1
                    self._emit(SourceEventKind.RECONNECTED, resume_from=self.stats.last_frame_index + 1)
                    log.info("hd8_reconnected", resume_from=self.stats.last_frame_index + 1)
                    outage = False
                self._data_seen = False
                await self._read_data()
                raise ConnectionError("HD8 data connection closed by the sensor")
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                # OSError, ProtocolError, timeouts are the expected ones; anything else is a bug, but
                # the acquisition must outlive it: log it with its traceback and reconnect.
                if not isinstance(exc, (OSError, P.ProtocolError, asyncio.IncompleteReadError, TimeoutError)):
                    log.exception("hd8_data_task_error")
                if not opened.done():
                    opened.set_exception(exc)
                    return
                if not outage:
                    outage = True
                    self._emit(SourceEventKind.DISCONNECTED, error=str(exc))
                    log.warning(
                        "hd8_data_disconnected", error=str(exc), last_frame=self.stats.last_frame_index
                    )
                if self._data_writer is not None:
                    self._data_writer.transport.abort()
                    self._data_writer = None
                if self._data_seen:
                    # The link worked until now: retry fast; a sensor that accepts and then hangs up
                    # at once keeps growing the backoff instead of being hammered.
                    backoff = cfg.reconnect_initial_s
                    self._data_seen = False
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2.0, cfg.reconnect_max_s)

    async def _open_data(self) -> None:
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(self.host, self.data_port), self.config.connect_timeout_s
        )
        last = self.stats.last_frame_index
        start = last + 1 if (self.config.resume and last >= 0) else P.LIVE
        writer.write(P.encode_subscribe(start))
        await writer.drain()
        self._data_writer = writer
        self._data_reader = reader

    async def _restart_if_needed(self) -> None:
        """After an outage the sensor may have restarted: reopen control and START it again if needed.

        Raises:
            OSError, ProtocolError: control is unreachable (the supervisor retries with backoff).
        """
        for attempt in range(2):
            try:
                if self._ctl is None:
                    await self._open_control()
                state = await self.get_state()
                break
            except (OSError, P.ProtocolError) as exc:
                # The old control connection may be dead without having noticed yet: one fresh try.
                await self._close_control()
                if attempt == 1:
                    log.warning("hd8_control_recover_failed", error=str(exc))
                    raise
        last = self.stats.last_frame_index
        if state.next_frame_index <= last:
            # The sensor's frame counter went backwards: it restarted. Its frames start again at 0
            # and its clock restarted too; accept the new numbering and tell the consumer.
            self.stats.last_frame_index = state.next_frame_index - 1
            self._emit(SourceEventKind.RESTARTED, last_frame=last, next_frame=state.next_frame_index)
            log.warning("hd8_sensor_restarted", last_frame=last, next_frame=state.next_frame_index)
        if self._want_running and state.state != P.SensorState.RUNNING:
            await self.command(P.CommandId.START)

    async def _read_data(self) -> None:
        reader = self._data_reader
        framer = P.MessageFramer()
        asm = P.GroupAssembler()
        chunk_size = self.config.read_chunk_bytes
        stall_s = self.config.watchdog_timeout_s
        while True:
            if framer.pending:
                # Inside a message, silence means a corrupt size field (one stray byte shifts the
                # stream and the "size" can ask for megabytes that never come): resubscribe instead
                # of waiting for them forever.
                # asyncio.timeout, not wait_for: on Python 3.11 wait_for drops a cancellation that
                # arrives as the read completes, and on a busy stream that is most of them (close()
                # then waited for a second cancel).
                try:
                    async with asyncio.timeout(stall_s):
                        chunk = await reader.read(chunk_size)
                except TimeoutError:
                    raise P.FramingError(
                        f"no data for {stall_s} s inside a message ({framer.pending} bytes of it buffered)",
                        field="size",
                    ) from None
            else:
                chunk = await reader.read(chunk_size)
            if not chunk:
                return
            now_ns = time.monotonic_ns()
            self._data_seen = True
            self.stats.bytes_received += len(chunk)
            groups = []
            for msg in framer.feed(chunk):  # FramingError propagates: reconnect and resume
                group = asm.push(msg)
                if group is not None:
                    groups.append(group)
            if not groups:
                continue
            # Everything that arrived in one read is decoded in one numpy pass per layout.
            decoded = P.decode_groups(groups, now_ns)
            for exc in decoded.errors:
                self.stats.decode_errors += 1
                self._ratelog.warning("hd8_decode_error", error=str(exc), field=exc.field)
            for batch in decoded.batches:
                self._deliver(batch, now_ns)

    def _deliver(self, batch: ProfileBatch, now_ns: int) -> None:
        st = self.stats
        fi = batch.frame_index.astype(np.int64)
        last = st.last_frame_index
        # A profile is new only if its index exceeds everything before it (delivered or earlier in
        # this batch): replays after a reconnect, and groups a broken sensor repeats, are dropped.
        before = np.maximum.accumulate(np.concatenate([[last], fi[:-1]]))
        fresh = fi > before
        if not fresh.all():
            st.duplicates_dropped += int(len(fi) - fresh.sum())
            if not fresh.any():
                return
            batch = batch.select(fresh)
            fi = fi[fresh]
        steps = np.diff(fi) - 1
        if last >= 0:  # joining a running stream is not a loss; a jump after that is
            steps = np.concatenate([[fi[0] - last - 1], steps])
        missing = int(steps.sum())
        if missing:
            st.gaps += int((steps > 0).sum())
            st.missing_frames += missing
            self._emit(SourceEventKind.GAP, missing_frames=missing, after_frame=last)
            self._ratelog.warning("hd8_frame_gap", missing_frames=missing, after_frame=last)
        st.last_frame_index = int(fi[-1])
        self._last_frame_ns = now_ns
        if self._stalled:
            self._stalled = False
            self._emit(SourceEventKind.RESUMED, frame=st.last_frame_index)
            log.info("hd8_frames_resumed", frame=st.last_frame_index)
        if self._queued_profiles + len(batch) > self.config.buffer_profiles:
            st.overflow_batches += 1
            st.overflow_frames += len(batch)
            self._emit(SourceEventKind.OVERFLOW, dropped_frames=len(batch))
            self._ratelog.warning(
                "hd8_buffer_overflow", dropped_frames=len(batch), overflow_frames=st.overflow_frames
            )
            return
        self._queue.put_nowait(batch)
        self._queued_profiles += len(batch)
        st.batches += 1
        st.frames += len(batch)
        st.count_frames(len(batch), now_ns)

    async def _watchdog(self) -> None:
        timeout_ns = int(self.config.watchdog_timeout_s * 1e9)
        while True:
            await asyncio.sleep(self.config.watchdog_timeout_s / 4)
            now = time.monotonic_ns()
            if self._want_running and not self._stalled and now - self._last_frame_ns > timeout_ns:
                self._stalled = True
                self.stats.reset_rate()  # the rate window only refreshes when frames arrive
                silent_s = (now - self._last_frame_ns) / 1e9
                self._emit(SourceEventKind.STALLED, silent_s=silent_s, last_frame=self.stats.last_frame_index)
                log.warning(
                    "hd8_frames_stalled", silent_s=round(silent_s, 3), last_frame=self.stats.last_frame_index
                )

    async def _keepalive(self) -> None:
        while True:
            await asyncio.sleep(self.config.keepalive_interval_s)
            try:
                if self._ctl is None:
                    await self._open_control()
                await self.command(P.CommandId.KEEP_ALIVE)
            except (OSError, P.ProtocolError) as exc:
                self._ratelog.warning("hd8_keepalive_failed", error=str(exc))
