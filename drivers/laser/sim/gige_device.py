"""The sensor simulator as a GigE Vision 3D profiler: its rendered profiles over GVCP/GVSP.

Aravis's fake-device side does the GigE Vision (:class:`Aravis.GvFakeCamera`: discovery, registers,
the GenICam XML, heartbeat, GVSP leader / payload / trailer), described as a profiler
(:mod:`drivers.laser.sim.gige_xml`: Scan3dControl, AcquisitionLineRate); this module fills its
buffers. Aravis annotates its fill callback ``(scope call)``, so PyGObject would free the closure
when the setter returns; the callback is installed with ctypes on the same library instead, and runs
in the fake device's thread at each frame the device's own pace (``Height`` rows at the line rate
the client set) makes due.

Each buffer holds ``Height`` profiles ray cast by :meth:`LaserSimulator.render_profiles` at their
true mid-exposure times (the newest one line period before the buffer is sent), quantised to Mono16
with the Scan3d scale and offset the description declares (:func:`~drivers.laser.gige.scan3d.
profiles_to_rows`, the client's own codec), and stamped with the simulated sensor clock (its offset
and drift, as the HD8 model's). Faults: GVSP packet loss (``lost_packet_ratio``, the fake device's
own knob); Aravis's fake device serves no packet resend, so a lost packet tears its buffer.

GigE Vision's control port is fixed (UDP 3956): one device per address.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from drivers.laser.gige.scan3d import RangeLayout, profiles_to_rows
from drivers.laser.sim.gige_xml import profiler_genicam_xml
from drivers.laser.sim.sensor import LaserSimulator
from drivers.runtime import RateLimitedLog

__all__ = ["GigeSimDevice"]

log = structlog.get_logger(__name__)

_REG_FRAME_PERIOD_US = 0x138  # ARV_FAKE_CAMERA_REGISTER_ACQUISITION_FRAME_PERIOD_US
_REG_WIDTH = 0x100
_REG_HEIGHT = 0x104
_PIXEL_FORMAT_MONO16 = 0x01100007

_FILL = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


def _libaravis() -> ctypes.CDLL:
    lib = ctypes.CDLL(ctypes.util.find_library("aravis-0.8") or "libaravis-0.8.so.0")
    lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    lib.arv_fake_camera_set_fill_pattern.restype = None
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_image_width.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_get_image_width.restype = ctypes.c_int
    lib.arv_buffer_get_image_height.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_get_image_height.restype = ctypes.c_int
    lib.arv_buffer_set_timestamp.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
    lib.arv_buffer_set_timestamp.restype = None
    lib.arv_buffer_set_frame_id.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
    lib.arv_buffer_set_frame_id.restype = None
    return lib


def _gpointer(obj: Any) -> int:
    """The C pointer of a PyGObject wrapper."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype = ctypes.c_void_p
    get.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return int(get(obj.__gpointer__, None))


class GigeSimDevice:
    """A :class:`LaserSimulator`'s profiles served as a GigE Vision profiler on ``address``.

    Args:
        sim: the simulator (not started: this device renders through it instead of its HD8 servers).
        address: the interface address the device answers on (loopback in tests and ``cellctl sim``).
        serial: its serial number (Aravis id ``Aravis-Fake-<serial>``).
        rows_per_buffer: the Height it starts with (the client usually sets its own).
        lost_packet_ratio: GVSP packets dropped, 0..1.
    """

    def __init__(
        self,
        sim: LaserSimulator,
        *,
        address: str = "127.0.0.1",
        serial: str = "SIMGIGE",
        rows_per_buffer: int = 10,
        lost_packet_ratio: float = 0.0,
    ) -> None:
        cfg = sim.config
        self.sim = sim
        self.address = address
        self.serial = serial
        c_scale = cfg.z_scale_nm * 1e-6
        optics = cfg.optics()
        #: the layout the description declares (raw 0: no return; z_min is code 1)
        self.layout = RangeLayout(
            width=cfg.width,
            a_scale_mm=cfg.x_pitch_mm,
            a_offset_mm=float(optics.x_start_mm),
            c_scale_mm=c_scale,
            c_offset_mm=cfg.z_min_mm - c_scale,
            invalid_value=0,
            line_rate_hz=cfg.rate_hz,
        )
        self.rows_per_buffer = rows_per_buffer
        self.lost_packet_ratio = lost_packet_ratio
        self.buffers_filled = 0
        self.fill_errors = 0
        #: frame periods the fake device's thread let pass without a frame (their rows are lost)
        self.skipped_blocks = 0
        self._last_block: int | None = None
        self._real_minus_clock_us = 0.0
        self._gv: Any = None
        self._fake: Any = None
        self._lib: ctypes.CDLL | None = None
        self._cb: Any = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._ratelog = RateLimitedLog(log)

    def start(self) -> None:
        """Write the description, start the fake device, install the fill callback (blocking, short)."""
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis

        lay = self.layout
        self._tmp = tempfile.TemporaryDirectory(prefix="gige-sim-")
        xml = Path(self._tmp.name) / "profiler.xml"
        xml.write_text(
            profiler_genicam_xml(
                a_scale_mm=lay.a_scale_mm,
                a_offset_mm=lay.a_offset_mm,
                c_scale_mm=lay.c_scale_mm,
                c_offset_mm=lay.c_offset_mm,
                invalid_value=0,
            )
        )
        self._real_minus_clock_us = time.time_ns() / 1000 - self.sim.clock() * 1e6
        gv = Aravis.GvFakeCamera.new_full(self.address, self.serial, str(xml))
        if gv is None or not gv.is_running():
            raise OSError(f"the GigE Vision device cannot listen on {self.address} (UDP 3956 taken?)")
        gv.set_property("gvsp-lost-ratio", float(self.lost_packet_ratio))
        fake = gv.get_fake_camera()
        fake.write_register(_REG_WIDTH, lay.width)
        fake.write_register(_REG_HEIGHT, self.rows_per_buffer)
        fake.write_register(_REG_FRAME_PERIOD_US, round(self.rows_per_buffer * 1e6 / lay.line_rate_hz))
        fake.write_register(0x128, _PIXEL_FORMAT_MONO16)  # PixelFormat
        lib = _libaravis()
        self._cb = _FILL(self._fill)
        lib.arv_fake_camera_set_fill_pattern(_gpointer(fake), ctypes.cast(self._cb, ctypes.c_void_p), None)
        self._gv, self._fake, self._lib = gv, fake, lib
        log.info("gige_sim_device_started", address=self.address, serial=self.serial, layout=str(lay))

    def stop(self) -> None:
        """Stop serving: the stock pattern back, then the fake device's thread ends with it."""
        if self._fake is not None and self._lib is not None:
            # under the fake device's fill mutex: once it returns, our callback is never called again
            self._lib.arv_fake_camera_set_fill_pattern(_gpointer(self._fake), None, None)
        self._gv = self._fake = None  # disposing the GvFakeCamera joins its thread and closes its sockets
        self._cb = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def _fill(self, buf: int, _data: int, exposure_us: int, _gain: int, pixel_format: int) -> None:
        # the fake device's thread, at the frame's due time: render its rows and stamp them
        try:
            lib, fake = self._lib, self._fake
            assert lib is not None and fake is not None
            w, h = lib.arv_buffer_get_image_width(buf), lib.arv_buffer_get_image_height(buf)
            # arv_buffer_get_data's size is the received size (0 before a fill); the fake device checked
            # that the buffer holds its whole payload (Width * Height * pixel size) before calling us
            data = lib.arv_buffer_get_data(buf, ctypes.byref(ctypes.c_size_t()))
            if pixel_format != _PIXEL_FORMAT_MONO16 or w != self.layout.width:
                self.fill_errors += 1  # a format the simulator does not model: the client refuses it
                self._ratelog.warning("gige_sim_fill_refused", pixel_format=hex(pixel_format), width=w)
                return
            ok, period_us = fake.read_register(_REG_FRAME_PERIOD_US)
            if not (ok and period_us):
                period_us = round(h * 1e6 / self.layout.line_rate_hz)
            t_mid, block = self._row_times(h, int(period_us), exposure_us)
            z, valid, sensor_us = self.sim.render_profiles(t_mid)
            rows = profiles_to_rows(z, valid, self.layout)
            ctypes.memmove(data, rows.ctypes.data, rows.nbytes)
            lib.arv_buffer_set_timestamp(buf, round(float(sensor_us[0]) * 1000.0))
            lib.arv_buffer_set_frame_id(buf, block)
            self.buffers_filled += 1
        except Exception:  # never let an exception unwind into C
            self.fill_errors += 1
            log.exception("gige_sim_fill_failed")

    def _row_times(self, h: int, period_us: int, exposure_us: int) -> tuple[np.ndarray, int]:
        """True mid-exposure times of this buffer's rows, and its GVSP block id.

        The fake device makes a frame due on each multiple of the frame period on the host's real-time
        clock (``g_get_real_time``) and skips a boundary its thread was too busy to meet. Buffer ``n``
        therefore holds the rows exposed in the period that ends at boundary ``n``; its block id is
        ``n`` (16 bits, 1..65535), so a skipped boundary is a gap of one block at the client, as lost
        lines of a real profiler would be, and the rows keep the line rate exactly."""
        n = (time.time_ns() // 1000) // period_us
        # the boundary on the simulator's clock through one fixed mapping (read at start): reading both
        # clocks at each frame would put microseconds of jitter between the blocks' rows
        boundary = (n * period_us - self._real_minus_clock_us) * 1e-6
        line_s = period_us * 1e-6 / h
        t_mid = boundary - period_us * 1e-6 + (np.arange(h) + 1) * line_s - exposure_us * 0.5e-6
        if self._last_block is not None and n != self._last_block + 1:
            self.skipped_blocks += max(0, n - self._last_block - 1)
        self._last_block = n
        return t_mid, int(n % 65535) + 1

    def __enter__(self) -> GigeSimDevice:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def wait_until(predicate: Any, timeout_s: float) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` (for callers that start the device and a client)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False
