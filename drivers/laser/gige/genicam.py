"""GenICam feature access for a 3D profiler through Aravis: identity, the Scan3d checks, the settings.

Blocking (GVCP round trips): the source calls these from a worker thread, never the event loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from drivers.laser.gige._aravis import aravis
from drivers.laser.gige.errors import FeatureError, MissingFeatureError, NotAProfilerError, PixelFormatError
from drivers.laser.gige.scan3d import RANGE_PIXEL_FORMATS, RangeLayout

__all__ = ["DeviceInfo", "ProfilerSettings", "apply_settings", "check_profiler", "device_info", "read_layout"]

#: what makes a device a profiler the source can read (SFNC Scan3dControl)
PROFILER_FEATURES = ("Scan3dCoordinateSelector", "Scan3dCoordinateScale", "Scan3dCoordinateOffset")

#: Aravis reports buffer timestamps in ns whatever the device's tick (it converts with the tick frequency)
ARAVIS_TIMESTAMP_HZ = 1e9


@dataclass(frozen=True)
class DeviceInfo:
    """Identity of the connected device."""

    vendor: str
    model: str
    serial: str
    address: str


@dataclass(frozen=True)
class ProfilerSettings:
    """What the cell sets on the device (None: leave the device's value).

    Attributes:
        line_rate_hz: profiles per second (``AcquisitionLineRate``, or the frame rate times the rows).
        exposure_us: ``ExposureTime`` (or ``ExposureTimeAbs``), microseconds.
        width, x_offset: the region across the line (``Width``, ``OffsetX``), pixels.
        rows_per_buffer: profiles per GVSP block (``Height`` of the range image).
    """

    line_rate_hz: float | None = None
    exposure_us: float | None = None
    width: int | None = None
    x_offset: int | None = None
    rows_per_buffer: int | None = None


def _has(device: Any, name: str) -> bool:
    try:
        return bool(device.is_feature_available(name))
    except Exception:
        return device.get_feature(name) is not None


def _call(feature: str, fn: Any, *args: Any) -> Any:
    try:
        return fn(*args)
    except Exception as exc:  # GLib.Error carries the device's refusal; name the feature
        raise FeatureError(feature, getattr(exc, "message", None) or str(exc)) from exc


def device_info(camera: Any, address: str) -> DeviceInfo:
    """Vendor, model and serial of an open camera."""
    return DeviceInfo(
        vendor=_call("DeviceVendorName", camera.get_vendor_name) or "",
        model=_call("DeviceModelName", camera.get_model_name) or "",
        serial=_call("DeviceSerialNumber", camera.get_device_serial_number) or "",
        address=address,
    )


def check_profiler(camera: Any, name: str) -> None:
    """Refuse a device that is not a 3D profiler, or one whose units the source cannot take.

    Raises:
        NotAProfilerError: no Scan3dControl (a plain camera: Aravis's stock fake device is one).
        FeatureError: Scan3dDistanceUnit is not millimetres, or DeviceScanType is an area scan.
    """
    device = camera.get_device()
    missing = [f for f in PROFILER_FEATURES if not _has(device, f)]
    if missing:
        raise NotAProfilerError(name, missing)
    if _has(device, "Scan3dDistanceUnit"):
        unit = _call("Scan3dDistanceUnit", device.get_string_feature_value, "Scan3dDistanceUnit")
        if unit != "Millimeter":
            raise FeatureError("Scan3dDistanceUnit", f"is {unit!r}; the source converts Millimeter only")
    if _has(device, "DeviceScanType"):
        scan = _call("DeviceScanType", device.get_string_feature_value, "DeviceScanType")
        if scan not in ("Linescan3D", "Linescan"):
            raise FeatureError("DeviceScanType", f"is {scan!r}; a profiler streams Linescan3D range rows")


def _select_range_format(camera: Any) -> int:
    A = aravis()
    current = int(_call("PixelFormat", camera.get_pixel_format))
    if current in RANGE_PIXEL_FORMATS:
        return current
    offered = {int(f) for f in _call("PixelFormat", camera.dup_available_pixel_formats)}
    for code in (A.PIXEL_FORMAT_COORD3D_C_16, A.PIXEL_FORMAT_MONO_16):
        if int(code) in offered:
            _call("PixelFormat", camera.set_pixel_format, code)
            got = int(_call("PixelFormat", camera.get_pixel_format))
            if got != int(code):
                raise PixelFormatError(
                    got, f"the device kept it after PixelFormat was set to 0x{int(code):08x}"
                )
            return got
    names = _call("PixelFormat", camera.dup_available_pixel_formats_as_strings)
    raise PixelFormatError(
        current, f"the device offers only {', '.join(names)}; it needs Coord3D_C16 or Mono16"
    )


def _coordinate(device: Any, axis: str) -> tuple[float, float]:
    _call("Scan3dCoordinateSelector", device.set_string_feature_value, "Scan3dCoordinateSelector", axis)
    scale = _call("Scan3dCoordinateScale", device.get_float_feature_value, "Scan3dCoordinateScale")
    offset = _call("Scan3dCoordinateOffset", device.get_float_feature_value, "Scan3dCoordinateOffset")
    return float(scale), float(offset)


def line_rate_hz(camera: Any) -> float:
    """Profiles per second: ``AcquisitionLineRate`` if offered, else the frame rate times the rows."""
    device = camera.get_device()
    if _has(device, "AcquisitionLineRate"):
        return float(_call("AcquisitionLineRate", device.get_float_feature_value, "AcquisitionLineRate"))
    rows = int(_call("Height", device.get_integer_feature_value, "Height"))
    return float(_call("AcquisitionFrameRate", camera.get_frame_rate)) * rows


def apply_settings(camera: Any, settings: ProfilerSettings) -> None:
    """Write the cell's settings: region first (it bounds the rates), then rate, then exposure."""
    device = camera.get_device()
    if settings.x_offset is not None or settings.width is not None or settings.rows_per_buffer is not None:
        x, y, w, h = _call("Region", camera.get_region)
        # the offset goes to 0 first so a wider region fits, then to its value
        if settings.x_offset is not None:
            _call("OffsetX", camera.set_region, 0, y, w, h)
        w = settings.width if settings.width is not None else w
        h = settings.rows_per_buffer if settings.rows_per_buffer is not None else h
        x = settings.x_offset if settings.x_offset is not None else x
        _call("Region", camera.set_region, x, y, w, h)
        got = tuple(_call("Region", camera.get_region))
        if (got[0], got[2], got[3]) != (x, w, h):
            raise FeatureError("Region", f"asked OffsetX={x} Width={w} Height={h}, the device kept {got}")
    if settings.line_rate_hz is not None:
        if _has(device, "AcquisitionLineRate"):
            _call(
                "AcquisitionLineRate",
                device.set_float_feature_value,
                "AcquisitionLineRate",
                settings.line_rate_hz,
            )
        else:
            rows = int(_call("Height", device.get_integer_feature_value, "Height"))
            _call("AcquisitionFrameRate", camera.set_frame_rate, settings.line_rate_hz / rows)
    if settings.exposure_us is not None:
        if not (_has(device, "ExposureTime") or _has(device, "ExposureTimeAbs")):
            raise MissingFeatureError("ExposureTime", "[laser] exposure_us is set")
        _call("ExposureTime", camera.set_exposure_time, settings.exposure_us)


def read_layout(camera: Any) -> tuple[RangeLayout, int]:
    """Select a 16-bit range pixel format and read the Scan3d scale/offset per axis.

    Returns:
        the layout and the pixel format code in force.
    """
    device = camera.get_device()
    pixel_format = _select_range_format(camera)
    a_scale, a_offset = _coordinate(device, "CoordinateA")
    c_scale, c_offset = _coordinate(device, "CoordinateC")
    invalid: int | None = None
    if _has(device, "Scan3dInvalidDataFlag") and _has(device, "Scan3dInvalidDataValue"):
        flag = device.get_feature("Scan3dInvalidDataFlag")
        on = bool(_call("Scan3dInvalidDataFlag", flag.get_value)) if hasattr(flag, "get_value") else True
        if on:
            invalid = round(
                _call("Scan3dInvalidDataValue", device.get_float_feature_value, "Scan3dInvalidDataValue")
            )
    width = int(_call("Width", device.get_integer_feature_value, "Width"))
    layout = RangeLayout(
        width=width,
        a_scale_mm=a_scale,
        a_offset_mm=a_offset,
        c_scale_mm=c_scale,
        c_offset_mm=c_offset,
        invalid_value=invalid,
        line_rate_hz=line_rate_hz(camera),
        tick_hz=ARAVIS_TIMESTAMP_HZ,
    )
    return layout, pixel_format


def exposure_ns(camera: Any) -> int:
    """The exposure in force, ns (0 if the device has no exposure feature)."""
    device = camera.get_device()
    if not (_has(device, "ExposureTime") or _has(device, "ExposureTimeAbs")):
        return 0
    return round(float(_call("ExposureTime", camera.get_exposure_time)) * 1000)
