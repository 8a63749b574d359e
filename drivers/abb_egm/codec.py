"""EGM codec: protobuf ``EgmRobot`` / ``EgmSensor`` bytes <-> plain dataclasses.

Shared by the sensor-side endpoint (:mod:`drivers.abb_egm.endpoint`) and the controller simulator
(:mod:`drivers.abb_egm.sim.egm`) so the two cannot drift apart. No I/O here.

Units at this boundary are the controller's: joints in degrees, positions in millimetres,
orientations as unit quaternions with the scalar first (w, x, y, z), header ``tm`` in milliseconds,
``EgmClock`` as integer microseconds since 1970-01-01.

Additional axes in the robot's motion group (a linear track) travel in ``externalJoints`` beside
the arm's ``joints``, in both directions: ``feedBack`` / ``planned`` of ``EgmRobot`` and ``planned``
/ ``speedRef`` of ``EgmSensor``. egm.proto's comment on ``EgmJoints``: degrees, "mm for linear
external axes" (so a track's position is in mm and its speed in mm/s).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from google.protobuf.message import DecodeError, EncodeError

from drivers.abb_egm import egm_pb2

__all__ = [
    "EgmDecodeError",
    "EgmEncodeError",
    "EgmError",
    "MciState",
    "MessageType",
    "MotorState",
    "RapidState",
    "RobotMessage",
    "SensorMessage",
    "decode_robot",
    "decode_sensor",
    "encode_robot",
    "encode_sensor",
    "encode_sensor_header",
    "parse_robot_pb",
    "robot_from_pb",
]

_U32 = 2**32
#: The EGM manual caps repeated fields at 6 (7 for 7-axis robots); more is a malformed message.
MAX_AXES = 7
#: additional (external) axes in one message: the manual's cap of 6 on a repeated field
MAX_EXTERNAL_AXES = 6


class EgmError(Exception):
    """Base class of EGM codec and protocol errors."""


class EgmDecodeError(EgmError):
    """Bytes that are not a valid EGM message of the expected type.

    ``field`` names the offending field (or ``"<bytes>"`` when protobuf itself rejected the data);
    ``data`` keeps the first bytes of the datagram for the log.
    """

    def __init__(self, message_type: str, field: str, reason: str, data: bytes) -> None:
        self.message_type = message_type
        self.field = field
        self.reason = reason
        self.data = bytes(data[:64])
        super().__init__(
            f"cannot decode {message_type}: {field}: {reason} "
            f"({len(data)} bytes, head {self.data[:16].hex(' ')})"
        )


class EgmEncodeError(EgmError):
    """A dataclass that cannot become a valid EGM message (wrong shape, value out of range)."""

    def __init__(self, message_type: str, field: str, reason: str) -> None:
        self.message_type = message_type
        self.field = field
        self.reason = reason
        super().__init__(f"cannot encode {message_type}: {field}: {reason}")


class MessageType(enum.IntEnum):
    """``EgmHeader.MessageType``."""

    UNDEFINED = 0
    COMMAND = 1
    DATA = 2
    CORRECTION = 3
    PATH_CORRECTION = 4


class MotorState(enum.IntEnum):
    """``EgmMotorState.MotorStateType``."""

    UNDEFINED = 0
    ON = 1
    OFF = 2


class MciState(enum.IntEnum):
    """``EgmMCIState.MCIStateType``: the controller's EGM (motion correction interface) state."""

    UNDEFINED = 0
    ERROR = 1
    STOPPED = 2
    RUNNING = 3


class RapidState(enum.IntEnum):
    """``EgmRapidCtrlExecState.RapidCtrlExecStateType``."""

    UNDEFINED = 0
    STOPPED = 1
    RUNNING = 2


# eq=False: the fields hold numpy arrays, whose == is element-wise
@dataclass(frozen=True, slots=True, eq=False)
class RobotMessage:
    """One ``EgmRobot`` (controller -> sensor). ``None`` means the field was absent on the wire.

    Arrays are float64: ``feedback_q_deg`` / ``planned_q_deg`` (n_axes,) deg,
    ``*_pos_mm`` (3,) mm, ``*_quat_wxyz`` (4,) unit quaternion, scalar first.
    ``feedback_time_us`` is the controller's ``EgmClock`` in integer microseconds since the epoch.
    ``feedback_external_joints`` / ``planned_external_joints`` (n_ext,): the additional axes
    (``externalJoints``), deg for a rotational axis and mm for a linear one (a track).
    """

    seqno: int | None = None
    tm_ms: int | None = None
    mtype: MessageType = MessageType.UNDEFINED
    feedback_q_deg: np.ndarray | None = None
    feedback_pos_mm: np.ndarray | None = None
    feedback_quat_wxyz: np.ndarray | None = None
    feedback_time_us: int | None = None
    planned_q_deg: np.ndarray | None = None
    planned_pos_mm: np.ndarray | None = None
    planned_quat_wxyz: np.ndarray | None = None
    planned_time_us: int | None = None
    motor_state: MotorState | None = None
    mci_state: MciState | None = None
    mci_convergence_met: bool | None = None
    rapid_exec_state: RapidState | None = None
    utilization_pct: float | None = None
    move_index: int | None = None
    measured_force_fc_active: bool | None = None
    measured_force: np.ndarray | None = None
    feedback_external_joints: np.ndarray | None = None
    planned_external_joints: np.ndarray | None = None


@dataclass(frozen=True, slots=True, eq=False)
class SensorMessage:
    """One ``EgmSensor`` (sensor -> controller, position guidance).

    Joint mode: ``planned_q_deg`` (n_axes,) deg, optional ``speed_ref_q_deg_s`` (n_axes,) deg/s;
    additional axes in ``planned_external_joints`` (n_ext,) and ``speed_ref_external_joints``
    (n_ext,): deg and deg/s, or mm and mm/s for a linear axis (a track).
    Pose mode: ``planned_pos_mm`` (3,) mm with ``planned_quat_wxyz`` (4,) or ``planned_euler_deg`` (3,)
    (Euler wins on the controller if both are given), optional ``speed_ref_cart`` (6,) mm/s and deg/s.
    """

    seqno: int | None = None
    tm_ms: int | None = None
    mtype: MessageType = MessageType.CORRECTION
    planned_q_deg: np.ndarray | None = None
    speed_ref_q_deg_s: np.ndarray | None = None
    planned_pos_mm: np.ndarray | None = None
    planned_quat_wxyz: np.ndarray | None = None
    planned_euler_deg: np.ndarray | None = None
    speed_ref_cart: np.ndarray | None = None
    planned_external_joints: np.ndarray | None = None
    speed_ref_external_joints: np.ndarray | None = None


# ---------------------------------------------------------------------------------------------
# decoding


# The endpoint decodes one message per 4 ms cycle inside its reply path: plain Python float checks
# on six values cost a fraction of numpy's per-call overhead on tiny arrays.


def _repeated(values, message_type: str, field: str, data: bytes, max_len: int = MAX_AXES) -> np.ndarray:
    vals = list(values)
    if len(vals) > max_len:
        raise EgmDecodeError(message_type, field, f"{len(vals)} values, at most {max_len}", data)
    if not all(map(math.isfinite, vals)):
        raise EgmDecodeError(message_type, field, "non-finite value", data)
    return np.array(vals, dtype=np.float64)


def _cartesian(msg, message_type: str, field: str, data: bytes) -> np.ndarray:
    vals = (msg.x, msg.y, msg.z)
    if not all(map(math.isfinite, vals)):
        raise EgmDecodeError(message_type, field, "non-finite value", data)
    return np.array(vals, dtype=np.float64)


def _quaternion(msg, message_type: str, field: str, data: bytes) -> np.ndarray:
    vals = (msg.u0, msg.u1, msg.u2, msg.u3)
    norm = math.hypot(*vals)
    if not math.isfinite(norm) or norm < 1e-9:
        raise EgmDecodeError(message_type, field, f"not a rotation quaternion (norm {norm})", data)
    return np.array(vals, dtype=np.float64)


def _clock_us(msg) -> int:
    return int(msg.sec) * 1_000_000 + int(msg.usec)


def _parse(cls, data: bytes, name: str):
    msg = cls()
    try:
        msg.ParseFromString(data)
    except (DecodeError, RuntimeError, ValueError) as exc:
        raise EgmDecodeError(name, "<bytes>", str(exc) or type(exc).__name__, data) from None
    return msg


def parse_robot_pb(data: bytes, *, require_data_mtype: bool = True) -> egm_pb2.EgmRobot:
    """First half of :func:`decode_robot`: parse and check the header and the feedback's presence.

    Cheap (about a microsecond), so a reply can go out before the values are converted with
    :func:`robot_from_pb`.

    Raises:
        EgmDecodeError: not protobuf, a missing header or feedback joints, wrong ``mtype``.
    """
    name = "EgmRobot"
    m = _parse(egm_pb2.EgmRobot, data, name)
    if not m.HasField("header"):
        raise EgmDecodeError(name, "header", "missing", data)
    mtype = _enum(MessageType, m.header.mtype)
    if require_data_mtype and mtype != MessageType.DATA:
        raise EgmDecodeError(name, "header.mtype", f"{mtype.name}, expected DATA", data)
    if not m.HasField("feedBack") or not m.feedBack.HasField("joints"):
        raise EgmDecodeError(name, "feedBack.joints", "missing", data)
    return m


def decode_robot(data: bytes, *, require_data_mtype: bool = True) -> RobotMessage:
    """Decode one ``EgmRobot`` datagram.

    Args:
        data: the UDP payload.
        require_data_mtype: reject messages whose header ``mtype`` is not ``MSGTYPE_DATA``.

    Raises:
        EgmDecodeError: not protobuf, a missing header or feedback, wrong ``mtype``, more than
            7 axes, non-finite numbers.
    """
    return robot_from_pb(parse_robot_pb(data, require_data_mtype=require_data_mtype), data)


def robot_from_pb(m: egm_pb2.EgmRobot, data: bytes = b"") -> RobotMessage:
    """Second half of :func:`decode_robot`: convert a parsed ``EgmRobot`` into a :class:`RobotMessage`.

    ``data`` (the raw datagram) only goes into error messages.

    Raises:
        EgmDecodeError: more than 7 axes, non-finite numbers, a zero quaternion.
    """
    name = "EgmRobot"
    h = m.header
    mtype = _enum(MessageType, h.mtype)
    fb = m.feedBack
    pl = m.planned if m.HasField("planned") else None
    return RobotMessage(
        seqno=h.seqno if h.HasField("seqno") else None,
        tm_ms=h.tm if h.HasField("tm") else None,
        mtype=mtype,
        feedback_q_deg=_repeated(fb.joints.joints, name, "feedBack.joints", data),
        feedback_pos_mm=(
            _cartesian(fb.cartesian.pos, name, "feedBack.cartesian.pos", data)
            if fb.HasField("cartesian") and fb.cartesian.HasField("pos")
            else None
        ),
        feedback_quat_wxyz=(
            _quaternion(fb.cartesian.orient, name, "feedBack.cartesian.orient", data)
            if fb.HasField("cartesian") and fb.cartesian.HasField("orient")
            else None
        ),
        feedback_time_us=_clock_us(fb.time) if fb.HasField("time") else None,
        planned_q_deg=(
            _repeated(pl.joints.joints, name, "planned.joints", data)
            if pl is not None and pl.HasField("joints")
            else None
        ),
        planned_pos_mm=(
            _cartesian(pl.cartesian.pos, name, "planned.cartesian.pos", data)
            if pl is not None and pl.HasField("cartesian") and pl.cartesian.HasField("pos")
            else None
        ),
        planned_quat_wxyz=(
            _quaternion(pl.cartesian.orient, name, "planned.cartesian.orient", data)
            if pl is not None and pl.HasField("cartesian") and pl.cartesian.HasField("orient")
            else None
        ),
        planned_time_us=_clock_us(pl.time) if pl is not None and pl.HasField("time") else None,
        motor_state=_enum(MotorState, m.motorState.state) if m.HasField("motorState") else None,
        mci_state=_enum(MciState, m.mciState.state) if m.HasField("mciState") else None,
        mci_convergence_met=m.mciConvergenceMet if m.HasField("mciConvergenceMet") else None,
        rapid_exec_state=(
            _enum(RapidState, m.rapidExecState.state) if m.HasField("rapidExecState") else None
        ),
        utilization_pct=m.utilizationRate if m.HasField("utilizationRate") else None,
        move_index=m.moveIndex if m.HasField("moveIndex") else None,
        measured_force_fc_active=(
            m.measuredForce.fcActive
            if m.HasField("measuredForce") and m.measuredForce.HasField("fcActive")
            else None
        ),
        measured_force=(
            _repeated(m.measuredForce.force, name, "measuredForce.force", data, max_len=6)
            if m.HasField("measuredForce")
            else None
        ),
        feedback_external_joints=(
            _repeated(fb.externalJoints.joints, name, "feedBack.externalJoints", data, MAX_EXTERNAL_AXES)
            if fb.HasField("externalJoints")
            else None
        ),
        planned_external_joints=(
            _repeated(pl.externalJoints.joints, name, "planned.externalJoints", data, MAX_EXTERNAL_AXES)
            if pl is not None and pl.HasField("externalJoints")
            else None
        ),
    )


def _enum(cls, value: int):
    # proto2 keeps unknown enum values as unknown fields, so only known values reach here;
    # the guard is for descriptors that drift from this module. A dict lookup, not Enum(value),
    # because it runs on every cycle.
    member = cls._value2member_map_.get(value)
    return member if member is not None else cls._value2member_map_[0]


def decode_sensor(data: bytes, *, require_correction_mtype: bool = True) -> SensorMessage:
    """Decode one ``EgmSensor`` datagram (position guidance).

    Raises:
        EgmDecodeError: not protobuf, a missing header, wrong ``mtype`` (when required), a pose
            without position, more than 7 axes, non-finite numbers.
    """
    name = "EgmSensor"
    m = _parse(egm_pb2.EgmSensor, data, name)
    if not m.HasField("header"):
        raise EgmDecodeError(name, "header", "missing", data)
    h = m.header
    mtype = _enum(MessageType, h.mtype)
    if require_correction_mtype and mtype != MessageType.CORRECTION:
        raise EgmDecodeError(name, "header.mtype", f"{mtype.name}, expected CORRECTION", data)
    pl = m.planned if m.HasField("planned") else None
    sr = m.speedRef if m.HasField("speedRef") else None
    cart = pl.cartesian if pl is not None and pl.HasField("cartesian") else None
    if cart is not None and not cart.HasField("pos"):
        raise EgmDecodeError(name, "planned.cartesian.pos", "missing", data)
    return SensorMessage(
        seqno=h.seqno if h.HasField("seqno") else None,
        tm_ms=h.tm if h.HasField("tm") else None,
        mtype=mtype,
        planned_q_deg=(
            _repeated(pl.joints.joints, name, "planned.joints", data)
            if pl is not None and pl.HasField("joints")
            else None
        ),
        speed_ref_q_deg_s=(
            _repeated(sr.joints.joints, name, "speedRef.joints", data)
            if sr is not None and sr.HasField("joints")
            else None
        ),
        planned_pos_mm=(_cartesian(cart.pos, name, "planned.cartesian.pos", data) if cart else None),
        planned_quat_wxyz=(
            _quaternion(cart.orient, name, "planned.cartesian.orient", data)
            if cart is not None and cart.HasField("orient")
            else None
        ),
        planned_euler_deg=(
            _cartesian(cart.euler, name, "planned.cartesian.euler", data)
            if cart is not None and cart.HasField("euler")
            else None
        ),
        speed_ref_cart=(
            _repeated(sr.cartesians.value, name, "speedRef.cartesians", data, max_len=6)
            if sr is not None and sr.HasField("cartesians")
            else None
        ),
        planned_external_joints=(
            _repeated(pl.externalJoints.joints, name, "planned.externalJoints", data, MAX_EXTERNAL_AXES)
            if pl is not None and pl.HasField("externalJoints")
            else None
        ),
        speed_ref_external_joints=(
            _repeated(sr.externalJoints.joints, name, "speedRef.externalJoints", data, MAX_EXTERNAL_AXES)
            if sr is not None and sr.HasField("externalJoints")
            else None
        ),
    )


# ---------------------------------------------------------------------------------------------
# encoding


def _vector(values, message_type: str, field: str, n: int | None = None, max_len: int = MAX_AXES) -> list:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if n is not None and arr.shape[0] != n:
        raise EgmEncodeError(message_type, field, f"expected {n} values, got {arr.shape[0]}")
    if arr.shape[0] > max_len:
        raise EgmEncodeError(message_type, field, f"{arr.shape[0]} values, at most {max_len}")
    if not np.all(np.isfinite(arr)):
        raise EgmEncodeError(message_type, field, "non-finite value")
    return arr.tolist()


def _set_clock(msg, t_us: int) -> None:
    if t_us < 0:
        raise EgmEncodeError("EgmClock", "time", f"negative time {t_us} us")
    msg.sec, msg.usec = divmod(int(t_us), 1_000_000)


def _set_pose(pose, pos_mm, quat_wxyz, euler_deg, name: str, field: str) -> None:
    x, y, z = _vector(pos_mm, name, field + ".pos", 3)
    pose.pos.x, pose.pos.y, pose.pos.z = x, y, z
    if quat_wxyz is not None:
        u0, u1, u2, u3 = _vector(quat_wxyz, name, field + ".orient", 4)
        pose.orient.u0, pose.orient.u1, pose.orient.u2, pose.orient.u3 = u0, u1, u2, u3
    if euler_deg is not None:
        ex, ey, ez = _vector(euler_deg, name, field + ".euler", 3)
        pose.euler.x, pose.euler.y, pose.euler.z = ex, ey, ez


def _header(h, seqno: int | None, tm_ms: int | None, mtype: MessageType) -> None:
    if seqno is not None:
        h.seqno = int(seqno) % _U32
    if tm_ms is not None:
        h.tm = int(tm_ms) % _U32
    h.mtype = int(mtype)


def encode_robot(msg: RobotMessage) -> bytes:
    """Encode a :class:`RobotMessage` as ``EgmRobot`` bytes; ``None`` fields are left out.

    ``seqno`` and ``tm_ms`` wrap modulo 2**32 as on the controller.

    Raises:
        EgmEncodeError: a vector of the wrong length or with non-finite values.
    """
    name = "EgmRobot"
    m = egm_pb2.EgmRobot()
    _header(m.header, msg.seqno, msg.tm_ms, msg.mtype)
    fb = m.feedBack
    if msg.feedback_q_deg is not None:
        fb.joints.joints.extend(_vector(msg.feedback_q_deg, name, "feedBack.joints"))
    if msg.feedback_pos_mm is not None:
        _set_pose(fb.cartesian, msg.feedback_pos_mm, msg.feedback_quat_wxyz, None, name, "feedBack.cartesian")
    if msg.feedback_time_us is not None:
        _set_clock(fb.time, msg.feedback_time_us)
    if msg.feedback_external_joints is not None:
        fb.externalJoints.joints.extend(
            _vector(msg.feedback_external_joints, name, "feedBack.externalJoints", max_len=MAX_EXTERNAL_AXES)
        )
    if msg.planned_q_deg is not None:
        m.planned.joints.joints.extend(_vector(msg.planned_q_deg, name, "planned.joints"))
    if msg.planned_pos_mm is not None:
        _set_pose(
            m.planned.cartesian, msg.planned_pos_mm, msg.planned_quat_wxyz, None, name, "planned.cartesian"
        )
    if msg.planned_time_us is not None:
        _set_clock(m.planned.time, msg.planned_time_us)
    if msg.planned_external_joints is not None:
        m.planned.externalJoints.joints.extend(
            _vector(msg.planned_external_joints, name, "planned.externalJoints", max_len=MAX_EXTERNAL_AXES)
        )
    if msg.motor_state is not None:
        m.motorState.state = int(msg.motor_state)
    if msg.mci_state is not None:
        m.mciState.state = int(msg.mci_state)
    if msg.mci_convergence_met is not None:
        m.mciConvergenceMet = bool(msg.mci_convergence_met)
    if msg.rapid_exec_state is not None:
        m.rapidExecState.state = int(msg.rapid_exec_state)
    if msg.utilization_pct is not None:
        m.utilizationRate = float(msg.utilization_pct)
    if msg.move_index is not None:
        m.moveIndex = int(msg.move_index) % _U32
    if msg.measured_force is not None or msg.measured_force_fc_active is not None:
        if msg.measured_force_fc_active is not None:
            m.measuredForce.fcActive = bool(msg.measured_force_fc_active)
        if msg.measured_force is not None:
            m.measuredForce.force.extend(_vector(msg.measured_force, name, "measuredForce.force", max_len=6))
    try:
        return m.SerializeToString()
    except EncodeError as exc:  # a required leaf field left unset
        raise EgmEncodeError(name, "<message>", str(exc)) from None


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def encode_sensor_header(seqno: int, tm_ms: int, mtype: MessageType = MessageType.CORRECTION) -> bytes:
    """The ``EgmSensor.header`` field alone, as bytes.

    Protobuf messages concatenate: ``encode_sensor_header(s, t) + encode_sensor(msg, with_header=False)``
    is byte-identical to encoding ``msg`` with that header, so a sender can encode the reference once
    and only the header per cycle.
    """
    body = b"\x08" + _varint(int(seqno) % _U32) + b"\x10" + _varint(int(tm_ms) % _U32)
    body += b"\x18" + _varint(int(mtype))
    return b"\x0a" + _varint(len(body)) + body


def encode_sensor(msg: SensorMessage, *, with_header: bool = True) -> bytes:
    """Encode a :class:`SensorMessage` as ``EgmSensor`` bytes; ``None`` fields are left out.

    ``with_header=False`` leaves the header out (see :func:`encode_sensor_header`).

    Raises:
        EgmEncodeError: a vector of the wrong length or with non-finite values, or an orientation
            without a position.
    """
    name = "EgmSensor"
    m = egm_pb2.EgmSensor()
    if with_header:
        _header(m.header, msg.seqno, msg.tm_ms, msg.mtype)
    if msg.planned_q_deg is not None:
        m.planned.joints.joints.extend(_vector(msg.planned_q_deg, name, "planned.joints"))
    if msg.planned_pos_mm is not None:
        _set_pose(
            m.planned.cartesian,
            msg.planned_pos_mm,
            msg.planned_quat_wxyz,
            msg.planned_euler_deg,
            name,
            "planned.cartesian",
        )
    elif msg.planned_quat_wxyz is not None or msg.planned_euler_deg is not None:
        raise EgmEncodeError(name, "planned.cartesian.pos", "orientation given without position")
    if msg.speed_ref_q_deg_s is not None:
        m.speedRef.joints.joints.extend(_vector(msg.speed_ref_q_deg_s, name, "speedRef.joints"))
    if msg.speed_ref_cart is not None:
        m.speedRef.cartesians.value.extend(_vector(msg.speed_ref_cart, name, "speedRef.cartesians", 6))
    if msg.planned_external_joints is not None:
        m.planned.externalJoints.joints.extend(
            _vector(msg.planned_external_joints, name, "planned.externalJoints", max_len=MAX_EXTERNAL_AXES)
        )
    if msg.speed_ref_external_joints is not None:
        m.speedRef.externalJoints.joints.extend(
            _vector(msg.speed_ref_external_joints, name, "speedRef.externalJoints", max_len=MAX_EXTERNAL_AXES)
        )
    try:
        return m.SerializeToString()
    except EncodeError as exc:
        raise EgmEncodeError(name, "<message>", str(exc)) from None
