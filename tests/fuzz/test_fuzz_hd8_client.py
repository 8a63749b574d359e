"""Fuzz the HD8 client (drivers/laser/client.py) with mutated frames from a fake sensor over loopback TCP.

The fake sensor (written here, speaking drivers/laser/protocol.py) serves frames 0..4, then mutated
bytes, then frames 5..9; after a reconnect it serves from the frame the client asks for. Whatever
the mutation, the client must report it as a decode or framing error (never an unexpected
exception), resynchronise or reconnect, and get past frame 9 within a bounded time (no hang).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools

import numpy as np
from fuzzlib import fuzz_settings, mutated
from hypothesis import example, given
from hypothesis import strategies as st
from structlog.testing import capture_logs

from drivers.laser import protocol as P
from drivers.laser.client import HD8Client, HD8ClientConfig

WIDTH = 16
LAST_FRAME = 9
SCALE = P.ProfileScale(x_scale_nm=50_000, z_scale_nm=2_000, x_offset_um=-400, z_offset_um=100_000)
INFO = P.SensorInfo("HD8-FAKE", "FUZZ-1", WIDTH, 50_000, -400, 70_000, 130_000, 1_000_000, 10_000, 10_000_000)


def frame_group(first: int, n: int = 1, *, points: bool = False) -> bytes:
    """A valid frame group of ``n`` profiles starting at frame ``first``."""
    fi = np.arange(first, first + n, dtype=np.uint64)
    z = (np.arange(n * WIDTH, dtype=np.int16).reshape(n, WIDTH) % 1000).astype(np.int16)
    return P.encode_frame_group(
        frame_index=fi,
        sensor_time_us=1_000_000 + fi * 5000,
        hd8_ms=fi * 5,
        encoder=fi,
        status=np.zeros(n),
        exposure_ns=np.full(n, 500_000),
        scale=SCALE,
        z_raw=z,
        x_raw=np.tile(np.arange(WIDTH, dtype=np.int16), (n, 1)) if points else None,
    )


SEEDS = (frame_group(100), frame_group(200, 3), frame_group(300, 2, points=True), P.encode_subscribe(7))


class FakeSensor:
    """Control and data servers on ephemeral loopback ports; the first data connection carries ``junk``."""

    def __init__(self, junk: bytes) -> None:
        self.junk = junk
        self.connections = 0
        self.servers: list[asyncio.Server] = []
        self.writers: list[asyncio.StreamWriter] = []

    async def start(self) -> tuple[int, int]:
        ctl = await asyncio.start_server(self._control, "127.0.0.1", 0)
        dat = await asyncio.start_server(self._data, "127.0.0.1", 0)
        self.servers = [ctl, dat]
        return ctl.sockets[0].getsockname()[1], dat.sockets[0].getsockname()[1]

    async def close(self) -> None:
        for w in self.writers:
            w.transport.abort()
        for s in self.servers:
            s.close()
            await s.wait_closed()

    async def _control(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        framer = P.MessageFramer(max_message_size=4096)
        while chunk := await reader.read(4096):
            for msg in framer.feed(chunk):
                cmd = P.decode_command(msg).command
                if cmd == P.CommandId.GET_INFO:
                    payload = INFO.to_bytes()
                elif cmd == P.CommandId.GET_STATE:
                    payload = P.StateReply(P.SensorState.RUNNING, LAST_FRAME + 1, 0).to_bytes()
                else:
                    payload = b""
                writer.write(P.encode_reply(cmd, P.Status.OK, payload))

    async def _data(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        self.connections += 1
        framer = P.MessageFramer()
        msgs: list[P.Message] = []
        while not msgs:
            chunk = await reader.read(4096)
            if not chunk:
                return
            msgs = framer.feed(chunk)
        start = P.decode_subscribe(msgs[0])
        first = 0 if start == P.LIVE else int(start)
        if self.connections == 1:
            writer.write(b"".join(frame_group(i) for i in range(5)) + self.junk)
            writer.write(b"".join(frame_group(i) for i in range(5, LAST_FRAME + 1)))
        else:
            writer.write(b"".join(frame_group(i) for i in range(first, LAST_FRAME + 1)))
        with contextlib.suppress(ConnectionError):
            await writer.drain()
            while await reader.read(4096):  # hold the connection open like a sensor between frames
                pass


async def _run(junk: bytes) -> tuple[list[int], HD8Client, list[dict], int]:
    sensor = FakeSensor(junk)
    ctl_port, data_port = await sensor.start()
    config = HD8ClientConfig(
        watchdog_timeout_s=0.3, reconnect_initial_s=0.01, reconnect_max_s=0.2, keepalive_interval_s=0.5
    )
    client = HD8Client("127.0.0.1", ctl_port, data_port, config=config)
    frames: list[int] = []

    async def consume() -> None:
        async for batch in client:
            frames.extend(int(f) for f in batch.frame_index)

    with capture_logs() as logs:
        consumer = asyncio.create_task(consume())
        try:
            await client.connect()
            await client.start()
            for _ in range(1000):  # up to 10 s: past the last valid frame
                if client.stats.last_frame_index >= LAST_FRAME:
                    break
                await asyncio.sleep(0.01)
        finally:
            await client.close()
            await asyncio.wait_for(consumer, 5)
            await sensor.close()
    return frames, client, logs, sensor.connections


@st.composite
def _junk(draw: st.DrawFn) -> bytes:
    return draw(mutated(draw(st.sampled_from(SEEDS)), SEEDS))


def _check(frames: list[int], client: HD8Client, logs: list[dict]) -> None:
    assert not [e for e in logs if e["event"] == "hd8_data_task_error"], logs  # only protocol errors
    assert client.stats.last_frame_index >= LAST_FRAME, (client.stats, [e["event"] for e in logs])
    assert frames[:5] == [0, 1, 2, 3, 4]
    assert all(b > a for a, b in itertools.pairwise(frames))  # never duplicated or reordered


@fuzz_settings(25)
@given(junk=_junk())
# found by this test: one stray byte shifts the stream, the next "size" asks for megabytes that
# never come, and the client waited for them forever (now: FramingError after the watchdog time)
@example(junk=b"6")
def test_hd8_client_reports_mutated_frames_and_carries_on_past_them(junk):
    frames, client, logs, _ = asyncio.run(asyncio.wait_for(_run(junk), 30))
    _check(frames, client, logs)


@fuzz_settings(15)
@given(junk=st.binary(min_size=1, max_size=512))
def test_hd8_client_survives_random_bytes_on_the_data_channel(junk):
    frames, client, logs, _ = asyncio.run(asyncio.wait_for(_run(junk), 30))
    _check(frames, client, logs)
