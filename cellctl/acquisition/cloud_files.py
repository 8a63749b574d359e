"""Cloud files: PLY for internal work, LAS 1.4 for exchange with metrology tools.

Both are written here with numpy structured arrays (no extra package):

* **PLY**: the product's one organised-PLY layout (:func:`analysis.cloud_io.write_cloud_ply`, read
  back by ``cellctl inspect``): ``float x, y, z`` (robot base frame, mm), ``int pass`` (transit
  filed under pass 0), ``int profile`` (running profile index), ``int point`` (column in the
  profile) and ``double t_s`` (exposure time from the first profile). Float32 coordinates, as
  CloudCompare, PCL and Open3D's tensor reader expect (line-laser-and-sync.md section 6).
* **LAS 1.4**, point data record format 6 (30 bytes) plus two *extra bytes* (``profile`` u32,
  ``point`` u16, described in the standard extra-bytes VLR). Coordinates are scaled integers:
  scale 0.001 (1 um, the unit is mm) and an offset at the cloud's minimum, so int32 covers +-2 km.
  ``point source ID`` carries the pass + 1 (files of the earlier convention hold 0 for transit) and
  ``GPS time`` the exposure time in seconds from the first profile. Chosen over E57 because E57 needs libE57Format (a new package).
"""

from __future__ import annotations

import datetime as _dt
import struct
from pathlib import Path

import numpy as np

from cellctl.acquisition.assembly import AssembledScan

__all__ = ["LAS_SCALE_MM", "CloudFileError", "read_las", "write_las", "write_ply"]

LAS_SCALE_MM = 0.001
_LAS_HEADER_SIZE = 375
_VLR_HEADER_SIZE = 54
_EXTRA_BYTES_DESCRIPTOR = 192


class CloudFileError(ValueError):
    """A cloud file cannot be written or read (names the file and the field)."""


#: the organised-PLY vertex of :func:`analysis.cloud_io.write_cloud_ply`, as :func:`write_ply` streams it
_PLY_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("pass", "<i4"),
        ("profile", "<i4"),
        ("point", "<i4"),
        ("t_s", "<f8"),
    ]
)
_PLY_COMMENT = "cellctl scan cloud: robot base frame, mm"


def write_ply(scan: AssembledScan, path: str | Path) -> Path:
    """Write the valid points of ``scan`` as binary PLY (the layout of
    :func:`analysis.cloud_io.write_cloud_ply`, byte for byte); returns the path.

    Written block of rows by block of rows (:meth:`AssembledScan.cloud_blocks`): a 6 m plate's
    170 M points need a block's records in memory, not 7 GB of float64 copies."""
    path = Path(path)
    if len(scan) and int(scan.profile_index.max()) > np.iinfo(np.int32).max:
        raise CloudFileError(f"{path}: profile index {int(scan.profile_index.max())} does not fit int32")
    props = "".join(
        f"property {'float' if n in 'xyz' else 'double' if n == 't_s' else 'int'} {n}\n"
        for n in _PLY_VERTEX.names
    )
    head = f"ply\nformat binary_little_endian 1.0\ncomment {_PLY_COMMENT}\nelement vertex {scan.n_valid}\n"
    with path.open("wb") as f:
        f.write((head + props + "end_header\n").encode("ascii"))
        for b in scan.cloud_blocks():
            rec = np.empty(len(b["t_s"]), _PLY_VERTEX)
            rec["x"], rec["y"], rec["z"] = b["xyz_mm"].T
            rec["pass"], rec["profile"], rec["point"] = b["pass_id"], b["profile_index"], b["point_index"]
            rec["t_s"] = b["t_s"]
            f.write(rec.tobytes())
    return path


_LAS_POINT = np.dtype(
    [
        ("X", "<i4"),
        ("Y", "<i4"),
        ("Z", "<i4"),
        ("intensity", "<u2"),
        ("returns", "u1"),
        ("flags", "u1"),
        ("classification", "u1"),
        ("user_data", "u1"),
        ("scan_angle", "<i2"),
        ("point_source_id", "<u2"),
        ("gps_time", "<f8"),
        ("profile", "<u4"),
        ("point", "<u2"),
    ]
)
assert _LAS_POINT.itemsize == 36


def _extra_bytes_vlr() -> bytes:
    def descriptor(data_type: int, name: str, description: str) -> bytes:
        d = bytearray(_EXTRA_BYTES_DESCRIPTOR)
        d[2] = data_type
        d[4 : 4 + len(name)] = name.encode()
        d[160 : 160 + len(description)] = description.encode()
        return bytes(d)

    payload = descriptor(5, "profile", "running profile index") + descriptor(
        3, "point", "column in the profile"
    )
    header = struct.pack("<H16sHH32s", 0, b"LASF_Spec", 4, len(payload), b"extra bytes: profile, point")
    return header + payload


def write_las(cloud: AssembledScan, path: str | Path) -> Path:
    """Write the valid points of ``cloud`` as LAS 1.4, point format 6 + extra bytes; returns the path.

    Two passes over blocks of rows (:meth:`AssembledScan.cloud_blocks`): the extent for the header,
    then the records; a block's points in memory at a time (a 6 m plate: 170 M points)."""
    path = Path(path)
    n = cloud.n_valid
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    pass_max = 0
    for b in cloud.cloud_blocks():
        if len(b["t_s"]):
            lo = np.minimum(lo, b["xyz_mm"].min(axis=0).astype(np.float64))
            hi = np.maximum(hi, b["xyz_mm"].max(axis=0).astype(np.float64))
            pass_max = max(pass_max, int(b["pass_id"].max()))
    lo = np.floor(lo) if n else np.zeros(3)
    hi = hi if n else np.zeros(3)
    if n and np.rint((hi - lo) / LAS_SCALE_MM).max() > np.iinfo(np.int32).max:
        raise CloudFileError(f"{path}: cloud extent {hi - lo} mm does not fit int32 at {LAS_SCALE_MM} mm")
    if n and pass_max >= 65535:
        raise CloudFileError(f"{path}: pass id {pass_max} does not fit point_source_id")
    vlr = _extra_bytes_vlr()
    today = _dt.date.today()
    by_return = [n] + [0] * 14
    header = struct.pack(
        "<4sHH16sBB32s32sHHHIIBHI5I3d3d6dQQIQ15Q",
        b"LASF",
        0,  # file source id
        0x10,  # global encoding: WKT bit (required for point formats 6-10; no CRS: a robot frame)
        b"\0" * 16,
        1,
        4,
        b"cellctl robot base frame, mm",
        b"cellctl acquisition",
        today.timetuple().tm_yday,
        today.year,
        _LAS_HEADER_SIZE,
        _LAS_HEADER_SIZE + len(vlr),
        1,  # one VLR
        6,  # point data record format
        _LAS_POINT.itemsize,
        0,  # legacy point count: 0 for format 6+
        0,
        0,
        0,
        0,
        0,
        LAS_SCALE_MM,
        LAS_SCALE_MM,
        LAS_SCALE_MM,
        *lo,
        hi[0],
        lo[0],
        hi[1],
        lo[1],
        hi[2],
        lo[2],
        0,  # waveform data
        0,  # first EVLR
        0,  # number of EVLRs
        n,
        *by_return,
    )
    assert len(header) == _LAS_HEADER_SIZE
    with open(path, "wb") as f:
        f.write(header)
        f.write(vlr)
        for b in cloud.cloud_blocks():
            rec = np.zeros(len(b["t_s"]), dtype=_LAS_POINT)
            scaled = np.rint((b["xyz_mm"].astype(np.float64) - lo) / LAS_SCALE_MM).astype(np.int32)
            rec["X"], rec["Y"], rec["Z"] = scaled.T
            rec["returns"] = 0x11  # return 1 of 1
            rec["point_source_id"] = (b["pass_id"] + 1).astype(np.uint16)
            rec["gps_time"] = b["t_s"]
            rec["profile"] = b["profile_index"].astype(np.uint32)
            rec["point"] = b["point_index"].astype(np.uint16)
            f.write(rec.tobytes())
    return path


def read_las(path: str | Path) -> dict[str, np.ndarray]:
    """Read a LAS file written by :func:`write_las`: ``xyz_mm`` (n, 3) float64, ``pass_id``,
    ``profile_index``, ``point_index``, ``t_s`` (the cloud vocabulary; an older file's transit, point
    source 0, reads as pass 0)."""
    data = Path(path).read_bytes()
    if data[:4] != b"LASF" or data[24:26] != b"\x01\x04":
        raise CloudFileError(
            f"{path}: not a LAS 1.4 file (signature {data[:4]!r}, version {data[24:26].hex()})"
        )
    offset, _nvlr, fmt, reclen = struct.unpack_from("<IIBH", data, 96)
    if fmt != 6 or reclen != _LAS_POINT.itemsize:
        raise CloudFileError(
            f"{path}: point format {fmt} / length {reclen}, expected 6 / {_LAS_POINT.itemsize}"
        )
    scale = np.array(struct.unpack_from("<3d", data, 131))
    off = np.array(struct.unpack_from("<3d", data, 155))
    (n,) = struct.unpack_from("<Q", data, 247)
    rec = np.frombuffer(data, dtype=_LAS_POINT, count=n, offset=offset)
    xyz = np.column_stack([rec["X"], rec["Y"], rec["Z"]]).astype(np.float64) * scale + off
    return {
        "xyz_mm": xyz,
        "pass_id": np.maximum(rec["point_source_id"].astype(np.int32) - 1, 0),
        "profile_index": rec["profile"].copy(),
        "point_index": rec["point"].copy(),
        "t_s": rec["gps_time"].copy(),
    }
