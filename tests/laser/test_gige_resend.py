"""A successful GVSP packet resend: Aravis's client (the GigE source) and Aravis's fake device, with a
relay in between that drops payload packets and answers PACKETRESEND (tests/laser/gvsp_relay.py).

Aravis's fake device answers no PACKETRESEND (0.8.26), so against it alone a lost packet always
tears its buffer (test_gige_fake_device.py). The relay stands on 127.0.0.2 for a device that serves
resends: the source opens it as the device, the fake device streams to it, it forwards every packet
but every 29th payload packet and sends any packet asked again from its cache. The same drops with
the relay's answers switched off tear the buffers they fall in: the resends are what completed them.

Each buffer's block id is read back from its rows (the fake device's Mono16 ramp is
``256 * (column + block id + row) mod 65535``; 256 is its own inverse mod 65535), so the blocks the
relay dropped packets from are named among the delivered (or torn) ones.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.laser.gige import GigeProfileSource, GigeSourceConfig
from tests.laser.gige_helpers import C_OFFSET, C_SCALE, fake_device, profiler_xml
from tests.laser.gvsp_relay import GvspRelay, parse_gvsp_header, parse_packet_resend
from tests.laser.laser_helpers import collect, run

RAMP_EXPOSURE_NS = 10_000_000  # the fake device's ramp is exact at 10 ms
ROWS = 100  # rows per buffer: 100 x 500 Mono16 = 13 payload packets of 8 kB, a leader and a trailer
DROP_EVERY = 29  # about every other buffer loses one payload packet (a few lose two)
N_ROWS = 4000
RATE_HZ = 4000.0  # 40 buffers/s
#: how long Aravis keeps an incomplete buffer (the source's default is 100 ms): the relay is a Python
#: thread, and on a loaded machine a stall of it is a network stall; both tests use the same value
RETENTION_MS = 400


def _block_ids(batch) -> np.ndarray:
    """The GVSP block id of each row of ``batch``, from the ramp; asserts every valid point fits it."""
    codes = np.rint(np.nan_to_num((batch.z_mm - C_OFFSET) / C_SCALE, nan=-1.0)).astype(np.int64)
    rows, cols = np.nonzero(batch.valid)
    b = (256 * codes[rows, cols] - cols) % 65535  # = block id + row (mod 65535)
    with_points, first = np.unique(rows, return_index=True)  # the first valid point of each row
    assert len(with_points) == len(batch), "a row without a valid point"
    block = (b[first] - np.arange(len(batch))) % 65535
    # every valid point is the ramp of that block id: the buffer is intact, packet by packet
    expect = (256 * (cols + block[rows] + rows)) % 65535
    assert (codes[rows, cols] == expect).all()
    return np.where(block == 0, 65535, block)  # GVSP 1.x ids run 1..65535


async def _stream(relay: GvspRelay) -> tuple[list, object]:
    cfg = GigeSourceConfig(rows_per_buffer=ROWS, packet_size=8192, frame_retention_ms=RETENTION_MS)
    src = GigeProfileSource(relay.address, config=cfg)
    await src.connect()
    await src.configure(rate_hz=RATE_HZ, exposure_ns=RAMP_EXPOSURE_NS, width=500)
    await src.start()
    out = await collect(src, N_ROWS, timeout_s=30)
    src.refresh_stats()
    await src.close()
    return out, src.stats


def _through_relay(tmp_path, serial: str, *, answer_resends: bool):
    relay = GvspRelay(drop_every=DROP_EVERY, answer_resends=answer_resends)
    with fake_device(serial, profiler_xml(tmp_path)), relay:
        batches, stats = run(_stream(relay), timeout_s=60)
    blocks = [int(_block_ids(b)[0]) for b in batches]
    assert all(len(set(_block_ids(b).tolist())) == 1 for b in batches)
    return batches, stats, relay.stats, blocks


def _span(blocks: list[int]) -> list[int]:
    """Every block id from the first delivered to the last, in order (ids wrap 65535 -> 1)."""
    out = [blocks[0]]
    while out[-1] != blocks[-1]:
        out.append(out[-1] % 65535 + 1)
        assert len(out) <= 65535
    return out


@pytest.mark.process
@pytest.mark.slow
def test_packets_dropped_on_the_way_are_resent_and_every_buffer_completes(tmp_path):
    batches, stats, relay, blocks = _through_relay(tmp_path, "WT63RESEND", answer_resends=True)
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    assert fi[0] == 0 and (np.diff(fi) == 1).all()  # every row, in order
    assert stats.torn_buffers == 0 and stats.gaps == 0 and stats.missing_frames == 0
    assert stats.missing_packets == 0 and stats.duplicates_dropped == 0
    # the relay dropped packets, was asked for them (standard ids: the fake device sends no
    # extended ones) and had each one to send again
    assert relay.dropped >= 10 and relay.resend_commands > 0 and relay.extended_resend_commands == 0
    assert relay.resent > 0 and relay.unavailable == 0
    assert stats.resent_packets > 0  # Aravis's count of asked-for packets that came
    # the buffers with a dropped packet are delivered, intact (checked row by row in _block_ids)
    assert blocks == _span(blocks)
    delivered = set(blocks)
    dropped_in = [k for k in relay.dropped_keys if k[0] in delivered]
    assert len({b for b, _ in dropped_in}) >= 8
    assert set(dropped_in) <= set(relay.resent_keys)
    assert stats.resent_packets >= len(dropped_in)  # each came to Aravis as a packet it had asked for
    # what was dropped before the last delivered buffer was in a delivered one (none was skipped)
    last = max(i for i, k in enumerate(relay.dropped_keys) if k[0] in delivered)
    assert all(k[0] in delivered for k in relay.dropped_keys[: last + 1])


@pytest.mark.process
@pytest.mark.slow
def test_without_the_relays_resends_the_same_drops_tear_the_buffers_they_fall_in(tmp_path):
    batches, stats, relay, blocks = _through_relay(tmp_path, "WT63NORESEND", answer_resends=False)
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    assert (np.diff(fi) > 0).all()
    assert relay.dropped >= 10 and relay.resend_commands > 0 and relay.resent == 0
    assert stats.resent_packets == 0 and stats.missing_packets > 0
    assert stats.torn_buffers > 0 and stats.gaps > 0
    assert stats.frames + stats.missing_frames == stats.last_frame_index + 1
    assert stats.missing_frames % ROWS == 0  # whole buffers
    # no buffer with a dropped packet is delivered; each one within the delivered span is a gap
    dropped_blocks = {b for b, _ in relay.dropped_keys}
    assert not dropped_blocks & set(blocks)
    missing = set(_span(blocks)) - set(blocks)
    assert dropped_blocks & set(_span(blocks)) <= missing
    assert len(missing) >= 8
    assert stats.missing_frames >= ROWS * len(missing)


def test_the_relay_reads_both_forms_of_packetresend_and_gvsp_headers():
    """The packets as Aravis 0.8.26 builds them (arvgvcp.c: arv_gvcp_packet_new_packet_resend_cmd)."""
    header = struct.pack(">BBHHH", 0x42, 0x00, 0x0040, 12, 7)
    assert parse_packet_resend(header + struct.pack(">III", 65402, 3, 5)) == (0, 65402, 3, 5)
    ext = struct.pack(">BBHHH", 0x42, 0x10, 0x0040, 20, 8) + struct.pack(">IIIQ", 0, 3, 9, 1 << 40)
    assert parse_packet_resend(ext) == (0, 1 << 40, 3, 9)
    assert parse_packet_resend(struct.pack(">BBHHH", 0x42, 0, 0x0080, 4, 9) + bytes(12)) is None
    # GVSP: status, block id (16), content type << 24 | packet id (24); extended: flag 0x80 in byte 4
    assert parse_gvsp_header(struct.pack(">HHI", 0, 65401, 0x03 << 24 | 4) + bytes(8)) == (65401, 4, 3, False)
    ext_gvsp = struct.pack(">HHIQI", 0, 0, (0x80 | 0x02) << 24, 1 << 33, 14)
    assert parse_gvsp_header(ext_gvsp) == (1 << 33, 14, 2, True)
