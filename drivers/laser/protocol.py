"""HD8 profile protocol codec: bytes <-> messages, shared by the client and the simulator.

No I/O here (pymodbus shape: framer + messages, transport elsewhere). The wire format is specified in
``docs/hd8-protocol.md``; this module is its executable form. Everything is little-endian.

Every message, on both channels, starts with a 6-byte header: ``size u32`` (the whole message, header
included) and ``control u16`` (bits 0-14 message type or command id, bit 15 = last message of a frame
group). On the data channel a frame group is a STAMP message followed by one PROFILE message (uniform
or point-pair) carrying the same ``count`` profiles; the profile message has the last flag.

Encoding and decoding work on whole batches of profiles with numpy (no per-point Python).
"""

from __future__ import annotations

import enum
import functools
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.laser.source import ProfileBatch

__all__ = [
    "HEADER",
    "INVALID_RAW",
    "LIVE",
    "MAX_MESSAGE_SIZE",
    "PROFILE_HEADER_SIZE",
    "STAMP_DTYPE",
    "STAMP_HEADER_SIZE",
    "Command",
    "CommandError",
    "CommandId",
    "DecodeError",
    "DecodedGroups",
    "FramingError",
    "GroupAssembler",
    "Message",
    "MessageFramer",
    "MessageType",
    "ProfileFormat",
    "ProfileScale",
    "ProtocolError",
    "ProtocolTimeout",
    "Reply",
    "SensorInfo",
    "SensorState",
    "StateReply",
    "Status",
    "StatusBits",
    "TimestampReply",
    "TriggerMode",
    "decode_command",
    "decode_group",
    "decode_groups",
    "decode_reply",
    "decode_subscribe",
    "decode_u32_param",
    "encode_command",
    "encode_frame_group",
    "encode_reply",
    "encode_subscribe",
    "quantize_mm",
]

HEADER = struct.Struct("<IH")  # size u32, control u16
LAST_FLAG = 0x8000
TYPE_MASK = 0x7FFF
#: Largest message either side accepts; a bigger size field means the stream is corrupt.
MAX_MESSAGE_SIZE = 64 * 1024 * 1024
MAX_PROFILES_PER_MESSAGE = 65_535
MAX_WIDTH = 8192
#: Raw int16 value for "no return" (Gocator convention).
INVALID_RAW = -32768
#: SUBSCRIBE start frame meaning "no replay, live frames only".
LIVE = 0xFFFF_FFFF_FFFF_FFFF
PROTOCOL_VERSION = 1


class ProtocolError(Exception):
    """Base class of every HD8 protocol error."""


class DecodeError(ProtocolError):
    """A message failed validation; the stream framing is still intact, the group can be skipped.

    Attributes:
        field: name of the offending field.
        data: up to 64 bytes of the offending message, for the log.
    """

    def __init__(self, message: str, *, field: str = "", data: bytes | memoryview = b"") -> None:
        self.field = field
        self.data = bytes(data[:64])
        suffix = f" (field {field})" if field else ""
        super().__init__(f"{message}{suffix}; bytes {self.data.hex()}")


class FramingError(DecodeError):
    """The byte stream cannot be split into messages any more; the connection must be dropped."""


class CommandError(ProtocolError):
    """The sensor answered a control command with a status other than OK."""

    def __init__(self, command: int, status: int, detail: str = "") -> None:
        self.command = command
        self.status = status
        try:
            cname = CommandId(command).name
        except ValueError:
            cname = f"0x{command:04x}"
        try:
            sname = Status(status).name
        except ValueError:
            sname = str(status)
        super().__init__(f"command {cname} failed with status {sname}{': ' + detail if detail else ''}")


class ProtocolTimeout(ProtocolError, TimeoutError):
    """No reply (or no data) within the allowed time."""


class MessageType(enum.IntEnum):
    """Data-channel message types (bits 0-14 of ``control``)."""

    STAMP = 0x0001
    PROFILE_POINTS = 0x0005  # int16 (x, z) pairs, unresampled
    PROFILE_UNIFORM = 0x0006  # int16 z on a uniform x grid
    SUBSCRIBE = 0x0100  # host -> sensor, first message on a data connection


class ProfileFormat(enum.IntEnum):
    """Profile representation on the wire (values equal the message type)."""

    POINTS = MessageType.PROFILE_POINTS
    UNIFORM = MessageType.PROFILE_UNIFORM


class CommandId(enum.IntEnum):
    """Control-channel commands."""

    GET_INFO = 0x4001
    SET_EXPOSURE = 0x4002  # u32 ns
    SET_RATE = 0x4003  # u32 mHz
    SET_TRIGGER_MODE = 0x4004  # u32 TriggerMode
    SET_PROFILE_FORMAT = 0x4005  # u32 ProfileFormat
    START = 0x4010
    STOP = 0x4011
    RESET_TIMESTAMP = 0x4020
    GET_TIMESTAMP = 0x4021
    GET_STATE = 0x4030
    KEEP_ALIVE = 0x4040


class Status(enum.IntEnum):
    """Reply status (Gocator convention: 1 = OK, negative = error)."""

    OK = 1
    FAILED = -1
    UNKNOWN_COMMAND = -2
    INVALID_PARAMETER = -3
    INVALID_STATE = -4
    MALFORMED = -5


class TriggerMode(enum.IntEnum):
    """Acquisition trigger, numbered like the HD8 SDK's ``TriggerMode``."""

    TIME = 0  # internal free-run at the configured rate
    EXTERNAL = 1  # one profile per rising edge on the trigger input
    ENCODER = 2  # encoder-triggered


class StatusBits(enum.IntFlag):
    """Per-frame status bits in the stamp."""

    TRIGGER_INPUT = 1 << 0  # state of the digital trigger input at exposure
    TIME_FROM_MS_COUNTER = 1 << 1  # sensor_time_us was derived from the 1 ms counter (1 ms resolution)
    OVERRUN = 1 << 2  # the sensor lost frames before this one (buffer overrun)
    REPLAYED = 1 << 3  # sent from the sensor's ring buffer after a SUBSCRIBE with a start frame


class SensorState(enum.IntEnum):
    READY = 0
    RUNNING = 1


# --------------------------------------------------------------------------------------------- framing


@dataclass(frozen=True)
class Message:
    """One framed message: type (or command id), last-of-group flag, the whole message bytes."""

    type: int
    last: bool
    data: bytes


class MessageFramer:
    """Incremental splitter of a byte stream into :class:`Message` objects.

    Feed it whatever the transport delivered; it returns every complete message and keeps the rest.
    A size field that is too small or too large raises :class:`FramingError`: after that the stream
    position is unknown and the connection has to be dropped.
    """

    def __init__(self, max_message_size: int = MAX_MESSAGE_SIZE) -> None:
        self._buf = bytearray()
        self._max = max_message_size

    @property
    def pending(self) -> int:
        """Bytes buffered but not yet part of a complete message."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        """Append ``data`` and return the complete messages it finished (possibly none)."""
        buf = self._buf
        buf += data
        out: list[Message] = []
        off = 0
        n = len(buf)
        while n - off >= HEADER.size:
            size, control = HEADER.unpack_from(buf, off)
            if size < HEADER.size or size > self._max:
                bad = bytes(buf[off : off + 16])
                self._buf = bytearray()
                raise FramingError(f"message size {size} outside [6, {self._max}]", field="size", data=bad)
            if n - off < size:
                break
            out.append(Message(control & TYPE_MASK, bool(control & LAST_FLAG), bytes(buf[off : off + size])))
            off += size
        if off:
            del buf[:off]
        return out


def _header(msg_type: int, size: int, last: bool) -> bytes:
    return HEADER.pack(size, (msg_type & TYPE_MASK) | (LAST_FLAG if last else 0))


# --------------------------------------------------------------------------------------------- stamps

STAMP_HEADER = struct.Struct("<IHIHH")  # size, control, count u32, stamp_size u16, reserved u16
STAMP_HEADER_SIZE = STAMP_HEADER.size  # 14
STAMP_DTYPE = np.dtype(
    [
        ("frame_index", "<u8"),
        ("sensor_time_us", "<u8"),
        ("encoder", "<i8"),
        ("hd8_ms", "<u4"),
        ("status", "<u4"),
        ("exposure_ns", "<u4"),
        ("reserved", "<u4"),
    ]
)
assert STAMP_DTYPE.itemsize == 40

# ---------------------------------------------------------------------------------------------- profiles

# size, control, attr_size u16, count u32, width u32, x_scale_nm u32, z_scale_nm u32, x_offset_um s32,
# z_offset_um s32, first_frame_index u64
PROFILE_HEADER = struct.Struct("<IHHIIIIiiQ")
PROFILE_HEADER_SIZE = PROFILE_HEADER.size  # 40
PROFILE_ATTR_SIZE = PROFILE_HEADER_SIZE - HEADER.size  # 34


@dataclass(frozen=True)
class ProfileScale:
    """Integer scaling of profile values: ``mm = raw * scale_nm / 1e6 + offset_um / 1e3``.

    For a uniform profile, x of point ``i`` is ``i * x_scale_nm / 1e6 + x_offset_um / 1e3``
    (``x_scale_nm`` is the x pitch).
    """

    x_scale_nm: int
    z_scale_nm: int
    x_offset_um: int
    z_offset_um: int

    def __post_init__(self) -> None:
        for name in ("x_scale_nm", "z_scale_nm"):
            v = getattr(self, name)
            if not 0 < v < 2**32:
                raise ValueError(f"ProfileScale.{name}={v} must be in (0, 2**32)")
        for name in ("x_offset_um", "z_offset_um"):
            v = getattr(self, name)
            if not -(2**31) <= v < 2**31:
                raise ValueError(f"ProfileScale.{name}={v} does not fit s32")

    def uniform_x_mm(self, width: int) -> np.ndarray:
        """(width,) float32 x of each uniform-grid point, mm."""
        return (
            np.arange(width, dtype=np.float64) * (self.x_scale_nm * 1e-6) + self.x_offset_um * 1e-3
        ).astype(np.float32)


def quantize_mm(values_mm: np.ndarray, valid: np.ndarray, scale_nm: int, offset_um: int) -> np.ndarray:
    """Quantise millimetre values to the wire's int16 raw values.

    Args:
        values_mm: (...) float, mm.
        valid: (...) bool; False, non-finite or out-of-range values become :data:`INVALID_RAW`.
        scale_nm: size of one raw step, nm.
        offset_um: value of raw 0, um.

    Returns:
        (...) int16 raw values.
    """
    raw = np.rint((np.asarray(values_mm, dtype=np.float64) - offset_um * 1e-3) / (scale_nm * 1e-6))
    ok = valid & np.isfinite(raw) & (raw >= -32767) & (raw <= 32767)
    return np.where(ok, raw, INVALID_RAW).astype(np.int16)


def encode_frame_group(
    *,
    frame_index: np.ndarray,
    sensor_time_us: np.ndarray,
    hd8_ms: np.ndarray,
    encoder: np.ndarray,
    status: np.ndarray,
    exposure_ns: np.ndarray,
    scale: ProfileScale,
    z_raw: np.ndarray,
    x_raw: np.ndarray | None = None,
) -> bytes:
    """Encode ``n`` profiles as one frame group (STAMP message + PROFILE message with the last flag).

    Args:
        frame_index, sensor_time_us, hd8_ms, encoder, status, exposure_ns: (n,) stamp fields
            (see :class:`drivers.laser.source.ProfileBatch` for units).
        scale: integer scaling of x and z.
        z_raw: (n, w) int16 raw z (use :func:`quantize_mm`); :data:`INVALID_RAW` = no return.
        x_raw: (n, w) int16 raw x for the point-pair format; None for the uniform format.

    Returns:
        The group's bytes, ready to write on the data channel.
    """
    z_raw = np.asarray(z_raw)
    if z_raw.ndim != 2 or z_raw.dtype != np.int16:
        raise ValueError(f"z_raw must be (n, w) int16, got {z_raw.shape} {z_raw.dtype}")
    n, w = z_raw.shape
    if not 0 < n <= MAX_PROFILES_PER_MESSAGE or not 0 < w <= MAX_WIDTH:
        raise ValueError(f"profile count {n} / width {w} out of range")
    stamps = np.zeros(n, dtype=STAMP_DTYPE)
    for name, arr in (
        ("frame_index", frame_index),
        ("sensor_time_us", sensor_time_us),
        ("hd8_ms", hd8_ms),
        ("encoder", encoder),
        ("status", status),
        ("exposure_ns", exposure_ns),
    ):
        arr = np.asarray(arr)
        if arr.shape != (n,):
            raise ValueError(f"{name} has shape {arr.shape}, expected ({n},)")
        stamps[name] = arr
    stamp_size = STAMP_HEADER_SIZE + n * STAMP_DTYPE.itemsize
    parts = [STAMP_HEADER.pack(stamp_size, MessageType.STAMP, n, STAMP_DTYPE.itemsize, 0), stamps.tobytes()]
    if x_raw is None:
        msg_type = MessageType.PROFILE_UNIFORM
        body = np.ascontiguousarray(z_raw, dtype="<i2").tobytes()
    else:
        x_raw = np.asarray(x_raw)
        if x_raw.shape != z_raw.shape or x_raw.dtype != np.int16:
            raise ValueError(f"x_raw must be {z_raw.shape} int16, got {x_raw.shape} {x_raw.dtype}")
        msg_type = MessageType.PROFILE_POINTS
        body = np.stack([x_raw, z_raw], axis=-1).astype("<i2", copy=False).tobytes()
    size = PROFILE_HEADER_SIZE + len(body)
    parts.append(
        PROFILE_HEADER.pack(
            size,
            msg_type | LAST_FLAG,
            PROFILE_ATTR_SIZE,
            n,
            w,
            scale.x_scale_nm,
            scale.z_scale_nm,
            scale.x_offset_um,
            scale.z_offset_um,
            int(stamps["frame_index"][0]),
        )
    )
    parts.append(body)
    return b"".join(parts)


@dataclass(frozen=True)
class _GroupView:
    """A validated frame group: where its stamps and points are, and how to scale them."""

    stamps: bytes
    points: bytes
    count: int
    kind: int  # MessageType.PROFILE_UNIFORM or PROFILE_POINTS
    layout: tuple[int, int, int, int, int]  # width, x_scale_nm, z_scale_nm, x_offset_um, z_offset_um


def _validate_group(messages: Sequence[Message]) -> _GroupView:
    """Check every header field of one frame group; raise :class:`DecodeError` naming the first bad one."""
    if len(messages) != 2:
        types = [f"0x{m.type:04x}" for m in messages]
        raise DecodeError(
            f"frame group has {len(messages)} messages {types}, expected STAMP + PROFILE",
            field="group",
            data=messages[0].data if messages else b"",
        )
    stamp_msg, prof_msg = messages
    if stamp_msg.type != MessageType.STAMP:
        raise DecodeError(
            f"group starts with type 0x{stamp_msg.type:04x}, expected STAMP",
            field="type",
            data=stamp_msg.data,
        )
    if prof_msg.type not in (MessageType.PROFILE_UNIFORM, MessageType.PROFILE_POINTS):
        raise DecodeError(
            f"unknown profile message type 0x{prof_msg.type:04x}", field="type", data=prof_msg.data
        )
    sdata = stamp_msg.data
    if len(sdata) < STAMP_HEADER_SIZE:
        raise DecodeError(
            f"STAMP message of {len(sdata)} bytes is shorter than its header", field="size", data=sdata
        )
    ssize, _control, scount, stamp_size, _reserved = STAMP_HEADER.unpack_from(sdata)
    if stamp_size != STAMP_DTYPE.itemsize:
        raise DecodeError(
            f"STAMP stamp_size {stamp_size}, expected {STAMP_DTYPE.itemsize}", field="stamp_size", data=sdata
        )
    if scount == 0 or scount > MAX_PROFILES_PER_MESSAGE:
        raise DecodeError(f"STAMP count {scount} out of range", field="count", data=sdata)
    expected = STAMP_HEADER_SIZE + scount * stamp_size
    if ssize != expected:
        raise DecodeError(
            f"STAMP size {ssize} does not match count {scount} (expected {expected})",
            field="count",
            data=sdata,
        )
    data = prof_msg.data
    if len(data) < PROFILE_HEADER_SIZE:
        raise DecodeError(
            f"profile message of {len(data)} bytes is shorter than its header", field="size", data=data
        )
    (size, _control, attr_size, count, width, xs_nm, zs_nm, xo_um, zo_um, first_frame) = (
        PROFILE_HEADER.unpack_from(data)
    )
    if attr_size != PROFILE_ATTR_SIZE:
        raise DecodeError(
            f"profile attr_size {attr_size}, expected {PROFILE_ATTR_SIZE}", field="attr_size", data=data
        )
    if count != scount:
        raise DecodeError(f"profile count {count} != stamp count {scount}", field="count", data=data)
    if not 0 < width <= MAX_WIDTH:
        raise DecodeError(f"profile width {width} out of range", field="width", data=data)
    if xs_nm == 0 or zs_nm == 0:
        raise DecodeError(
            "profile scale is zero", field="x_scale_nm" if xs_nm == 0 else "z_scale_nm", data=data
        )
    per_point = 2 if prof_msg.type == MessageType.PROFILE_UNIFORM else 4
    expected = PROFILE_HEADER_SIZE + count * width * per_point
    if size != expected:
        raise DecodeError(
            f"profile size {size} does not match count {count} x width {width} (expected {expected})",
            field="size",
            data=data,
        )
    first_stamp = _U64.unpack_from(sdata, STAMP_HEADER_SIZE)[0]
    if first_frame != first_stamp:
        raise DecodeError(
            f"profile first_frame_index {first_frame} != stamp frame_index {first_stamp}",
            field="first_frame_index",
            data=data,
        )
    if count > 1:
        fi = np.frombuffer(sdata, dtype=STAMP_DTYPE, count=count, offset=STAMP_HEADER_SIZE)["frame_index"]
        if not np.all(fi[1:] > fi[:-1]):
            raise DecodeError("stamp frame indices do not increase", field="frame_index", data=sdata)
    return _GroupView(
        stamps=sdata[STAMP_HEADER_SIZE:],
        points=data[PROFILE_HEADER_SIZE:],
        count=count,
        kind=prof_msg.type,
        layout=(width, xs_nm, zs_nm, xo_um, zo_um),
    )


_U64 = struct.Struct("<Q")


@functools.lru_cache(maxsize=16)
def _uniform_x_row(width: int, xs_nm: int, xo_um: int) -> np.ndarray:
    row = (np.arange(width, dtype=np.float64) * (xs_nm * 1e-6) + xo_um * 1e-3).astype(np.float32)
    row.flags.writeable = False
    return row


def _scaled(raw: np.ndarray, scale_nm: int, offset_um: int) -> np.ndarray:
    """(n, w) int16 raw values -> (n, w) float32 mm, ``raw * scale + offset`` in float32.

    In place on one float32 array: the same float32 products and sums as the expression
    ``raw * np.float32(scale) + np.float32(offset)``, without its second temporary.
    """
    out = raw.astype(np.float32)
    out *= np.float32(scale_nm * 1e-6)
    out += np.float32(offset_um * 1e-3)
    return out


def _build_batch(views: Sequence[_GroupView], host_recv_ns: int) -> ProfileBatch:
    """One numpy decode for consecutive groups that share format, width and scale."""
    first = views[0]
    width, xs_nm, zs_nm, xo_um, zo_um = first.layout
    if len(views) == 1:
        sbytes, pbytes = first.stamps, first.points
    else:
        sbytes = b"".join(v.stamps for v in views)
        pbytes = b"".join(v.points for v in views)
    stamps = np.frombuffer(sbytes, dtype=STAMP_DTYPE)
    count = len(stamps)
    if first.kind == MessageType.PROFILE_UNIFORM:
        raw = np.frombuffer(pbytes, dtype="<i2").reshape(count, width)
        valid = raw != INVALID_RAW
        # every uniform profile has the same x: a read-only broadcast of one cached row, not n copies
        # (consumers see an (n, w) float32 array; the raw writer stores the row once)
        x_mm = np.broadcast_to(_uniform_x_row(width, xs_nm, xo_um), (count, width))
        z_mm = _scaled(raw, zs_nm, zo_um)
    else:
        raw = np.frombuffer(pbytes, dtype="<i2").reshape(count, width, 2)
        xr = raw[:, :, 0]
        zr = raw[:, :, 1]
        valid = (zr != INVALID_RAW) & (xr != INVALID_RAW)
        x_mm = _scaled(xr, xs_nm, xo_um)
        z_mm = _scaled(zr, zs_nm, zo_um)
    if not valid.all():
        invalid = ~valid
        np.copyto(z_mm, np.float32(np.nan), where=invalid)
        if first.kind != MessageType.PROFILE_UNIFORM:
            np.copyto(x_mm, np.float32(np.nan), where=invalid)
    return ProfileBatch(
        frame_index=stamps["frame_index"].astype(np.uint64),
        sensor_time_us=stamps["sensor_time_us"].astype(np.uint64),
        hd8_ms=stamps["hd8_ms"].astype(np.uint32),
        encoder=stamps["encoder"].astype(np.int64),
        status=stamps["status"].astype(np.uint32),
        exposure_ns=stamps["exposure_ns"].astype(np.uint32),
        x_mm=x_mm,
        z_mm=z_mm,
        valid=valid,
        host_recv_ns=np.full(count, host_recv_ns, dtype=np.int64),
    )


def decode_group(messages: Sequence[Message], host_recv_ns: int) -> ProfileBatch:
    """Decode one frame group (STAMP + PROFILE_UNIFORM or PROFILE_POINTS) into a :class:`ProfileBatch`.

    Args:
        messages: the group's messages in arrival order, the last one carrying the last flag.
        host_recv_ns: ``time.monotonic_ns()`` when the group was received; copied to every profile.

    Raises:
        DecodeError: wrong message types or order, sizes that disagree with count and width, counts
            that disagree between stamp and profile, frame indices that do not increase. The framing
            itself is intact, so the caller can skip this group and carry on.
    """
    return _build_batch([_validate_group(messages)], host_recv_ns)


@dataclass(frozen=True)
class DecodedGroups:
    """Result of :func:`decode_groups`: the batches in arrival order and the groups that failed."""

    batches: list[ProfileBatch]
    errors: list[DecodeError]


def decode_groups(groups: Sequence[Sequence[Message]], host_recv_ns: int) -> DecodedGroups:
    """Decode many frame groups at once: one numpy pass per run of groups with the same layout.

    This is the client's hot path: when data queues up, a single read holds many groups, and the
    per-group Python cost shrinks to header validation. Invalid groups are reported in ``errors``
    (each a :class:`DecodeError`) and left out; the others keep their order.
    """
    batches: list[ProfileBatch] = []
    errors: list[DecodeError] = []
    run: list[_GroupView] = []
    for msgs in groups:
        try:
            view = _validate_group(msgs)
        except DecodeError as exc:
            errors.append(exc)
            continue
        if run and (view.kind != run[0].kind or view.layout != run[0].layout):
            batches.append(_build_batch(run, host_recv_ns))
            run = []
        run.append(view)
    if run:
        batches.append(_build_batch(run, host_recv_ns))
    return DecodedGroups(batches, errors)


class GroupAssembler:
    """Collects data-channel messages into frame groups (a group ends at the last flag).

    A group that grows beyond ``max_messages`` without a last flag is returned as-is so that
    :func:`decode_group` rejects it with a :class:`DecodeError` instead of buffering forever.
    """

    def __init__(self, max_messages: int = 8) -> None:
        self._pending: list[Message] = []
        self._max = max_messages

    def push(self, msg: Message) -> list[Message] | None:
        """Add one message; return the finished group, or None while the group is still open."""
        self._pending.append(msg)
        if msg.last or len(self._pending) >= self._max:
            group, self._pending = self._pending, []
            return group
        return None

    def reset(self) -> None:
        """Forget a half-received group (after a reconnect)."""
        self._pending = []


# ---------------------------------------------------------------------------------------- subscribe

SUBSCRIBE = struct.Struct("<IHQ")


def encode_subscribe(start_frame: int = LIVE) -> bytes:
    """First message a host writes on a new data connection: replay from ``start_frame`` (or LIVE)."""
    return SUBSCRIBE.pack(SUBSCRIBE.size, MessageType.SUBSCRIBE | LAST_FLAG, start_frame)


def decode_subscribe(msg: Message) -> int:
    """Return the start frame of a SUBSCRIBE message (:data:`LIVE` for live-only)."""
    if msg.type != MessageType.SUBSCRIBE:
        raise DecodeError(f"expected SUBSCRIBE, got type 0x{msg.type:04x}", field="type", data=msg.data)
    if len(msg.data) != SUBSCRIBE.size:
        raise DecodeError(
            f"SUBSCRIBE has {len(msg.data)} bytes, expected {SUBSCRIBE.size}", field="size", data=msg.data
        )
    return SUBSCRIBE.unpack(msg.data)[2]


# ------------------------------------------------------------------------------------------- control

REPLY_HEADER = struct.Struct("<IHi")  # size, command, status


def encode_command(command: int, payload: bytes = b"") -> bytes:
    """Encode a control request: header (size, command id) + payload."""
    return _header(command, HEADER.size + len(payload), False) + payload


@dataclass(frozen=True)
class Command:
    """A decoded control request."""

    command: CommandId
    payload: bytes


@dataclass(frozen=True)
class Reply:
    """A decoded control reply; ``payload`` is the ASCII error text when ``status`` is not OK."""

    command: int
    status: int
    payload: bytes


def decode_command(msg: Message) -> Command:
    """Split a control request into its command id and payload.

    Raises:
        DecodeError: the id is not a known command (``field='command'``).
    """
    try:
        cmd = CommandId(msg.type)
    except ValueError:
        raise DecodeError(f"unknown command 0x{msg.type:04x}", field="command", data=msg.data) from None
    return Command(cmd, msg.data[HEADER.size :])


def encode_reply(command: int, status: int, payload: bytes = b"") -> bytes:
    """Encode a control reply: header (size, command id), status s32, payload."""
    return REPLY_HEADER.pack(REPLY_HEADER.size + len(payload), command & TYPE_MASK, status) + payload


def decode_reply(msg: Message) -> Reply:
    """Decode a control reply (command id, status, payload)."""
    if len(msg.data) < REPLY_HEADER.size:
        raise DecodeError(
            f"reply of {len(msg.data)} bytes is shorter than its header", field="size", data=msg.data
        )
    _size, command, status = REPLY_HEADER.unpack_from(msg.data)
    return Reply(command, status, msg.data[REPLY_HEADER.size :])


U32 = struct.Struct("<I")


def decode_u32_param(cmd: CommandId, payload: bytes) -> int:
    """Parameter of the single-u32 SET_* commands."""
    if len(payload) != U32.size:
        raise DecodeError(
            f"{cmd.name} needs a 4-byte u32 parameter, got {len(payload)} bytes", field="value", data=payload
        )
    return U32.unpack(payload)[0]


@dataclass(frozen=True)
class SensorInfo:
    """GET_INFO reply: identity and geometry of the sensor.

    Attributes:
        model, serial: ASCII, at most 16 and 24 bytes.
        width: points per uniform profile.
        x_pitch_nm: uniform x pitch, nm.
        x_start_um: x of the first uniform point, um.
        z_min_um, z_max_um: measuring range along z, um.
        max_rate_mhz: highest profile rate, mHz.
        min_exposure_ns, max_exposure_ns: exposure limits, ns.
        protocol_version: wire protocol version (1).
    """

    model: str
    serial: str
    width: int
    x_pitch_nm: int
    x_start_um: int
    z_min_um: int
    z_max_um: int
    max_rate_mhz: int
    min_exposure_ns: int
    max_exposure_ns: int
    protocol_version: int = PROTOCOL_VERSION

    _S = struct.Struct("<HHIIiiiIII16s24s")

    def to_bytes(self) -> bytes:
        return self._S.pack(
            self.protocol_version,
            0,
            self.width,
            self.x_pitch_nm,
            self.x_start_um,
            self.z_min_um,
            self.z_max_um,
            self.max_rate_mhz,
            self.min_exposure_ns,
            self.max_exposure_ns,
            self.model.encode("ascii")[:16],
            self.serial.encode("ascii")[:24],
        )

    @classmethod
    def from_bytes(cls, payload: bytes) -> SensorInfo:
        if len(payload) != cls._S.size:
            raise DecodeError(
                f"GET_INFO payload of {len(payload)} bytes, expected {cls._S.size}",
                field="size",
                data=payload,
            )
        (ver, _r, width, pitch, x0, zmin, zmax, rate, emin, emax, model, serial) = cls._S.unpack(payload)
        return cls(
            model=model.rstrip(b"\0").decode("ascii", "replace"),
            serial=serial.rstrip(b"\0").decode("ascii", "replace"),
            width=width,
            x_pitch_nm=pitch,
            x_start_um=x0,
            z_min_um=zmin,
            z_max_um=zmax,
            max_rate_mhz=rate,
            min_exposure_ns=emin,
            max_exposure_ns=emax,
            protocol_version=ver,
        )


@dataclass(frozen=True)
class TimestampReply:
    """GET_TIMESTAMP reply: the sensor clock now (us) and the HD8 ms counter now."""

    sensor_time_us: int
    hd8_ms: int

    _S = struct.Struct("<QII")

    def to_bytes(self) -> bytes:
        return self._S.pack(self.sensor_time_us, self.hd8_ms, 0)

    @classmethod
    def from_bytes(cls, payload: bytes) -> TimestampReply:
        if len(payload) != cls._S.size:
            raise DecodeError(
                f"GET_TIMESTAMP payload of {len(payload)} bytes, expected {cls._S.size}",
                field="size",
                data=payload,
            )
        us, ms, _ = cls._S.unpack(payload)
        return cls(us, ms)


@dataclass(frozen=True)
class StateReply:
    """GET_STATE reply: run state, the next frame index and the oldest frame still replayable."""

    state: SensorState
    next_frame_index: int
    oldest_buffered_frame: int

    _S = struct.Struct("<IIQQ")

    def to_bytes(self) -> bytes:
        return self._S.pack(int(self.state), 0, self.next_frame_index, self.oldest_buffered_frame)

    @classmethod
    def from_bytes(cls, payload: bytes) -> StateReply:
        if len(payload) != cls._S.size:
            raise DecodeError(
                f"GET_STATE payload of {len(payload)} bytes, expected {cls._S.size}",
                field="size",
                data=payload,
            )
        state, _, nxt, oldest = cls._S.unpack(payload)
        return cls(SensorState(state), nxt, oldest)
