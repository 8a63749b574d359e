"""The binary layout of a published cloud (daemon -> analysis worker), and its codec.

One message is one scan. Chosen for speed: a small fixed header, a field table, a UTF-8 JSON
metadata block, then each array as raw little-endian bytes, 8-byte aligned, so decoding is
``np.frombuffer`` per field (no per-point work, no copy). Layout version 1::

    offset  size  type     header
    0       4     bytes    magic b"CCLD"
    4       2     u16      version (1)
    6       2     u16      header size in bytes (48)
    8       8     u64      n_points
    16      2     u16      n_fields
    18      2     u16      reserved, 0
    20      4     u32      meta_len: bytes of the metadata JSON
    24      8     u64      data_offset: where the first array starts
    32      8     u64      total_size: the whole message in bytes
    40      4     u32      CRC-32 of bytes 0..39 + field table + metadata
    44      4     u32      reserved, 0

    then n_fields entries of 32 bytes:
    0       16    ascii    field name, NUL padded
    16      1     u8       dtype code (1 f32, 2 f64, 3 u8, 4 u16, 5 u32, 6 u64)
    17      1     u8       components per point
    18      6     -        reserved, 0
    24      8     u64      offset of the array from the start of the message (multiple of 8)

    then meta_len bytes of JSON, the object of :class:`CloudMetaBlock`:
    {"job_id": str, "plate_id": str, "frame": "robot base", "cell_id": str | null,
     "placement": {"pos_mm": [x, y, z], "rpy_deg": [r, p, y]} | null}

Fields (fixed dtype each; ``xyz_mm`` required, the others optional):
``xyz_mm`` f32 x3 (mm, robot base frame), ``pass_id`` u16, ``profile_index`` u32 (profile within
its pass), ``point_index`` u16 (point along the laser line), ``t_s`` f64 (s, cell clock); pass,
profile and point together are the point's place on the scan grid: the names, the transit
convention and the meaning of ``t_s`` are those of ``analysis.cloud_io.ScanCloud``, which the
worker hands to the analysis (:meth:`Cloud.scan_cloud`). Arrays follow in table order, without overlap.
The payload itself is not checksummed: Zenoh runs over TCP, which already is.

The metadata is a pydantic model (:class:`CloudMeta`, with the ids :class:`CloudMetaBlock`): a key
it does not name is refused (CloudFormatError, field ``meta``). Every daemon since the first
(2026-11-22) has written all five keys, so every kept ``cloud.bin`` decodes; ``frame``, ``cell_id``
and ``placement`` are optional, so a message of only the two ids (a tool's, a test's) decodes too.
Nothing in the cell reads them back (the worker takes the placement from its job, not the cloud):
they make a downloaded ``cloud.bin`` say where it was measured.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from analysis.cloud_io import ScanCloud
from analysis.contracts.placement import Placement

MAGIC = b"CCLD"
VERSION = 1
HEADER = struct.Struct("<4sHHQHHIQQII")
FIELD_ENTRY = struct.Struct("<16sBB6xQ")
HEADER_SIZE = HEADER.size  # 48
MAX_META_BYTES = 64 * 1024
MAX_FIELDS = 16
ALIGN = 8
ENCODING = "application/x-cellctl-cloud"

_DTYPE_CODES: dict[int, np.dtype] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("u1"),
    4: np.dtype("<u2"),
    5: np.dtype("<u4"),
    6: np.dtype("<u8"),
}
_CODE_OF = {dt: code for code, dt in _DTYPE_CODES.items()}
# name -> (dtype, components)
FIELDS: dict[str, tuple[np.dtype, int]] = {
    "xyz_mm": (np.dtype("<f4"), 3),
    "pass_id": (np.dtype("<u2"), 1),
    "profile_index": (np.dtype("<u4"), 1),
    "point_index": (np.dtype("<u2"), 1),
    "t_s": (np.dtype("<f8"), 1),
}
OPTIONAL_FIELDS = ("pass_id", "profile_index", "point_index", "t_s")


class CloudFormatError(ValueError):
    """A cloud message (or a cloud to encode) that breaks the layout; names the field or byte offset."""

    def __init__(self, message: str, *, field: str | None = None, offset: int | None = None) -> None:
        self.field = field
        self.offset = offset
        where = []
        if field is not None:
            where.append(f"field {field!r}")
        if offset is not None:
            where.append(f"byte {offset}")
        super().__init__(f"{message} ({', '.join(where)})" if where else message)


class CloudMeta(BaseModel):
    """What a cloud says of itself beyond its job: the frame of ``xyz_mm`` (always the robot base),
    the cell that measured it, and the placement the job was scanned with (None: found by a locate
    run after the record was made, or not given)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    frame: Literal["robot base"] = "robot base"
    cell_id: str | None = None
    placement: Placement | None = None


class CloudMetaBlock(CloudMeta):
    """The metadata block on the wire: :class:`CloudMeta` with the job's ids."""

    job_id: str
    plate_id: str

    @property
    def meta(self) -> CloudMeta:
        return CloudMeta.model_validate(self.model_dump(exclude={"job_id", "plate_id"}))


@dataclass(frozen=True)
class Cloud:
    """One assembled scan on the wire: the arrays of :class:`analysis.cloud_io.ScanCloud` (the same
    names and conventions) at the wire's dtypes, with the job it belongs to.

    xyz_mm: (n, 3) float32, mm, robot base frame. Optional per-point arrays, each (n,):
    pass_id uint16 (transit under pass 0), profile_index uint32 (running within the scan),
    point_index uint16 (along the line), t_s float64 (exposure time, s from the first profile).
    ``meta`` says the frame, the cell and the placement (:class:`CloudMeta`).
    """

    xyz_mm: np.ndarray
    job_id: str
    plate_id: str
    pass_id: np.ndarray | None = None
    profile_index: np.ndarray | None = None
    point_index: np.ndarray | None = None
    t_s: np.ndarray | None = None
    meta: CloudMeta = field(default_factory=CloudMeta)

    @property
    def n_points(self) -> int:
        return int(self.xyz_mm.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        """The present per-point arrays by field name (xyz_mm first)."""
        out = {"xyz_mm": self.xyz_mm}
        for name in OPTIONAL_FIELDS:
            arr = getattr(self, name)
            if arr is not None:
                out[name] = arr
        return out

    def scan_cloud(self) -> ScanCloud:
        """The analysis' cloud (what a worker hands to the analysis): organised when all three
        organisation arrays came along, with the exposure times when they did."""
        org = [self.pass_id, self.profile_index, self.point_index]
        if all(a is not None for a in org):
            return ScanCloud(self.xyz_mm, *org, t_s=self.t_s)
        return ScanCloud(self.xyz_mm, t_s=self.t_s)


def _pad(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def _check_array(name: str, arr: Any, n: int | None) -> np.ndarray:
    dtype, comps = FIELDS[name]
    a = np.asarray(arr)
    want = (a.shape[0] if n is None else n, comps) if comps > 1 else (a.shape[0] if n is None else n,)
    if a.ndim != len(want) or a.shape != want:
        raise CloudFormatError(f"expected shape {want}, got {a.shape}", field=name)
    if a.dtype != dtype:
        if dtype.kind in "ui" and a.dtype.kind not in "uib":
            raise CloudFormatError(f"expected integers ({dtype}), got {a.dtype}", field=name)
        if dtype.kind in "ui" and a.size and (a.min() < 0 or a.max() > np.iinfo(dtype).max):
            raise CloudFormatError(f"values outside the range of {dtype}", field=name)
        a = a.astype(dtype)
    return a


def encode_cloud(cloud: Cloud) -> bytearray:
    """Serialise a cloud into one message (layout above). Raises CloudFormatError on bad arrays.

    Cost: one copy of each array into the output buffer.
    """
    xyz = _check_array("xyz_mm", cloud.xyz_mm, None)
    n = xyz.shape[0]
    if not np.isfinite(xyz).all():
        raise CloudFormatError("non-finite coordinates", field="xyz_mm")
    arrays = {"xyz_mm": xyz}
    for name in OPTIONAL_FIELDS:
        arr = getattr(cloud, name)
        if arr is not None:
            arrays[name] = _check_array(name, arr, n)
    if "t_s" in arrays and not np.isfinite(arrays["t_s"]).all():
        raise CloudFormatError("non-finite times", field="t_s")
    out, views = allocate_cloud(
        cloud.job_id, cloud.plate_id, cloud.meta, n, {name: a.dtype for name, a in arrays.items()}
    )
    for name, arr in arrays.items():
        views[name][:] = arr
    return out


def allocate_cloud(
    job_id: str, plate_id: str, meta: CloudMeta, n: int, fields: dict[str, np.dtype]
) -> tuple[bytearray, dict[str, np.ndarray]]:
    """A message of ``n`` points with ``fields`` (name -> dtype, in order; ``xyz_mm`` first), its
    header, field table and metadata written, and each field's array as a view into it to be filled
    (``(n, 3)`` for ``xyz_mm``): an encoder that writes the points where they go, without a whole
    cloud first and its copy (:func:`cellctl.acquisition.publish.encode_scan`). The views are not
    checked: :func:`encode_cloud` checks its arrays before it fills them."""
    for name, dtype in fields.items():
        if name not in FIELDS or np.dtype(dtype) != FIELDS[name][0]:
            raise CloudFormatError(f"dtype {np.dtype(dtype)} is not the field's", field=name)
    sizes = {name: (FIELDS[name][0], n * FIELDS[name][1] * FIELDS[name][0].itemsize) for name in fields}
    prefix, offsets, total = _encoded_prefix(job_id, plate_id, meta, n, sizes)
    out = bytearray(total)
    out[: len(prefix)] = prefix
    views = {}
    for name in fields:
        dtype, comps = FIELDS[name]
        v = np.frombuffer(out, dtype=dtype, count=n * comps, offset=offsets[name])
        views[name] = v.reshape(n, comps) if comps > 1 else v
    return out, views


def _encoded_prefix(
    job_id: str, plate_id: str, meta: CloudMeta, n: int, arrays: dict[str, tuple[np.dtype, int]]
) -> tuple[bytes, dict[str, int], int]:
    """The header, field table and metadata of a message of ``n`` points holding ``arrays`` (name ->
    (dtype, bytes), in their order), padded up to the first array: ``(prefix, offsets of the arrays,
    total size)``."""
    if not isinstance(meta, CloudMeta):
        raise CloudFormatError(f"metadata is a {type(meta).__name__}, not a CloudMeta", field="meta")
    block = {"job_id": str(job_id), "plate_id": str(plate_id), **meta.model_dump(mode="json")}
    meta_bytes = json.dumps(block, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(meta_bytes) > MAX_META_BYTES:
        raise CloudFormatError(f"metadata is {len(meta_bytes)} bytes, limit {MAX_META_BYTES}", field="meta")

    table_size = FIELD_ENTRY.size * len(arrays)
    data_offset = _pad(HEADER_SIZE + table_size + len(meta_bytes))
    offsets = {}
    pos = data_offset
    for name, (_, nbytes) in arrays.items():
        offsets[name] = pos
        pos = _pad(pos + nbytes)
    total = pos
    table = b"".join(
        FIELD_ENTRY.pack(name.encode("ascii"), _CODE_OF[dtype], FIELDS[name][1], offsets[name])
        for name, (dtype, _) in arrays.items()
    )
    head = HEADER.pack(
        MAGIC, VERSION, HEADER_SIZE, n, len(arrays), 0, len(meta_bytes), data_offset, total, 0, 0
    )
    crc = zlib.crc32(head[:40] + table + meta_bytes)
    prefix = head[:40] + struct.pack("<II", crc, 0) + table + meta_bytes
    return prefix + bytes(data_offset - len(prefix)), offsets, total


def decode_cloud(buf: bytes | bytearray | memoryview, *, check_finite: bool = True) -> Cloud:
    """Parse one message into a Cloud; the arrays are views into ``buf`` (no copy).

    Every header value is checked against the buffer before any array is built. Raises
    CloudFormatError naming the field or byte offset of the first problem.
    """
    mv = memoryview(buf).cast("B")
    size = mv.nbytes
    if size < HEADER_SIZE:
        raise CloudFormatError(
            f"message is {size} bytes, shorter than the {HEADER_SIZE}-byte header", offset=0
        )
    (magic, version, header_size, n, n_fields, reserved, meta_len, data_offset, total, crc, reserved2) = (
        HEADER.unpack_from(mv, 0)
    )
    if magic != MAGIC:
        raise CloudFormatError(f"bad magic {bytes(magic)!r}, expected {MAGIC!r}", field="magic", offset=0)
    if version != VERSION:
        raise CloudFormatError(
            f"unsupported version {version}, this reader speaks {VERSION}", field="version", offset=4
        )
    if header_size != HEADER_SIZE:
        raise CloudFormatError(
            f"header size {header_size}, expected {HEADER_SIZE}", field="header_size", offset=6
        )
    if reserved or reserved2:
        raise CloudFormatError("reserved header bytes are not zero", field="reserved", offset=18)
    if total != size:
        raise CloudFormatError(
            f"header says {total} bytes, message has {size}", field="total_size", offset=32
        )
    if not 1 <= n_fields <= MAX_FIELDS:
        raise CloudFormatError(f"{n_fields} fields, expected 1..{MAX_FIELDS}", field="n_fields", offset=16)
    if meta_len > MAX_META_BYTES:
        raise CloudFormatError(
            f"metadata length {meta_len} over {MAX_META_BYTES}", field="meta_len", offset=20
        )
    table_end = HEADER_SIZE + FIELD_ENTRY.size * n_fields
    meta_end = table_end + meta_len
    if meta_end > size or data_offset < meta_end or data_offset % ALIGN or data_offset > size:
        raise CloudFormatError(
            f"data offset {data_offset} inconsistent with table/metadata end {meta_end} and size {size}",
            field="data_offset",
            offset=24,
        )
    if zlib.crc32(bytes(mv[:40]) + bytes(mv[HEADER_SIZE:meta_end])) != crc:
        raise CloudFormatError("header checksum mismatch", field="header_crc", offset=40)
    block = _meta_block(mv[table_end:meta_end], table_end)

    arrays: dict[str, np.ndarray] = {}
    cursor = data_offset
    for i in range(n_fields):
        at = HEADER_SIZE + i * FIELD_ENTRY.size
        raw_name, code, comps, offset = FIELD_ENTRY.unpack_from(mv, at)
        name = raw_name.rstrip(b"\0").decode("ascii", errors="replace")
        if name not in FIELDS:
            raise CloudFormatError(f"unknown field name {name!r}", field=name, offset=at)
        if name in arrays:
            raise CloudFormatError("field appears twice", field=name, offset=at)
        dtype, want_comps = FIELDS[name]
        if _DTYPE_CODES.get(code) != dtype or comps != want_comps:
            raise CloudFormatError(
                f"dtype code {code} x{comps}, expected {dtype} x{want_comps}", field=name, offset=at + 16
            )
        nbytes = n * comps * dtype.itemsize
        if offset % ALIGN or offset < cursor or offset + nbytes > size:
            raise CloudFormatError(
                f"array at {offset}+{nbytes} overlaps, is unaligned, or runs past the {size}-byte message",
                field=name,
                offset=at + 24,
            )
        arr = np.frombuffer(mv, dtype=dtype, count=n * comps, offset=offset)
        arrays[name] = arr.reshape(n, comps) if comps > 1 else arr
        cursor = offset + nbytes
    if "xyz_mm" not in arrays:
        raise CloudFormatError("required field is missing", field="xyz_mm")
    if check_finite and not np.isfinite(arrays["xyz_mm"]).all():
        raise CloudFormatError("non-finite coordinates", field="xyz_mm")
    return Cloud(job_id=block.job_id, plate_id=block.plate_id, meta=block.meta, **arrays)


def _meta_block(raw: memoryview, offset: int) -> CloudMetaBlock:
    """The metadata JSON at ``offset`` as its model; CloudFormatError (field ``meta``) when it is not
    UTF-8 JSON, not an object, lacks a string id, or has a key the model does not name."""
    try:
        return CloudMetaBlock.model_validate_json(bytes(raw))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "metadata"
        raise CloudFormatError(f"metadata {where}: {first['msg']}", field="meta", offset=offset) from None


def peek_meta(buf: bytes | bytearray | memoryview) -> tuple[CloudMetaBlock, int]:
    """Only the metadata and n_points, without touching the arrays: ``(block, n_points)``."""
    mv = memoryview(buf).cast("B")
    if mv.nbytes < HEADER_SIZE or bytes(mv[:4]) != MAGIC:
        raise CloudFormatError("not a cloud message", field="magic", offset=0)
    _, _, _, n, n_fields, _, meta_len, _, _, _, _ = HEADER.unpack_from(mv, 0)
    start = HEADER_SIZE + FIELD_ENTRY.size * n_fields
    if n_fields > MAX_FIELDS or meta_len > MAX_META_BYTES or start + meta_len > mv.nbytes:
        raise CloudFormatError("header inconsistent with message size", field="meta_len", offset=20)
    return _meta_block(mv[start : start + meta_len], start), int(n)


def concat_encoded(payloads: list[bytes | bytearray]) -> bytearray:
    """Encoded clouds of one job, one after the other, as one encoded cloud (the ids and ``meta`` of
    the first; every per-point array present in all of them). A streamed job's chunks -> its cloud."""
    if not payloads:
        raise CloudFormatError("no cloud to concatenate")
    clouds = [decode_cloud(p) for p in payloads]
    first = clouds[0]
    if len(clouds) == 1:
        return encode_cloud(first)
    arrays = {
        name: np.concatenate([getattr(c, name) for c in clouds])
        for name in ("xyz_mm", *OPTIONAL_FIELDS)
        if all(getattr(c, name) is not None for c in clouds)
    }
    return encode_cloud(Cloud(job_id=first.job_id, plate_id=first.plate_id, meta=first.meta, **arrays))


def write_concatenated(
    path: str | Path,
    payloads: Sequence[bytes | bytearray | memoryview],
    *,
    read: Callable[[np.ndarray], None] | None = None,
) -> int:
    """Write :func:`concat_encoded` of ``payloads`` to ``path``, the same bytes, without building it in
    memory: each array goes to the file straight from the chunks it is in (a streamed scan's cloud,
    70 MB on the sail plate, written while its analysis runs). Returns the bytes written.

    read: called with each chunk's array once it has been read (checked or written): the daemon's
    chunks are memory-mapped from a spill file, whose pages it then takes out of memory again."""
    if not payloads:
        raise CloudFormatError("no cloud to concatenate")
    clouds = []
    for p in payloads:
        clouds.append(decode_cloud(p))
        if read is not None:
            read(clouds[-1].xyz_mm)  # read by the finiteness check
    first = clouds[0]
    names = [
        name for name in ("xyz_mm", *OPTIONAL_FIELDS) if all(getattr(c, name) is not None for c in clouds)
    ]
    n = sum(c.n_points for c in clouds)
    fields = {
        name: (getattr(first, name).dtype, sum(getattr(c, name).nbytes for c in clouds)) for name in names
    }
    prefix, offsets, total = _encoded_prefix(first.job_id, first.plate_id, first.meta, n, fields)
    with open(path, "wb") as f:
        f.write(prefix)
        for name in names:
            assert f.tell() == offsets[name]
            for c in clouds:  # views into the chunks (decode_cloud copies nothing)
                arr = getattr(c, name)
                if arr.size:
                    f.write(memoryview(np.ascontiguousarray(arr).reshape(-1)).cast("B"))
                    if read is not None:
                        read(arr)
            f.write(bytes(_pad(f.tell()) - f.tell()))
        assert f.tell() == total
    return total
