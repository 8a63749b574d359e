"""Codec of the HD8 profile protocol: golden bytes, round trips, strict validation."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.laser import protocol as P

SCALE = P.ProfileScale(x_scale_nm=100_000, z_scale_nm=2000, x_offset_um=-150, z_offset_um=100_000)


def stamps(n: int, first: int = 7) -> dict[str, np.ndarray]:
    return dict(
        frame_index=np.arange(first, first + n, dtype=np.uint64),
        sensor_time_us=np.arange(n, dtype=np.uint64) * 5000 + 123_456,
        hd8_ms=np.arange(n, dtype=np.uint32) * 5 + 4_294_967_290,
        encoder=np.arange(n, dtype=np.int64) - 3,
        status=np.full(n, 2, dtype=np.uint32),
        exposure_ns=np.full(n, 500_000, dtype=np.uint32),
    )


def test_uniform_group_matches_golden_bytes() -> None:
    z_raw = np.array([[1, -2, P.INVALID_RAW, 300]], dtype=np.int16)
    got = P.encode_frame_group(scale=SCALE, z_raw=z_raw, **stamps(1))
    # Written out field by field from docs/hd8-protocol.md, independent of the encoder's structs.
    stamp = (
        (54).to_bytes(4, "little")  # size: 14 + 40
        + (0x0001).to_bytes(2, "little")  # STAMP, not last
        + (1).to_bytes(4, "little")  # count
        + (40).to_bytes(2, "little")  # stamp size
        + b"\0\0"
        + (7).to_bytes(8, "little")  # frame index
        + (123_456).to_bytes(8, "little")  # sensor time us
        + (-3).to_bytes(8, "little", signed=True)  # encoder
        + (4_294_967_290).to_bytes(4, "little")  # hd8 ms
        + (2).to_bytes(4, "little")  # status
        + (500_000).to_bytes(4, "little")  # exposure ns
        + b"\0\0\0\0"
    )
    profile = (
        (48).to_bytes(4, "little")  # 40 + 4 points * 2 bytes
        + (0x8006).to_bytes(2, "little")  # PROFILE_UNIFORM | last
        + (34).to_bytes(2, "little")
        + (1).to_bytes(4, "little")
        + (4).to_bytes(4, "little")
        + (100_000).to_bytes(4, "little")
        + (2000).to_bytes(4, "little")
        + (-150).to_bytes(4, "little", signed=True)
        + (100_000).to_bytes(4, "little", signed=True)
        + (7).to_bytes(8, "little")
        + bytes.fromhex("0100feff0080" + "2c01")
    )
    assert got == stamp + profile


def test_uniform_group_decodes_to_millimetres_and_validity() -> None:
    z_raw = np.array([[1, -2, P.INVALID_RAW, 300]], dtype=np.int16)
    data = P.encode_frame_group(scale=SCALE, z_raw=z_raw, **stamps(1))
    msgs = P.MessageFramer().feed(data)
    b = P.decode_group(msgs, host_recv_ns=42)
    np.testing.assert_allclose(b.x_mm[0], [-0.15, -0.05, 0.05, 0.15], atol=1e-6)
    np.testing.assert_allclose(b.z_mm[0][[0, 1, 3]], [100.002, 99.996, 100.6], atol=1e-5)
    assert np.isnan(b.z_mm[0, 2])
    assert b.valid.tolist() == [[True, True, False, True]]
    assert b.hd8_ms[0] == 4_294_967_290 and b.encoder[0] == -3 and b.host_recv_ns[0] == 42


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 20),
    w=st.integers(1, 64),
    points=st.booleans(),
    seed=st.integers(0, 2**31),
    first=st.integers(0, 2**63),
)
def test_frame_group_round_trips_every_field(n: int, w: int, points: bool, seed: int, first: int) -> None:
    rng = np.random.default_rng(seed)
    z_raw = rng.integers(-32768, 32768, size=(n, w)).astype(np.int16)
    x_raw = rng.integers(-32767, 32768, size=(n, w)).astype(np.int16) if points else None
    s = stamps(n, first=min(first, 2**64 - n - 1))
    s["sensor_time_us"] = rng.integers(0, 2**63, size=n).astype(np.uint64)
    data = P.encode_frame_group(scale=SCALE, z_raw=z_raw, x_raw=x_raw, **s)
    b = P.decode_group(P.MessageFramer().feed(data), host_recv_ns=1)
    for k, v in s.items():
        np.testing.assert_array_equal(getattr(b, k), v)
    valid = z_raw != P.INVALID_RAW
    np.testing.assert_array_equal(b.valid, valid)
    np.testing.assert_allclose(b.z_mm[valid], z_raw[valid] * 0.002 + 100.0, rtol=1e-6)
    if points:
        np.testing.assert_allclose(b.x_mm[valid], x_raw[valid] * 0.1 - 0.15, rtol=1e-5, atol=1e-3)


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(0, 400), max_size=8))
def test_framer_reassembles_messages_split_anywhere(cuts: list[int]) -> None:
    data = b"".join(
        P.encode_frame_group(scale=SCALE, z_raw=np.full((2, 10), k, np.int16), **stamps(2, first=2 * k))
        for k in range(3)
    )
    framer = P.MessageFramer()
    msgs: list[P.Message] = []
    prev = 0
    for c in [*sorted(set(min(c, len(data)) for c in cuts)), len(data)]:
        msgs += framer.feed(data[prev:c])
        prev = c
    assert [m.type for m in msgs] == [1, 6] * 3
    assert [m.last for m in msgs] == [False, True] * 3
    assert framer.pending == 0


def test_quantize_marks_out_of_range_and_nan_invalid() -> None:
    z = np.array([100.0, np.nan, 1000.0, 100.0])
    valid = np.array([True, True, True, False])
    raw = P.quantize_mm(z, valid, 2000, 100_000)
    assert raw.tolist() == [0, P.INVALID_RAW, P.INVALID_RAW, P.INVALID_RAW]


def test_framer_rejects_size_below_header_as_framing_error() -> None:
    with pytest.raises(P.FramingError, match="size 3") as ei:
        P.MessageFramer().feed(struct.pack("<IH", 3, 1) + b"\0" * 10)
    assert ei.value.field == "size"


def test_framer_rejects_oversized_message() -> None:
    with pytest.raises(P.FramingError, match="outside"):
        P.MessageFramer(max_message_size=100).feed(struct.pack("<IH", 101, 1))


def _group(n: int = 2, w: int = 5) -> list[P.Message]:
    data = P.encode_frame_group(scale=SCALE, z_raw=np.zeros((n, w), np.int16), **stamps(n))
    return P.MessageFramer().feed(data)


def _patch(msg: P.Message, offset: int, fmt: str, value: int) -> P.Message:
    b = bytearray(msg.data)
    struct.pack_into(fmt, b, offset, value)
    return P.Message(msg.type, msg.last, bytes(b))


@pytest.mark.parametrize(
    ("which", "offset", "fmt", "value", "field"),
    [
        (1, 8, "<I", 3, "count"),  # profile count disagrees with stamps
        (1, 12, "<I", 4, "size"),  # width disagrees with the message size
        (1, 6, "<H", 30, "attr_size"),
        (1, 20, "<I", 0, "z_scale_nm"),
        (1, 32, "<Q", 99, "first_frame_index"),
        (0, 10, "<H", 32, "stamp_size"),
        (0, 6, "<I", 5, "count"),  # stamp count disagrees with the stamp message size
    ],
)
def test_decode_group_names_the_offending_field(
    which: int, offset: int, fmt: str, value: int, field: str
) -> None:
    msgs = _group()
    msgs[which] = _patch(msgs[which], offset, fmt, value)
    with pytest.raises(P.DecodeError) as ei:
        P.decode_group(msgs, 0)
    assert ei.value.field == field
    assert field in str(ei.value)


def test_decode_group_rejects_a_group_without_stamp() -> None:
    msgs = _group()
    with pytest.raises(P.DecodeError, match="expected STAMP"):
        P.decode_group([msgs[1], msgs[1]], 0)
    with pytest.raises(P.DecodeError, match="1 messages"):
        P.decode_group([msgs[1]], 0)


def test_decode_group_rejects_frame_indices_that_do_not_increase() -> None:
    s = stamps(3)
    s["frame_index"] = np.array([5, 5, 6], dtype=np.uint64)
    data = P.encode_frame_group(scale=SCALE, z_raw=np.zeros((3, 2), np.int16), **s)
    with pytest.raises(P.DecodeError, match="do not increase"):
        P.decode_group(P.MessageFramer().feed(data), 0)


def test_group_assembler_closes_a_group_that_never_ends() -> None:
    asm = P.GroupAssembler(max_messages=3)
    m = P.Message(P.MessageType.STAMP, False, b"")
    assert asm.push(m) is None and asm.push(m) is None
    group = asm.push(m)
    assert group is not None and len(group) == 3
    with pytest.raises(P.DecodeError):
        P.decode_group(group, 0)


def test_control_command_and_reply_round_trip() -> None:
    req = P.encode_command(P.CommandId.SET_RATE, P.U32.pack(200_000))
    assert req == struct.pack("<IHI", 10, 0x4003, 200_000)
    (msg,) = P.MessageFramer().feed(req)
    req_msg = P.decode_command(msg)
    assert req_msg.command is P.CommandId.SET_RATE
    assert P.decode_u32_param(req_msg.command, req_msg.payload) == 200_000
    rep = P.encode_reply(P.CommandId.SET_RATE, P.Status.INVALID_STATE, b"busy")
    assert rep == struct.pack("<IHi", 14, 0x4003, -4) + b"busy"
    (rmsg,) = P.MessageFramer().feed(rep)
    assert P.decode_reply(rmsg) == P.Reply(0x4003, -4, b"busy")


def test_unknown_command_is_a_decode_error_naming_the_id() -> None:
    (msg,) = P.MessageFramer().feed(P.encode_command(0x4999))
    with pytest.raises(P.DecodeError, match="0x4999") as ei:
        P.decode_command(msg)
    assert ei.value.field == "command"


def test_u32_parameter_of_wrong_length_is_rejected() -> None:
    with pytest.raises(P.DecodeError, match="SET_EXPOSURE"):
        P.decode_u32_param(P.CommandId.SET_EXPOSURE, b"\x01\x02")


def test_sensor_info_timestamp_and_state_replies_round_trip() -> None:
    info = P.SensorInfo(
        "HD8-0050W", "SN8-0050W-1", 500, 100_000, -24_950, 70_000, 130_000, 1_000_000, 100_000, 3_000_000
    )
    assert P.SensorInfo.from_bytes(info.to_bytes()) == info
    ts = P.TimestampReply(2**40 + 5, 2**32 - 1)
    assert P.TimestampReply.from_bytes(ts.to_bytes()) == ts
    state = P.StateReply(P.SensorState.RUNNING, 1234, 1000)
    assert P.StateReply.from_bytes(state.to_bytes()) == state
    with pytest.raises(P.DecodeError, match="GET_INFO payload"):
        P.SensorInfo.from_bytes(info.to_bytes()[:-1])


def test_subscribe_round_trip_and_live_marker() -> None:
    (msg,) = P.MessageFramer().feed(P.encode_subscribe(17))
    assert P.decode_subscribe(msg) == 17
    (msg,) = P.MessageFramer().feed(P.encode_subscribe())
    assert P.decode_subscribe(msg) == P.LIVE
    with pytest.raises(P.DecodeError, match="expected SUBSCRIBE"):
        P.decode_subscribe(_group()[0])


def test_command_error_message_names_command_and_status() -> None:
    err = P.CommandError(P.CommandId.SET_RATE, P.Status.INVALID_STATE, "stop first")
    assert "SET_RATE" in str(err) and "INVALID_STATE" in str(err) and "stop first" in str(err)


def test_decode_groups_splits_runs_by_layout_and_skips_bad_groups() -> None:
    other = P.ProfileScale(x_scale_nm=50_000, z_scale_nm=1000, x_offset_um=0, z_offset_um=0)
    datas = [
        P.encode_frame_group(scale=SCALE, z_raw=np.full((2, 4), 10, np.int16), **stamps(2, first=0)),
        P.encode_frame_group(scale=SCALE, z_raw=np.full((1, 4), 20, np.int16), **stamps(1, first=2)),
        P.encode_frame_group(scale=other, z_raw=np.full((1, 4), 30, np.int16), **stamps(1, first=3)),
        P.encode_frame_group(scale=other, z_raw=np.full((1, 4), 40, np.int16), **stamps(1, first=4)),
    ]
    framer = P.MessageFramer()
    groups = [framer.feed(d) for d in datas]
    groups[3][1] = _patch(groups[3][1], 8, "<I", 2)  # count mismatch: this group must be dropped
    out = P.decode_groups(groups, host_recv_ns=5)
    assert [len(b) for b in out.batches] == [3, 1]  # the first two share a layout: one numpy pass
    assert out.batches[0].frame_index.tolist() == [0, 1, 2]
    np.testing.assert_allclose(out.batches[0].z_mm[:, 0], [100.02, 100.02, 100.04], atol=1e-5)
    np.testing.assert_allclose(out.batches[1].x_mm[0], [0.0, 0.05, 0.1, 0.15], atol=1e-6)
    assert len(out.errors) == 1 and out.errors[0].field == "count"
