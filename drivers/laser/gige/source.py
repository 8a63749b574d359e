"""GigeProfileSource: a GigE Vision / GenICam 3D profiler as a :class:`ProfileSource`, through Aravis.

Aravis (LGPL, GObject introspection) speaks GVCP (control: discovery, registers, the GenICam XML,
heartbeat) and GVSP (the stream: leader, payload packets, trailer; missing packets are asked again
with PACKETRESEND). This module keeps the cell's side of it:

* connect: open the device by address or id, refuse one that is not a profiler
  (:func:`~drivers.laser.gige.genicam.check_profiler`), select a 16-bit range format;
* configure: region, line rate and exposure from the cell's configuration, then read the Scan3d
  layout back from the device (the device's values, not the asked ones, convert the rows);
* stream: a reader thread pops completed buffers, converts their rows in one numpy pass
  (:mod:`drivers.laser.gige.scan3d`) and hands the batch to the event loop; a buffer that is not
  complete after the resends (a *torn* buffer) is never delivered: it is counted and its profiles show
  as a frame-index gap;
* supervise: when the device's control channel is lost (Aravis's heartbeat) or the stream stays silent
  past ``lost_after_s``, the device is reopened with backoff and the settings applied again; profile
  indices continue from the last delivered one (a jump by the device-clock time of the outage), so
  nothing is delivered twice or out of order.

Frame index: ``block * rows_per_buffer + row`` over unwrapped GVSP block ids; sensor time: the
buffer's device stamp plus the row's line periods (:func:`~drivers.laser.gige.scan3d.row_times_us`),
so the cell's clock synchronisation (offset and drift, cellctl/acquisition/clock_sync.py) treats it as
it treats the HD8's.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.laser.gige import genicam
from drivers.laser.gige._aravis import aravis
from drivers.laser.gige.errors import DeviceNotFoundError, GigeError, PixelFormatError
from drivers.laser.gige.scan3d import (
    RANGE_PIXEL_FORMATS,
    BlockIdUnwrapper,
    RangeLayout,
    row_times_us,
    rows_to_profiles,
)
from drivers.laser.source import ProfileBatch, ProfileSource, SourceEventKind, SourceStats
from drivers.runtime import RateLimitedLog

__all__ = ["GigeProfileSource", "GigeSourceConfig", "GigeStats", "discover"]

log = structlog.get_logger(__name__)

_CLOSED = object()
_POP_TIMEOUT_US = 100_000


class GigeSourceConfig(BaseModel):
    """Tuning of the GigE Vision source (all optional)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: profiles held for the consumer; a batch that would exceed it is dropped and counted (overflow)
    buffer_profiles: int = Field(20_000, gt=0)
    #: profiles per GVSP block (the range image's Height): fewer means lower latency, more packets
    rows_per_buffer: int = Field(10, gt=0)
    #: the region across the line set at connect (Width, OffsetX); None keeps the device's
    width: int | None = Field(None, gt=0)
    x_offset: int | None = Field(None, ge=0)
    #: buffers queued to Aravis's stream thread
    n_buffers: int = Field(32, ge=2)
    #: GVSP packet size in bytes; None negotiates the largest the path takes (loopback: 8 kB and more)
    packet_size: int | None = Field(None, ge=576, le=65_000)
    #: ask missing packets again (GVCP PACKETRESEND) before a buffer counts as torn
    packet_resend: bool = True
    #: how long Aravis waits for a buffer's missing packets, ms (Aravis's packet-timeout)
    packet_timeout_ms: int = Field(20, gt=0)
    #: how long Aravis keeps an incomplete buffer before giving it up, ms (frame-retention)
    frame_retention_ms: int = Field(100, gt=0)
    #: no profile for this long beyond one block's duration while running -> STALLED (RESUMED after)
    watchdog_timeout_s: float = Field(0.5, gt=0)
    #: silence beyond this plus one block's duration (or the heartbeat's control-lost) -> reopened
    lost_after_s: float = Field(2.0, gt=0)
    reconnect_initial_s: float = Field(0.05, gt=0)
    reconnect_max_s: float = Field(2.0, gt=0)


@dataclass
class GigeStats(SourceStats):
    """:class:`SourceStats` plus the GigE Vision stream's own counters.

    Attributes:
        torn_buffers: buffers incomplete after the resends (never delivered; their profiles are a gap).
        resent_packets, missing_packets: Aravis's GVSP counters (asked again / never arrived).
        underruns: buffers Aravis had to drop for want of a free buffer (``n_buffers`` too small for
            the frames held waiting for resends); their profiles are a gap too.
    """

    torn_buffers: int = 0
    underruns: int = 0
    resent_packets: int = 0
    missing_packets: int = 0


def discover(timeout_ms: int = 1000) -> list[dict[str, str]]:
    """GigE Vision devices that answer a discovery on every interface (blocking).

    Returns:
        one dict per device: ``id``, ``address``, ``serial``, ``model``, ``vendor``, ``protocol``.
    """
    A = aravis()
    A.update_device_list()
    out = []
    for i in range(A.get_n_devices()):
        if A.get_device_protocol(i) != "GigEVision":
            continue
        out.append(
            {
                "id": A.get_device_id(i),
                "address": A.get_device_address(i),
                "serial": A.get_device_serial_nbr(i),
                "model": A.get_device_model(i),
                "vendor": A.get_device_vendor(i),
                "protocol": A.get_device_protocol(i),
            }
        )
    return out


class _Link:
    """One open device: camera, stream, reader thread. Lives in threads; its ``lost`` flag is sticky."""

    def __init__(self, camera: Any, layout: RangeLayout, pixel_format: int, exposure_ns: int) -> None:
        self.camera = camera
        self.layout = layout
        self.pixel_format = pixel_format
        self.exposure_ns = exposure_ns
        self.stream: Any = None
        self.thread: threading.Thread | None = None
        self.stop_flag = threading.Event()
        self.lost = threading.Event()
        self.lost_handler: int | None = None


class GigeProfileSource(ProfileSource):
    """A GigE Vision 3D profiler (or Aravis's fake device with a profiler description).

    Args:
        device: the device's IP address or its Aravis id (``Vendor-Model-Serial``) or serial.
        config: see :class:`GigeSourceConfig`.

    After :meth:`connect`, :attr:`info` holds its identity and :attr:`layout` its range layout.
    """

    def __init__(self, device: str = "127.0.0.1", *, config: GigeSourceConfig | None = None) -> None:
        super().__init__()
        self.device = device
        self.config = config or GigeSourceConfig()
        self.stats: GigeStats = GigeStats()
        self.info: genicam.DeviceInfo | None = None
        self._settings = genicam.ProfilerSettings(
            rows_per_buffer=self.config.rows_per_buffer,
            width=self.config.width,
            x_offset=self.config.x_offset,
        )
        self._link: _Link | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queue: asyncio.Queue[Any] = asyncio.Queue()
        self._queued_profiles = 0
        self._want_running = False
        self._closed = False
        self._tasks: list[asyncio.Task[None]] = []
        self._blocks = BlockIdUnwrapper()
        self._index_base: int | None = None  # frame index of block count 0 in this connection
        self._last_sensor_us = -1
        self._last_frame_ns = 0
        self._stalled = False
        self._ratelog = RateLimitedLog(log)

    @property
    def layout(self) -> RangeLayout | None:
        """The range layout in force (None before :meth:`connect`)."""
        return None if self._link is None else self._link.layout

    # ------------------------------------------------------------------------------- device

    def _open(self) -> _Link:
        """Blocking: open, check and set up the device (called in a worker thread)."""
        A = aravis()
        try:
            camera = A.Camera.new(self.device)
        except Exception as exc:
            raise DeviceNotFoundError(self.device, getattr(exc, "message", None) or str(exc)) from exc
        if camera is None:
            raise DeviceNotFoundError(self.device)
        if not camera.is_gv_device():
            raise DeviceNotFoundError(self.device, "it is not a GigE Vision device")
        genicam.check_profiler(camera, self.device)
        genicam.apply_settings(camera, self._settings)
        layout, pixel_format = genicam.read_layout(camera)
        link = _Link(camera, layout, pixel_format, genicam.exposure_ns(camera))
        self.info = genicam.device_info(camera, self.device)
        return link

    def _start_stream(self, link: _Link) -> None:
        """Blocking: stream, buffers, acquisition and the reader thread."""
        A = aravis()
        cfg = self.config
        cam = link.camera
        if cfg.packet_size is None:
            cam.gv_auto_packet_size()
        else:
            cam.gv_set_packet_size(cfg.packet_size)
        device = cam.get_device()
        link.lost_handler = device.connect("control-lost", lambda *_: self._on_control_lost(link))
        stream = cam.create_stream(None, None)
        if stream is None:
            raise GigeError(f"device {self.device!r}: Aravis could not open a GVSP stream")
        stream.set_property(
            "packet-resend",
            A.GvStreamPacketResend.ALWAYS if cfg.packet_resend else A.GvStreamPacketResend.NEVER,
        )
        stream.set_property("packet-timeout", cfg.packet_timeout_ms * 1000)
        stream.set_property("frame-retention", cfg.frame_retention_ms * 1000)
        payload = cam.get_payload()
        for _ in range(cfg.n_buffers):
            stream.push_buffer(A.Buffer.new_allocate(payload))
        link.stream = stream
        link.stop_flag.clear()  # a stop() before this start() set it
        cam.set_acquisition_mode(A.AcquisitionMode.CONTINUOUS)
        cam.start_acquisition()
        link.thread = threading.Thread(target=self._reader, args=(link,), name="gige-reader", daemon=True)
        link.thread.start()

    def _stop_stream(self, link: _Link, *, device_alive: bool) -> None:
        """Blocking: stop acquisition (if the device still answers) and the reader thread."""
        link.stop_flag.set()
        if device_alive:
            try:
                link.camera.stop_acquisition()
            except Exception as exc:
                log.warning("gige_stop_acquisition_failed", error=str(exc))
        if link.thread is not None:
            link.thread.join(timeout=2.0)
        link.stream = None
        if link.lost_handler is not None:
            link.camera.get_device().disconnect(link.lost_handler)
            link.lost_handler = None
        if not device_alive:
            # Drop the camera now: its GvDevice's heartbeat thread would otherwise take control of the
            # device when it comes back, before (or from) the reopened link.
            link.camera = None

    def _on_control_lost(self, link: _Link) -> None:
        # Aravis's heartbeat thread: only flag it; the supervisor reopens the device
        link.lost.set()
        with contextlib.suppress(RuntimeError):  # the loop may be closed already
            if self._loop is not None:
                self._loop.call_soon_threadsafe(
                    functools.partial(self._ratelog.warning, "gige_control_lost", device=self.device)
                )

    # ----------------------------------------------------------------------------- reader

    def _reader(self, link: _Link) -> None:
        """The reader thread: pop buffers, convert complete ones, give every buffer back to Aravis."""
        A = aravis()
        success = A.BufferStatus.SUCCESS
        multipart = A.BufferPayloadType.MULTIPART
        stream = link.stream
        layout = link.layout
        loop = self._loop
        assert loop is not None
        while not link.stop_flag.is_set():
            buf = stream.timeout_pop_buffer(_POP_TIMEOUT_US)
            if buf is None:
                continue
            try:
                now_ns = time.monotonic_ns()
                status = buf.get_status()
                frame_id = int(buf.get_frame_id())
                if status != success:
                    loop.call_soon_threadsafe(self._on_torn, link, frame_id, status.value_nick)
                    continue
                try:
                    raw = self._range_rows(buf, multipart, layout.width)
                except (GigeError, ValueError) as exc:
                    loop.call_soon_threadsafe(self._on_bad_buffer, link, frame_id, exc)
                    continue
                ts = int(buf.get_timestamp())
                x, z, valid = rows_to_profiles(raw, layout)
                n = raw.shape[0]
                sensor_us = row_times_us(ts, n, layout)
                item = (frame_id, n, sensor_us, x, z, valid, now_ns, raw.nbytes)
                loop.call_soon_threadsafe(self._on_rows, link, item)
            finally:
                stream.push_buffer(buf)

    @staticmethod
    def _range_rows(buf: Any, multipart: Any, width: int) -> np.ndarray:
        """The buffer's range part as (rows, width) uint16 (the Range part of a multi-part buffer)."""
        if buf.get_payload_type() == multipart:
            for part in range(buf.get_n_parts()):
                fmt = int(buf.get_part_pixel_format(part))
                if fmt in RANGE_PIXEL_FORMATS:
                    data = buf.get_part_data(part)
                    w, h = buf.get_part_width(part), buf.get_part_height(part)
                    break
            else:
                fmts = [f"0x{int(buf.get_part_pixel_format(p)):08x}" for p in range(buf.get_n_parts())]
                raise PixelFormatError("multi-part", f"no 16-bit range part among {fmts}")
        else:
            fmt = int(buf.get_image_pixel_format())
            if fmt not in RANGE_PIXEL_FORMATS:
                raise PixelFormatError(fmt, "in a received buffer")
            data = buf.get_data()
            w, h = buf.get_image_width(), buf.get_image_height()
        if w != width:
            raise ValueError(f"buffer rows are {w} wide, the layout says {width}")
        if len(data) < 2 * w * h:
            raise ValueError(f"buffer holds {len(data)} bytes, {w}x{h} Mono16 needs {2 * w * h}")
        return np.frombuffer(data, dtype="<u2", count=w * h).reshape(h, w)

    # --------------------------------------------------------------- event loop side of a buffer

    def _on_torn(self, link: _Link, frame_id: int, status: str) -> None:
        if link is not self._link:
            return
        self._blocks.push(frame_id)  # its rows count: the next complete buffer shows them as a gap
        self.stats.torn_buffers += 1
        self.stats.decode_errors += 1
        self._ratelog.warning("gige_torn_buffer", block_id=frame_id, status=status)

    def _on_bad_buffer(self, link: _Link, frame_id: int, exc: Exception) -> None:
        if link is not self._link:
            return
        self._blocks.push(frame_id)
        self.stats.decode_errors += 1
        self._ratelog.warning("gige_bad_buffer", block_id=frame_id, error=str(exc))

    def _on_rows(self, link: _Link, item: tuple[Any, ...]) -> None:
        if link is not self._link:
            return  # a late buffer of a link already torn down
        frame_id, n, sensor_us, x, z, valid, now_ns, nbytes = item
        st = self.stats
        st.bytes_received += nbytes
        count = self._blocks.push(frame_id)
        if self._index_base is None:
            self._index_base = self._first_index(int(sensor_us[0]), link.layout)
        fi = (self._index_base + count * n + np.arange(n)).astype(np.int64)
        fresh = fi > st.last_frame_index
        if not fresh.all():
            st.duplicates_dropped += int((~fresh).sum())
            if not fresh.any():
                return
        fi = fi[fresh]
        batch = ProfileBatch(
            frame_index=fi.astype(np.uint64),
            sensor_time_us=sensor_us[fresh],
            hd8_ms=((sensor_us[fresh] // 1000) & 0xFFFFFFFF).astype(np.uint32),
            encoder=np.zeros(len(fi), np.int64),
            status=np.zeros(len(fi), np.uint32),
            exposure_ns=np.full(len(fi), link.exposure_ns, np.uint32),
            x_mm=x[fresh],
            z_mm=z[fresh],
            valid=valid[fresh],
            host_recv_ns=np.full(len(fi), now_ns, np.int64),
        )
        self._deliver(batch, now_ns)

    def _first_index(self, sensor_us: int, layout: RangeLayout) -> int:
        """Index of the first profile of a (re)opened link: after the last one, plus the outage's lines."""
        last = self.stats.last_frame_index
        if last < 0:
            return 0
        if sensor_us > self._last_sensor_us:
            lines = round((sensor_us - self._last_sensor_us) * layout.line_rate_hz / 1e6)
            return last + max(1, lines)
        # the device clock went back: it restarted; its profiles are new ones, numbered on
        self._emit(SourceEventKind.RESTARTED, last_frame=last, sensor_time_us=sensor_us)
        log.warning("gige_device_restarted", last_frame=last)
        self._last_sensor_us = -1
        return last + 1

    def _deliver(self, batch: ProfileBatch, now_ns: int) -> None:
        st = self.stats
        fi = batch.frame_index.astype(np.int64)
        last = st.last_frame_index
        # index 0 is the first block seen, complete or torn: a torn first block is a loss too
        steps = np.concatenate([[fi[0] - last - 1], np.diff(fi) - 1])
        missing = int(steps.sum())
        if missing:
            st.gaps += int((steps > 0).sum())
            st.missing_frames += missing
            self._emit(SourceEventKind.GAP, missing_frames=missing, after_frame=last)
            self._ratelog.warning("gige_frame_gap", missing_frames=missing, after_frame=last)
        st.last_frame_index = int(fi[-1])
        self._last_sensor_us = int(batch.sensor_time_us[-1])
        self._last_frame_ns = now_ns
        if self._stalled:
            self._stalled = False
            self._emit(SourceEventKind.RESUMED, frame=st.last_frame_index)
        if self._queued_profiles + len(batch) > self.config.buffer_profiles:
            st.overflow_batches += 1
            st.overflow_frames += len(batch)
            self._emit(SourceEventKind.OVERFLOW, dropped_frames=len(batch))
            self._ratelog.warning("gige_buffer_overflow", dropped_frames=len(batch))
            return
        self._queue.put_nowait(batch)
        self._queued_profiles += len(batch)
        st.batches += 1
        st.frames += len(batch)
        st.count_frames(len(batch), now_ns)

    # ------------------------------------------------------------------------ ProfileSource

    async def connect(self) -> None:
        """Open the device, check it is a profiler, select the range format and read its layout.

        Raises:
            DeviceNotFoundError, NotAProfilerError, MissingFeatureError, PixelFormatError, FeatureError.
        """
        if self._closed:
            raise RuntimeError("GigeProfileSource is closed")
        self._loop = asyncio.get_running_loop()
        if self._link is None:
            self._link = await asyncio.to_thread(self._open)
            log.info("gige_connected", device=self.device, info=str(self.info), layout=str(self._link.layout))

    async def configure(
        self,
        *,
        rate_hz: float | None = None,
        exposure_ns: int | None = None,
        width: int | None = None,
        x_offset: int | None = None,
        rows_per_buffer: int | None = None,
        **unknown: Any,
    ) -> None:
        """Set the line rate (``rate_hz``, profiles/s), exposure and region; kept for reconnects.

        Other keys (an HD8 setting such as ``profile_format``) are refused with a ``TypeError``.
        """
        if unknown:
            raise TypeError(f"GigeProfileSource.configure: unknown settings {sorted(unknown)}")
        old = self._settings
        self._settings = genicam.ProfilerSettings(
            line_rate_hz=rate_hz if rate_hz is not None else old.line_rate_hz,
            exposure_us=exposure_ns / 1000 if exposure_ns is not None else old.exposure_us,
            width=width if width is not None else old.width,
            x_offset=x_offset if x_offset is not None else old.x_offset,
            rows_per_buffer=rows_per_buffer if rows_per_buffer is not None else old.rows_per_buffer,
        )
        if self._link is not None:
            link = self._link
            await asyncio.to_thread(genicam.apply_settings, link.camera, self._settings)
            layout, fmt = await asyncio.to_thread(genicam.read_layout, link.camera)
            link.layout, link.pixel_format = layout, fmt
            link.exposure_ns = await asyncio.to_thread(genicam.exposure_ns, link.camera)

    async def start(self) -> None:
        """Start acquisition; batches then arrive through async iteration."""
        if self._closed:
            raise RuntimeError("GigeProfileSource is closed")
        if self._link is None:
            await self.connect()
        assert self._link is not None
        self._want_running = True
        self._last_frame_ns = time.monotonic_ns()
        if self._link.stream is None:
            await asyncio.to_thread(self._start_stream, self._link)
        if not self._tasks:
            self._tasks = [asyncio.create_task(self._supervise(), name="gige-supervisor")]

    async def stop(self) -> None:
        """Stop acquisition; profiles already delivered stay readable."""
        self._want_running = False
        link = self._link
        if link is not None and link.stream is not None:
            await asyncio.to_thread(self._stop_stream, link, device_alive=not link.lost.is_set())

    async def close(self) -> None:
        """Stop, release the device and end every iteration (buffered batches are yielded first)."""
        if self._closed:
            return
        self._closed = True
        self._want_running = False
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        link, self._link = self._link, None
        if link is not None and link.stream is not None:
            self._read_stream_stats(link)  # the counters as they stand at the end, not 0.1 s before
            await asyncio.to_thread(self._stop_stream, link, device_alive=not link.lost.is_set())
        self._queue.put_nowait(_CLOSED)

    async def __aiter__(self) -> AsyncIterator[ProfileBatch]:
        """Yield batches in frame-index order until :meth:`close`."""
        while True:
            item = await self._queue.get()
            if item is _CLOSED:
                self._queue.put_nowait(_CLOSED)
                return
            self._queued_profiles -= len(item)
            yield item

    # ------------------------------------------------------------------------- supervision

    async def _supervise(self) -> None:
        cfg = self.config
        while True:
            await asyncio.sleep(min(cfg.watchdog_timeout_s / 4, 0.1))
            link = self._link
            if link is None or not self._want_running:
                continue
            # profiles come a block at a time: silence within one block's duration is the normal pace
            block_ns = int(self._settings_rows(link) / link.layout.line_rate_hz * 1e9)
            watchdog_ns = int(cfg.watchdog_timeout_s * 1e9) + block_ns
            lost_ns = int(cfg.lost_after_s * 1e9) + block_ns
            self._read_stream_stats(link)
            silent_ns = time.monotonic_ns() - self._last_frame_ns
            if not self._stalled and silent_ns > watchdog_ns:
                self._stalled = True
                self.stats.reset_rate()
                self._emit(
                    SourceEventKind.STALLED, silent_s=silent_ns / 1e9, last_frame=self.stats.last_frame_index
                )
                log.warning("gige_frames_stalled", silent_s=round(silent_ns / 1e9, 3))
            if link.lost.is_set() or silent_ns > lost_ns:
                await self._reopen(link)

    def refresh_stats(self) -> GigeStats:
        """Read Aravis's packet counters into :attr:`stats` now (the supervisor does it every 0.1 s)."""
        if self._link is not None:
            self._read_stream_stats(self._link)
        return self.stats

    def _settings_rows(self, link: _Link) -> int:
        return self._settings.rows_per_buffer or self.config.rows_per_buffer

    def _read_stream_stats(self, link: _Link) -> None:
        stream = link.stream
        if stream is None or not hasattr(stream, "get_statistics"):
            return
        try:
            resent, missing = stream.get_statistics()
            _completed, _failures, underruns = aravis().Stream.get_statistics(stream)
        except Exception:
            return
        before = self._counters_before
        self.stats.resent_packets = before[0] + int(resent)
        self.stats.missing_packets = before[1] + int(missing)
        self.stats.underruns = before[2] + int(underruns)

    _counters_before = (0, 0, 0)

    async def _reopen(self, old: _Link) -> None:
        """The device is gone (or mute): tear the link down and reopen it with backoff."""
        cfg = self.config
        self._emit(SourceEventKind.DISCONNECTED, last_frame=self.stats.last_frame_index)
        log.warning("gige_device_lost", device=self.device, last_frame=self.stats.last_frame_index)
        st = self.stats
        self._counters_before = (st.resent_packets, st.missing_packets, st.underruns)
        self._link = None
        await asyncio.to_thread(self._stop_stream, old, device_alive=False)
        backoff = cfg.reconnect_initial_s
        while self._want_running and not self._closed:
            try:
                link = await asyncio.to_thread(self._open)
                await asyncio.to_thread(self._start_stream, link)
            except GigeError as exc:
                self._ratelog.warning("gige_reopen_failed", error=str(exc))
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, cfg.reconnect_max_s)
                continue
            self._blocks.reset()
            self._index_base = None
            self._last_frame_ns = time.monotonic_ns()
            self._link = link
            self.stats.reconnects += 1
            self._emit(SourceEventKind.RECONNECTED, resume_after=self.stats.last_frame_index)
            log.info("gige_reconnected", device=self.device)
            return
