"""EGM messages: schema, generated code, fixtures from a foreign encoder, hand-built golden bytes."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.abb_egm import egm_pb2
from drivers.abb_egm.codec import (
    EgmDecodeError,
    EgmEncodeError,
    MciState,
    MessageType,
    MotorState,
    RapidState,
    RobotMessage,
    SensorMessage,
    decode_robot,
    decode_sensor,
    encode_robot,
    encode_sensor,
    encode_sensor_header,
)

PKG = Path(__file__).resolve().parents[2] / "drivers" / "abb_egm"
FIXTURES = Path("/work/shared/testdata/egm")


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _tag(field: int, wire_type: int) -> bytes:
    return _varint(field << 3 | wire_type)


def _ld(field: int, payload: bytes) -> bytes:
    """A length-delimited field (wire type 2)."""
    return _tag(field, 2) + _varint(len(payload)) + payload


def _f64(field: int, value: float) -> bytes:
    return _tag(field, 1) + struct.pack("<d", value)


@pytest.mark.process
def test_checked_in_egm_pb2_matches_a_fresh_protoc_run(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", f"-I{PKG}", f"--python_out={tmp_path}", "egm.proto"],
        check=True,
        capture_output=True,
    )
    assert (tmp_path / "egm_pb2.py").read_text() == (PKG / "egm_pb2.py").read_text()


def test_proto_is_proto2_in_package_abb_egm_with_new_measured_force_layout():
    fd = egm_pb2.DESCRIPTOR
    assert fd.package == "abb.egm"
    force = egm_pb2.EgmMeasuredForce.DESCRIPTOR
    assert force.fields_by_name["fcActive"].number == 1
    assert force.fields_by_name["force"].number == 2
    robot = egm_pb2.EgmRobot.DESCRIPTOR
    numbers = {f.name: f.number for f in robot.fields}
    assert numbers == {
        "header": 1,
        "feedBack": 2,
        "planned": 3,
        "motorState": 4,
        "mciState": 5,
        "mciConvergenceMet": 6,
        "testSignals": 7,
        "rapidExecState": 8,
        "measuredForce": 9,
        "utilizationRate": 10,
        "moveIndex": 11,
        "CollisionInfo": 12,
        "RAPIDfromRobot": 13,
        "torqueRef": 14,
    }
    sensor = {f.name: f.number for f in egm_pb2.EgmSensor.DESCRIPTOR.fields}
    assert sensor == {"header": 1, "planned": 2, "speedRef": 3, "RAPIDtoRobot": 4}
    # proto2 required leaves: a proto3 port would lose these
    assert egm_pb2.EgmCartesian.DESCRIPTOR.fields_by_name["x"].is_required
    assert egm_pb2.EgmClock.DESCRIPTOR.fields_by_name["usec"].is_required


def test_joint_reference_golden_bytes_are_unpacked_doubles_under_the_right_tags():
    joints = [1.0, -2.5, 3.25, 0.0, 90.0, -180.0]
    hand = _ld(1, _tag(1, 0) + _varint(7) + _tag(3, 0) + _varint(3))  # header: seqno 7, CORRECTION
    hand += _ld(2, _ld(1, b"".join(_f64(1, j) for j in joints)))  # planned.joints.joints, not packed
    ours = encode_sensor(SensorMessage(seqno=7, planned_q_deg=np.array(joints)))
    assert ours == hand
    back = decode_sensor(hand)
    assert back.seqno == 7 and back.mtype is MessageType.CORRECTION
    np.testing.assert_array_equal(back.planned_q_deg, joints)


def test_robot_golden_bytes_decode_state_fields_by_number():
    hand = _ld(1, _tag(1, 0) + _varint(300) + _tag(2, 0) + _varint(2**32 - 1) + _tag(3, 0) + _varint(2))
    hand += _ld(
        2,
        _ld(1, b"".join(_f64(1, j) for j in (1, 2, 3, 4, 5, 6)))
        + _ld(4, _tag(1, 0) + _varint(5) + _tag(2, 0) + _varint(6)),
    )
    hand += _ld(4, _tag(1, 0) + _varint(1))  # motorState ON
    hand += _ld(5, _tag(1, 0) + _varint(3))  # mciState RUNNING
    hand += _tag(6, 0) + _varint(1)  # mciConvergenceMet
    hand += _ld(8, _tag(1, 0) + _varint(2))  # rapidExecState RUNNING
    hand += _ld(9, _tag(1, 0) + _varint(1) + b"".join(_f64(2, f) for f in (9.0, 8.0)))  # fcActive, force=2
    hand += _f64(10, 12.5)  # utilizationRate
    m = decode_robot(hand)
    assert m.seqno == 300 and m.tm_ms == 2**32 - 1 and m.mtype is MessageType.DATA
    np.testing.assert_array_equal(m.feedback_q_deg, [1, 2, 3, 4, 5, 6])
    assert m.feedback_time_us == 5_000_006
    assert m.motor_state is MotorState.ON and m.mci_state is MciState.RUNNING
    assert m.rapid_exec_state is RapidState.RUNNING and m.mci_convergence_met is True
    assert m.measured_force_fc_active is True
    np.testing.assert_array_equal(m.measured_force, [9.0, 8.0])
    assert m.utilization_pct == 12.5


def test_old_libegm_force_layout_is_rejected_not_silently_misread():
    # V1.1 put force at field 1 as repeated double (wire type 1); field 1 is now a bool varint.
    hand = _ld(1, _tag(1, 0) + _varint(1) + _tag(3, 0) + _varint(2))
    hand += _ld(2, _ld(1, _f64(1, 0.0)))
    hand += _ld(9, _f64(1, 5.0))
    m = egm_pb2.EgmRobot()
    m.ParseFromString(hand)
    # protobuf keeps the mistyped field as unknown instead of filling force
    assert list(m.measuredForce.force) == []
    decoded = decode_robot(hand)
    assert decoded.measured_force is not None and decoded.measured_force.size == 0


def _cases():
    return json.loads((FIXTURES / "cases.json").read_text())


@pytest.mark.parametrize("name", sorted(json.loads((FIXTURES / "cases.json").read_text())))
def test_foreign_encoded_fixture_decodes_to_the_stated_values(name):
    case = _cases()[name]
    data = (FIXTURES / f"{name}.bin").read_bytes()
    exp = case["expect"]
    if case["message"] == "EgmRobot":
        m = decode_robot(data)
        assert m.seqno == exp["seqno"] and m.tm_ms == exp["tm_ms"]
        assert m.mtype.name == exp["mtype"].removeprefix("MSGTYPE_")
        np.testing.assert_array_equal(m.feedback_q_deg, exp["feedback_joints_deg"])
        assert m.motor_state.name == exp["motor_state"].removeprefix("MOTORS_")
        assert m.mci_state.name == exp["mci_state"].removeprefix("MCI_")
        assert m.rapid_exec_state.name == exp["rapid_exec_state"].removeprefix("RAPID_")
        if "feedback_pos_mm" in exp:
            np.testing.assert_array_equal(m.feedback_pos_mm, exp["feedback_pos_mm"])
            np.testing.assert_array_equal(m.feedback_quat_wxyz, exp["feedback_quat_wxyz"])
            sec, usec = exp["feedback_time"]
            assert m.feedback_time_us == sec * 1_000_000 + usec
            np.testing.assert_array_equal(m.planned_q_deg, exp["planned_joints_deg"])
            assert m.mci_convergence_met == exp["mci_convergence_met"]
            assert m.utilization_pct == exp["utilization_rate"]
            assert m.move_index == exp["move_index"]
            assert m.measured_force_fc_active == exp["measured_force_fc_active"]
            np.testing.assert_array_equal(m.measured_force, exp["measured_force"])
        # our encoder produces bytes the same decoder reads back to the same values
        again = decode_robot(encode_robot(m))
        assert _robot_equal(again, m)
    else:
        m = decode_sensor(data)
        assert m.seqno == exp["seqno"] and m.mtype is MessageType.CORRECTION
        if "tm_ms" in exp:
            assert m.tm_ms == exp["tm_ms"]
        if "planned_joints_deg" in exp:
            np.testing.assert_array_equal(m.planned_q_deg, exp["planned_joints_deg"])
            np.testing.assert_array_equal(m.speed_ref_q_deg_s, exp["speed_ref_joints_deg_s"])
        else:
            np.testing.assert_array_equal(m.planned_pos_mm, exp["planned_pos_mm"])
            np.testing.assert_array_equal(m.planned_quat_wxyz, exp["planned_quat_wxyz"])
        # byte-identical re-encoding: field order and unpacked doubles match the foreign encoder
        assert encode_sensor(m) == data


def _robot_equal(a: RobotMessage, b: RobotMessage) -> bool:
    for field in RobotMessage.__dataclass_fields__:
        x, y = getattr(a, field), getattr(b, field)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def test_foreign_robot_fixture_reencodes_byte_identical():
    data = (FIXTURES / "egm_robot_running.bin").read_bytes()
    assert encode_robot(decode_robot(data)) == data


@pytest.mark.parametrize(
    "data, field",
    [
        (b"\xff\xff\xff", "<bytes>"),
        (b"", "header"),
        (b"\x0a\x02\x18\x03", "header.mtype"),  # a sensor message arriving at the sensor
        (b"\x0a\x02\x18\x02", "feedBack.joints"),
    ],
)
def test_malformed_robot_bytes_raise_decode_error_naming_the_field(data, field):
    with pytest.raises(EgmDecodeError) as info:
        decode_robot(data)
    assert info.value.field == field
    assert field in str(info.value)


def test_robot_message_with_too_many_joints_is_rejected():
    hand = _ld(1, _tag(3, 0) + _varint(2)) + _ld(2, _ld(1, b"".join(_f64(1, 0.0) for _ in range(8))))
    with pytest.raises(EgmDecodeError, match=r"feedBack\.joints"):
        decode_robot(hand)


def test_sensor_message_with_nan_joint_is_rejected():
    hand = _ld(1, _tag(3, 0) + _varint(3)) + _ld(2, _ld(1, _f64(1, float("nan"))))
    with pytest.raises(EgmDecodeError, match="non-finite"):
        decode_sensor(hand)


def test_encoder_rejects_wrong_vector_length_naming_the_field():
    with pytest.raises(EgmEncodeError, match=r"planned\.cartesian\.pos"):
        encode_sensor(SensorMessage(planned_pos_mm=np.zeros(2)))
    with pytest.raises(EgmEncodeError, match=r"planned\.cartesian\.pos"):
        encode_sensor(SensorMessage(planned_quat_wxyz=np.array([1.0, 0, 0, 0])))


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    seqno=st.integers(0, 2**32 - 1),
    tm=st.integers(0, 2**32 - 1),
    q=st.lists(finite, min_size=6, max_size=6),
    pos=st.lists(finite, min_size=3, max_size=3),
    t_us=st.integers(0, 2**50),
    motor=st.sampled_from(MotorState),
    mci=st.sampled_from(MciState),
    rapid=st.sampled_from(RapidState),
    util=finite,
)
def test_robot_message_round_trips(seqno, tm, q, pos, t_us, motor, mci, rapid, util):
    m = RobotMessage(
        seqno=seqno,
        tm_ms=tm,
        mtype=MessageType.DATA,
        feedback_q_deg=np.array(q),
        feedback_pos_mm=np.array(pos),
        feedback_quat_wxyz=np.array([0.5, 0.5, 0.5, 0.5]),
        feedback_time_us=t_us,
        planned_q_deg=np.array(q[::-1]),
        motor_state=motor,
        mci_state=mci,
        rapid_exec_state=rapid,
        mci_convergence_met=False,
        utilization_pct=util,
    )
    assert _robot_equal(decode_robot(encode_robot(m)), m)


@settings(max_examples=60, deadline=None)
@given(
    seqno=st.integers(0, 2**32 - 1),
    q=st.lists(finite, min_size=1, max_size=7),
    with_speed=st.booleans(),
)
def test_sensor_joint_message_round_trips(seqno, q, with_speed):
    qd = np.array(q) * 0.5 if with_speed else None
    back = decode_sensor(
        encode_sensor(SensorMessage(seqno=seqno, planned_q_deg=np.array(q), speed_ref_q_deg_s=qd))
    )
    assert back.seqno == seqno
    np.testing.assert_array_equal(back.planned_q_deg, q)
    if with_speed:
        np.testing.assert_array_equal(back.speed_ref_q_deg_s, qd)
    else:
        assert back.speed_ref_q_deg_s is None


@settings(max_examples=40, deadline=None)
@given(
    seqno=st.integers(0, 2**32 - 1), tm=st.integers(0, 2**32 - 1), q=st.lists(finite, min_size=6, max_size=6)
)
def test_header_plus_headerless_body_is_byte_identical_to_a_full_encode(seqno, tm, q):
    msg = SensorMessage(seqno=seqno, tm_ms=tm, planned_q_deg=np.array(q), speed_ref_q_deg_s=np.array(q) / 2)
    assert encode_sensor_header(seqno, tm) + encode_sensor(msg, with_header=False) == encode_sensor(msg)
