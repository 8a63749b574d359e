"""A loopback TCP forwarder that can cut a link on demand: the network fault between a Zenoh client
(a worker) and the daemon's listener, made honestly with real sockets.

It runs its own asyncio loop in a thread, so a plain (synchronous) test or benchmark can drive it:

    fwd = TcpForwarder(("127.0.0.1", daemon_port)).start()   # fwd.port: where the worker connects
    fwd.cut()       # every open connection is reset, new ones are accepted and closed at once
    fwd.restore()   # new connections are forwarded again
    fwd.close()

Only 127.0.0.1 is ever bound or dialled.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from dataclasses import dataclass


class ForwarderError(Exception):
    """The forwarder could not start (bind failed) or was used after close."""


@dataclass
class ForwarderStats:
    """What crossed the forwarder: connections forwarded, refused while cut, and bytes each way."""

    accepted: int = 0
    refused: int = 0
    cuts: int = 0
    bytes_up: int = 0  # client -> target
    bytes_down: int = 0  # target -> client


class TcpForwarder:
    """Forwards every connection on ``127.0.0.1:port`` to ``target`` until cut."""

    def __init__(self, target: tuple[str, int], *, chunk_bytes: int = 1 << 16) -> None:
        if target[0] not in ("127.0.0.1", "localhost"):
            raise ForwarderError(f"target {target[0]!r}: only loopback targets are forwarded")
        self.target = target
        self.chunk_bytes = chunk_bytes
        self.stats = ForwarderStats()
        self.port = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.base_events.Server | None = None
        self._links: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self._cut = False
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ control (any thread)

    def start(self) -> TcpForwarder:
        """Bind an ephemeral loopback port and serve in a background thread; returns self."""
        self._thread = threading.Thread(target=self._run, name="tcp-forwarder", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise ForwarderError(f"forwarder did not start: {self._error}") from self._error
        if not self.port:
            raise ForwarderError("forwarder did not start within 10 s")
        return self

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint a client connects to, ``tcp/127.0.0.1:<port>``."""
        return f"tcp/127.0.0.1:{self.port}"

    @property
    def is_cut(self) -> bool:
        return self._cut

    def cut(self) -> None:
        """Reset every forwarded connection and refuse new ones until :meth:`restore`."""
        self._call(self._do_cut)

    def restore(self) -> None:
        """Forward new connections again."""
        self._cut = False

    def close(self) -> None:
        """Stop serving, drop every link, join the thread (idempotent)."""
        if self._loop is None or self._thread is None:
            return
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10.0)
        self._loop = None

    def __enter__(self) -> TcpForwarder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the loop thread

    def _call(self, fn) -> None:
        if self._loop is None:
            raise ForwarderError("forwarder is not running")
        done = threading.Event()

        def run() -> None:
            try:
                fn()
            finally:
                done.set()

        self._loop.call_soon_threadsafe(run)
        done.wait(5.0)

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            self._server = loop.run_until_complete(
                asyncio.start_server(self._on_client, "127.0.0.1", 0, family=socket.AF_INET)
            )
            self.port = int(self._server.sockets[0].getsockname()[1])
        except OSError as exc:
            self._error = exc
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            self._drop_links()
            self._server.close()
            pending = asyncio.all_tasks(loop)
            for t in pending:
                t.cancel()
            with contextlib.suppress(Exception):
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.close()

    def _do_cut(self) -> None:
        self._cut = True
        self.stats.cuts += 1
        self._drop_links()

    def _drop_links(self) -> None:
        for a, b in list(self._links):
            for w in (a, b):
                # An abortive close (RST), as when a cable is pulled and the peer times out.
                with contextlib.suppress(Exception):
                    w.transport.abort()
        self._links.clear()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._cut:
            self.stats.refused += 1
            writer.transport.abort()
            return
        try:
            t_reader, t_writer = await asyncio.open_connection(*self.target)
        except OSError:
            self.stats.refused += 1
            writer.transport.abort()
            return
        self.stats.accepted += 1
        link = (writer, t_writer)
        self._links.add(link)
        try:
            await asyncio.gather(
                self._pump(reader, t_writer, up=True), self._pump(t_reader, writer, up=False)
            )
        finally:
            self._links.discard(link)
            for w in link:
                with contextlib.suppress(Exception):
                    w.transport.abort()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, up: bool) -> None:
        try:
            while True:
                data = await reader.read(self.chunk_bytes)
                if not data:
                    break
                writer.write(data)
                await writer.drain()
                if up:
                    self.stats.bytes_up += len(data)
                else:
                    self.stats.bytes_down += len(data)
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            with contextlib.suppress(Exception):
                writer.transport.abort()
