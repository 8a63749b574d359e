"""Range rows <-> profiles, per the SFNC's Scan3dControl: the codec the source and the simulator share.

A GigE Vision 3D profiler (SICK Ranger3/Ruler, AT C5/C6, scanCONTROL in GigE mode) sends *range
images*: each row is one profile, each pixel of a row one point across the laser line. In the SFNC's
``RectifiedC`` output mode the pixel value is the C coordinate (range along the laser axis) and the
column is the A coordinate (across the line) on a uniform grid::

    a_mm = Scan3dCoordinateOffset[A] + Scan3dCoordinateScale[A] * column
    c_mm = Scan3dCoordinateOffset[C] + Scan3dCoordinateScale[C] * pixel_value

and a pixel equal to ``Scan3dInvalidDataValue`` (when ``Scan3dInvalidDataFlag`` is set) has no return.
In the cell's sensor frame (:class:`drivers.laser.source.ProfileBatch`) A is x and C is z.

The device stamps each buffer (GVSP leader) with its clock in ticks of ``GevTimestampTickFrequency``;
rows follow at the line period, so row ``k`` of a buffer stamped ``t0`` was exposed at
``t0 + k * line_period``. GigE Vision 1.x block ids are 16 bits, cycle through 1..65535 (0 is never
used) and are unwrapped by :class:`BlockIdUnwrapper`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "RANGE_PIXEL_FORMATS",
    "BlockIdUnwrapper",
    "RangeLayout",
    "profiles_to_rows",
    "row_times_us",
    "rows_to_profiles",
]

#: PFNC codes of the 16-bit single-channel range formats the source converts
RANGE_PIXEL_FORMATS = {
    0x01100007: "Mono16",
    0x011000B8: "Coord3D_C16",
}

_GEV1_BLOCK_IDS = 65535  # 1..65535


@dataclass(frozen=True)
class RangeLayout:
    """How a range row maps to millimetres (read from the device's Scan3d features).

    Attributes:
        width: points per profile (the image's width, pixels).
        a_scale_mm, a_offset_mm: A (x) per column, mm.
        c_scale_mm, c_offset_mm: C (z) per pixel value, mm.
        invalid_value: raw value of a missing point, or None when the device flags none.
        line_rate_hz: profiles per second while acquiring (the row period's inverse).
        tick_hz: device timestamp ticks per second (``GevTimestampTickFrequency``).
    """

    width: int
    a_scale_mm: float
    a_offset_mm: float
    c_scale_mm: float
    c_offset_mm: float
    invalid_value: int | None
    line_rate_hz: float
    tick_hz: float = 1e9

    def __post_init__(self) -> None:
        if self.width < 1:
            raise ValueError(f"RangeLayout.width must be >= 1, got {self.width}")
        if not (np.isfinite(self.c_scale_mm) and self.c_scale_mm != 0.0):
            raise ValueError(f"RangeLayout.c_scale_mm must be finite and non-zero, got {self.c_scale_mm}")
        if not self.line_rate_hz > 0:
            raise ValueError(f"RangeLayout.line_rate_hz must be > 0, got {self.line_rate_hz}")
        if not self.tick_hz > 0:
            raise ValueError(f"RangeLayout.tick_hz must be > 0, got {self.tick_hz}")

    def x_mm(self) -> np.ndarray:
        """(width,) float32, x of each column, mm."""
        return (self.a_offset_mm + self.a_scale_mm * np.arange(self.width)).astype(np.float32)


def rows_to_profiles(raw: np.ndarray, layout: RangeLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Convert (n, width) uint16 range rows to profiles.

    Returns:
        x_mm (n, width) float32, z_mm (n, width) float32 (NaN where invalid), valid (n, width) bool.
    """
    if raw.ndim != 2 or raw.shape[1] != layout.width:
        raise ValueError(f"range rows have shape {raw.shape}, expected (n, {layout.width})")
    z = raw.astype(np.float32)
    z *= np.float32(layout.c_scale_mm)
    z += np.float32(layout.c_offset_mm)
    if layout.invalid_value is None:
        valid = np.ones(raw.shape, dtype=bool)
    else:
        valid = raw != layout.invalid_value
        z[~valid] = np.nan
    x = np.broadcast_to(layout.x_mm(), raw.shape).copy()
    return x, z, valid


def profiles_to_rows(z_mm: np.ndarray, valid: np.ndarray, layout: RangeLayout) -> np.ndarray:
    """The device side: (n, width) z in mm and validity -> uint16 range rows (clipped to the code range).

    Points outside the representable range, and invalid ones, get ``invalid_value`` (0 if None).
    """
    code = np.rint((np.nan_to_num(z_mm, nan=0.0) - layout.c_offset_mm) / layout.c_scale_mm)
    invalid = 0 if layout.invalid_value is None else layout.invalid_value
    ok = valid & np.isfinite(z_mm) & (code >= 0) & (code <= 0xFFFF) & (code != invalid)
    out = np.full(z_mm.shape, invalid, dtype=np.uint16)
    out[ok] = code[ok].astype(np.uint16)
    return out


def row_times_us(buffer_ticks: int, n_rows: int, layout: RangeLayout) -> np.ndarray:
    """(n_rows,) uint64 device time of each row in microseconds: the buffer's stamp plus k line periods."""
    t0_us = buffer_ticks * (1e6 / layout.tick_hz)
    return np.rint(t0_us + np.arange(n_rows) * (1e6 / layout.line_rate_hz)).astype(np.uint64)


class BlockIdUnwrapper:
    """GVSP block ids -> a count that never wraps.

    GigE Vision 1.x ids are 16 bits and cycle through 1..65535; ids above that (GigE Vision 2's 64-bit
    ids) are taken as they are. The first id seen counts as 0.
    """

    def __init__(self) -> None:
        self._last_raw: int | None = None
        self._count = 0

    def reset(self) -> None:
        """Forget the last id (after a reconnect: the next id counts as 0 again)."""
        self._last_raw = None
        self._count = 0

    def push(self, raw: int) -> int:
        """The unwrapped count of ``raw`` (an id equal to the last one counts as a repeat: same count)."""
        if self._last_raw is None:
            self._last_raw = raw
            self._count = 0
            return 0
        if raw > _GEV1_BLOCK_IDS or self._last_raw > _GEV1_BLOCK_IDS:
            step = raw - self._last_raw
        else:
            step = ((raw - 1) - (self._last_raw - 1)) % _GEV1_BLOCK_IDS
            if step > _GEV1_BLOCK_IDS // 2:  # a late or repeated id: behind, not 65 000 ahead
                step -= _GEV1_BLOCK_IDS
        self._count += step
        self._last_raw = raw
        return self._count
