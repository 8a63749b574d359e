"""The user-space slow link (tests/support/slow_link.py) the fleet uses where the kernel has no netem:
bytes arrive whole and in order, held the one-way delay, and lost segments stall what follows."""

from __future__ import annotations

import asyncio
import contextlib
import random
import time

from tests.support import slow_link
from tests.support.slow_link import MSS, LinkModel


def test_release_times_are_in_order_delayed_and_stalled_per_lost_segment():
    rng = random.Random(1)
    clean = LinkModel(delay_ms=20.0, loss_pct=0.0)
    assert clean.release_time(MSS, 5.0, 0.0, rng) == 5.02
    assert clean.release_time(MSS, 5.0, 6.0, rng) == 6.0  # never before the previous read
    lossy = LinkModel(delay_ms=20.0, loss_pct=100.0)
    assert abs(lossy.release_time(3 * MSS, 5.0, 0.0, rng) - (5.02 + 3 * 0.12)) < 1e-9
    one_pct = LinkModel(delay_ms=20.0, loss_pct=1.0)
    extra = [one_pct.release_time(MSS, 0.0, 0.0, rng) - 0.02 for _ in range(20000)]
    lost = sum(e > 0.1 for e in extra) / len(extra)
    assert 0.007 < lost < 0.013


def test_relayed_bytes_arrive_whole_in_order_after_the_delay():
    async def main():
        received = bytearray()
        got_all = asyncio.Event()

        async def sink(reader, writer):
            while data := await reader.read(1 << 16):
                received.extend(data)
                if len(received) >= 500_000:
                    got_all.set()
            writer.close()

        server = await asyncio.start_server(sink, "127.0.0.1", 0)
        target = ("127.0.0.1", server.sockets[0].getsockname()[1])
        ready: asyncio.Queue[int] = asyncio.Queue()
        try:
            model = LinkModel(delay_ms=30.0, loss_pct=2.0)
            relay = asyncio.create_task(slow_link.serve(target, model, seed=3, on_ready=ready.put_nowait))
            port = await asyncio.wait_for(ready.get(), 5)
            payload = bytes(random.Random(0).randbytes(500_000))
            t0 = time.monotonic()
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(payload)
            await writer.drain()
            await asyncio.wait_for(got_all.wait(), 20)
            elapsed = time.monotonic() - t0
            writer.close()
            relay.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await relay
        finally:
            server.close()
        return bytes(received), payload, elapsed

    received, payload, elapsed = asyncio.run(main())
    assert received == payload
    assert elapsed >= 0.03
