"""The simulators' fault channel: one JSON object a line over TCP, one JSON reply a line.

A simulator run on its own (``python -m drivers.abb_egm.sim --fault-port``, the HD8 simulator's
``fault_port``) serves it so that a test reaches the faults the way it reaches the simulator: over a
socket, never by a Python call. What a request holds is the simulator's (its ``apply`` callable);
here is only the wire: a line that is not JSON is answered ``{"ok": false, "error": ...}`` and the
connection goes on serving; a line past the stream limit or a client gone ends that connection only.
(The simulated cell, ``cellctl sim``, has its own channel over Zenoh: cellctl/simcell/faults.py.)
Simulator code shared by the simulators, so it lives in their wing (``drivers/sim/``): production
code never imports it (tests/test_architecture.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Callable
from typing import Any

__all__ = ["Apply", "send_fault_request", "start_fault_server"]

#: the simulator's side: the decoded request -> the reply object (``{"ok": bool, ...}``)
Apply = Callable[[Any], dict[str, Any]]


async def start_fault_server(host: str, port: int, apply: Apply) -> asyncio.Server:
    """Listen on ``host:port`` (0: any free port) and answer every line with ``apply``'s reply."""

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                try:
                    request = json.loads(line)
                except ValueError as exc:
                    reply: dict[str, Any] = {"ok": False, "error": f"not a JSON line: {exc}"}
                else:
                    reply = apply(request)
                writer.write(json.dumps(reply).encode() + b"\n")
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    return await asyncio.start_server(serve, host, port)


async def send_fault_request(
    address: tuple[str, int] | list[Any], request: dict[str, Any], timeout_s: float = 30.0
) -> dict[str, Any]:
    """Send one request on a fresh connection to ``address`` (host, port); returns the reply object."""
    reader, writer = await asyncio.wait_for(asyncio.open_connection(address[0], int(address[1])), timeout_s)
    try:
        writer.write(json.dumps(request).encode() + b"\n")
        await writer.drain()
        line = await asyncio.wait_for(reader.readline(), timeout_s)
    finally:
        writer.close()
    if not line:
        raise ConnectionError(f"fault channel {address} closed without a reply")
    return json.loads(line)
