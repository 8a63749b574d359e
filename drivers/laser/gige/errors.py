"""The GigE Vision source's errors: each names the device, the feature or the value at fault."""

from __future__ import annotations

__all__ = [
    "AravisUnavailableError",
    "DeviceNotFoundError",
    "FeatureError",
    "GigeError",
    "MissingFeatureError",
    "NotAProfilerError",
    "PixelFormatError",
]


class GigeError(Exception):
    """Base of every error of :mod:`drivers.laser.gige`."""


class AravisUnavailableError(GigeError):
    """PyGObject or Aravis's typelib (``Aravis-0.8``) cannot be loaded on this machine."""


class DeviceNotFoundError(GigeError):
    """No GigE Vision device answers at the configured address / id."""

    def __init__(self, device: str, detail: str = "") -> None:
        self.device = device
        super().__init__(f"no GigE Vision device {device!r}" + (f": {detail}" if detail else ""))


class FeatureError(GigeError):
    """A GenICam feature could not be read or written (the device refused it or it is out of range)."""

    def __init__(self, feature: str, detail: str) -> None:
        self.feature = feature
        super().__init__(f"GenICam feature {feature!r}: {detail}")


class MissingFeatureError(FeatureError):
    """The device's GenICam description lacks a feature the source needs."""

    def __init__(self, feature: str, why: str) -> None:
        super().__init__(feature, f"not offered by the device ({why})")


class NotAProfilerError(GigeError):
    """The device is a GigE Vision camera, but not a 3D profiler (no SFNC Scan3dControl)."""

    def __init__(self, device: str, missing: list[str]) -> None:
        self.device = device
        self.missing = missing
        super().__init__(
            f"device {device!r} is not a 3D profile sensor: it lacks the SFNC Scan3dControl features "
            f"{', '.join(missing)}"
        )


class PixelFormatError(GigeError):
    """The range data arrive (or would be set) in a pixel format the source cannot convert."""

    def __init__(self, pixel_format: int | str, detail: str = "") -> None:
        self.pixel_format = pixel_format
        fmt = f"0x{pixel_format:08x}" if isinstance(pixel_format, int) else pixel_format
        super().__init__(
            f"pixel format {fmt} is not a 16-bit range format" + (f": {detail}" if detail else "")
        )
