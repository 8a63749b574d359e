"""Headless Chromium driven over its DevTools protocol (a websocket on loopback), for the report tests.

Only what the tests need: start Debian's ``chromium`` on an ephemeral debugging port, attach to its
page, send commands, collect events.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import shutil
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp

CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
)


class CdpError(RuntimeError):
    """The browser did not start, or a DevTools command failed (the method and its error in the message)."""


def chromium_path() -> str:
    """The system Chromium; the report tests need it (scripts/setup.sh installs it)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise CdpError("chromium is not installed: run scripts/setup.sh (apt-get install chromium)")
    return exe


class Page:
    """One page target: ``send`` commands, ``events`` received so far, ``wait_for`` an event."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self._ws = ws
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future] = {}
        self.events: list[dict[str, Any]] = []
        self._new_event = asyncio.Event()
        self._reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for msg in self._ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            data = json.loads(msg.data)
            if "id" in data:
                fut = self._pending.pop(data["id"], None)
                if fut is not None and not fut.done():
                    fut.set_result(data)
            else:
                self.events.append(data)
                self._new_event.set()
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(CdpError("the browser closed the DevTools connection"))

    async def send(self, method: str, params: dict | None = None, timeout_s: float = 60.0) -> dict:
        """Send one command and return its result (raises CdpError on an error answer)."""
        msg_id = next(self._ids)
        fut = asyncio.get_running_loop().create_future()
        self._pending[msg_id] = fut
        await self._ws.send_str(json.dumps({"id": msg_id, "method": method, "params": params or {}}))
        reply = await asyncio.wait_for(fut, timeout_s)
        if "error" in reply:
            raise CdpError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    async def wait_for(self, method: str, timeout_s: float = 60.0) -> dict:
        """The first event named ``method`` (already received or arriving within the timeout)."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while True:
            for ev in self.events:
                if ev.get("method") == method:
                    return ev
            remaining = deadline - asyncio.get_running_loop().time()
            if remaining <= 0:
                raise CdpError(f"no {method} event within {timeout_s} s")
            self._new_event.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._new_event.wait(), remaining)

    async def evaluate(self, expression: str) -> Any:
        """Evaluate JavaScript in the page and return its JSON value."""
        res = await self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in res:
            raise CdpError(f"Runtime.evaluate: {res['exceptionDetails']}")
        return res["result"].get("value")

    async def close(self) -> None:
        self._reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._reader


async def _wait_port(user_data_dir: Path, proc: asyncio.subprocess.Process, timeout_s: float) -> int:
    marker = user_data_dir / "DevToolsActivePort"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.returncode is not None:
            raise CdpError(f"chromium exited with code {proc.returncode} before opening its DevTools port")
        with contextlib.suppress(FileNotFoundError, ValueError, IndexError):
            return int(marker.read_text().splitlines()[0])
        await asyncio.sleep(0.05)
    raise CdpError(f"chromium wrote no {marker} within {timeout_s} s")


@contextlib.asynccontextmanager
async def chromium_page(work_dir: Path, startup_timeout_s: float = 60.0) -> AsyncIterator[Page]:
    """Start headless Chromium with a fresh profile in ``work_dir`` and attach to its first page."""
    profile = work_dir / "chromium-profile"
    profile.mkdir(parents=True, exist_ok=True)
    with (work_dir / "chromium.log").open("wb") as log:
        proc = await asyncio.create_subprocess_exec(
            chromium_path(),
            *CHROMIUM_FLAGS,
            f"--user-data-dir={profile}",
            "about:blank",
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
    try:
        port = await _wait_port(profile, proc, startup_timeout_s)
        async with aiohttp.ClientSession(trust_env=False) as http:
            async with http.get(f"http://127.0.0.1:{port}/json/list") as resp:
                targets = await resp.json()
            ws_url = next(t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page")
            async with http.ws_connect(ws_url, max_msg_size=0) as ws:
                page = Page(ws)
                try:
                    yield page
                finally:
                    await page.close()
    finally:
        if proc.returncode is None:
            proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 10)
            except TimeoutError:
                proc.kill()
                await proc.wait()
