"""A slow, lossy TCP link in user space, for kernels without ``sch_netem`` (``tc qdisc ... netem``:
"Specified qdisc kind is unknown", and no module to load).

Run inside a host's network namespace, it listens on that host's loopback and relays every
connection to one target across the host's real link, holding the bytes of each direction for
``delay_ms`` (one-way delay: 20 ms each way is a 40 ms round trip) and, for ``loss_pct`` of the
MSS-sized segments, an extra ``loss_stall_ms``. A byte stream cannot lose bytes: what a TCP
connection sees of a lost segment is the stall until its retransmission arrives, every later
byte held behind it (head-of-line blocking), and that is what this models. The default stall,
three round trips, stands for a fast retransmit and the window regrown after it; netem's real
loss also shrinks the window for a while, which this does not model.

    ip netns exec <ns> python -m tests.support.slow_link --target 10.77.0.1:7447 --delay-ms 20 \
        --loss-pct 1

prints one JSON line ``{"ready": true, "port": P}`` (listening on 127.0.0.1:P) and relays until
SIGTERM. Only 127.0.0.1 is bound; the target is the caller's (the fleet's router address inside
its own namespaces).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import signal
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

MSS = 1448  # an Ethernet TCP segment's payload


@dataclass(frozen=True)
class LinkModel:
    """One direction's delay and loss."""

    delay_ms: float = 20.0
    loss_pct: float = 1.0
    loss_stall_ms: float | None = None  # None: three round trips (6 x delay_ms), at least 20 ms

    @property
    def stall_s(self) -> float:
        stall = self.loss_stall_ms if self.loss_stall_ms is not None else max(6.0 * self.delay_ms, 20.0)
        return stall / 1000.0

    def release_time(self, n_bytes: int, now: float, last: float, rng: random.Random) -> float:
        """When the last of ``n_bytes`` read at ``now`` may go on, after the previous release at
        ``last`` (strictly in order): the delay, plus a stall for every segment drawn as lost."""
        t = max(now + self.delay_ms / 1000.0, last)
        segments = -(-n_bytes // MSS)
        lost = sum(rng.random() * 100.0 < self.loss_pct for _ in range(segments))
        return t + lost * self.stall_s


async def _pipe(reader, writer, model: LinkModel, rng: random.Random, counter: list[int]) -> None:
    """Relay one direction: each read is held until its release time, in order."""
    queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def release() -> None:
        while True:
            t, data = await queue.get()
            if not data:
                break
            wait = t - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
            counter[0] += len(data)

    sender = asyncio.create_task(release())
    last = 0.0
    try:
        while True:
            data = await reader.read(1 << 16)
            last = model.release_time(len(data), time.monotonic(), last, rng) if data else last
            queue.put_nowait((last, data))
            if not data:
                break
        await sender
    except (ConnectionError, OSError):
        pass
    finally:
        sender.cancel()
        with contextlib.suppress(BaseException):
            await sender
        with contextlib.suppress(Exception):
            writer.transport.abort()


async def serve(
    target: tuple[str, int],
    model: LinkModel,
    *,
    seed: int = 0,
    connect_timeout_s: float = 5.0,
    on_ready: Callable[[int], None] | None = None,
) -> None:
    """Relay until SIGTERM (or cancelled); ``on_ready(port)`` once listening (default: the JSON
    ready line on stdout)."""
    rng = random.Random(seed)
    counts = [0], [0]  # bytes up (to the target), bytes down

    async def on_client(reader, writer) -> None:
        try:
            t_reader, t_writer = await asyncio.wait_for(asyncio.open_connection(*target), connect_timeout_s)
        except (OSError, TimeoutError):
            writer.transport.abort()  # the link is down: refuse, the client retries
            return
        await asyncio.gather(
            _pipe(reader, t_writer, model, rng, counts[0]), _pipe(t_reader, writer, model, rng, counts[1])
        )
        for w in (writer, t_writer):
            with contextlib.suppress(Exception):
                w.transport.abort()

    server = await asyncio.start_server(on_client, "127.0.0.1", 0, family=socket.AF_INET)
    port = server.sockets[0].getsockname()[1]
    if on_ready is not None:
        on_ready(port)
    else:
        print(json.dumps({"ready": True, "port": port}), flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    server.close()
    print(json.dumps({"bytes_up": counts[0][0], "bytes_down": counts[1][0]}), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--target", required=True, help="host:port to relay to")
    ap.add_argument("--delay-ms", type=float, default=20.0)
    ap.add_argument("--loss-pct", type=float, default=1.0)
    ap.add_argument("--loss-stall-ms", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    host, port = args.target.rsplit(":", 1)
    model = LinkModel(args.delay_ms, args.loss_pct, args.loss_stall_ms)
    asyncio.run(serve((host, int(port)), model, seed=args.seed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
