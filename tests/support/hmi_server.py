"""An HMI server in this process, without a cell: `HmiServer` with a fake `CellLink`.

The fake link holds a `CellStatus` the test sets (:meth:`LocalHmi.publish`, pushed to every open
websocket as the real link does), answers triggers and controls with what the test queues, and
records what it was sent. The server runs on its own event loop in a thread, on loopback, so that
an aiohttp client, Playwright or plain sockets can reach it; its log lines (structlog and the
standard library's) are captured in :attr:`LocalHmi.log`.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import shutil
import threading
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import structlog
from aiohttp import web

from cellctl.api import ApiCallError, CellStatus, ControlReply, TriggerAccepted
from cellctl.config import CellConfig, parse_config
from cellctl.hmi.auth import Authenticator, LoginLimiter, add_user, load_users
from cellctl.hmi.server import HmiServer
from cellctl.jobstore.jobs import JobRecord, JobStore
from cellctl.logging import configure_logging
from tests.support.ports import free_port

USERS = {
    "olga": ("operator", "operator-pass-1"),
    "vic": ("viewer", "viewer-pass-1"),
    "erin": ("engineer", "engineer-pass-1"),
}


class FakeLink:
    """What `HmiServer` uses of `CellLink`, without Zenoh."""

    def __init__(self, cfg: CellConfig, on_event: Any) -> None:
        self.on_event = on_event
        self.status: CellStatus | None = None
        self.on_job_end: Any = None
        self.sent: list[tuple[str, str]] = []
        self.replies: list[Any] = []  # TriggerAccepted / ControlReply / ApiCallError, first first
        self.live: dict[str, tuple[list[list[float]], int]] = {}  # job id -> (points, last chunk's seq)

    async def start(self) -> None:
        return None

    async def close(self) -> None:
        return None

    def live_cloud(self, job_id: str) -> tuple[list[list[float]], int]:
        return self.live.get(job_id, ([], -1))

    def _reply(self, kind: type) -> Any:
        r = self.replies.pop(0) if self.replies else None
        if isinstance(r, ApiCallError):
            raise r
        if r is None:
            raise ApiCallError("fake", None, "the fake cell has no reply queued")
        assert isinstance(r, kind), r
        return r

    async def trigger(self, body: str) -> TriggerAccepted:
        self.sent.append(("trigger", body))
        return self._reply(TriggerAccepted)

    async def control(self, action: str, body: str) -> ControlReply:
        self.sent.append((action, body))
        return self._reply(ControlReply)


class LocalHmi:
    """An `HmiServer` with a `FakeLink` serving on 127.0.0.1 from a thread of its own."""

    def __init__(self, root: Path, *, limiter: LoginLimiter | None = None, host: str = "127.0.0.1") -> None:
        self.root = root
        self.data_dir = root / "data"
        (self.data_dir / "jobs").mkdir(parents=True, exist_ok=True)
        (root / "designs").mkdir(exist_ok=True)
        users = root / "hmi-users"
        if not users.exists():
            for name, (role, pw) in USERS.items():
                add_user(users, name, role, pw)
        self.cfg = parse_config(
            {"cell": {"data_dir": str(self.data_dir), "designs_dir": str(root / "designs")}}
        )
        self.auth = Authenticator(load_users(users))
        if limiter is not None:
            self.auth.limiter = limiter
        self.host = host
        self.port = free_port()
        self.url = f"http://{host}:{self.port}"
        self.log = io.StringIO()
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="local-hmi", daemon=True)
        self.server: HmiServer | None = None
        self._runner: web.AppRunner | None = None

    def add_done_job(self, job_id: str, results_dir: Path, plate_id: str) -> Path:
        """A done job in the data directory (its record through the job store) with a copy of
        ``results_dir`` as its results; call before :meth:`start` (the history is built then).
        Returns the job's directory."""
        store = JobStore(self.data_dir)
        rec = JobRecord(job_id, plate_id, "plate.igs", "/srv/cell/designs/plate.igs", None, state="done",
                        history=[{"state": "done", "t_utc": "2026-12-07T12:30:00Z", "message": "done"}])  # fmt: skip
        store.create(rec)
        shutil.copytree(results_dir, store.results_dir(job_id), ignore=shutil.ignore_patterns("cloud.ply"))
        return store.job_dir(job_id)

    @property
    def link(self) -> FakeLink:
        assert self.server is not None
        return self.server.link  # type: ignore[return-value]

    def start(self) -> LocalHmi:
        configure_logging("json", stream=self.log)
        self._thread.start()
        self.run(self._start())
        return self

    async def _start(self) -> None:
        import cellctl.hmi.server as server_mod

        real = server_mod.CellLink
        server_mod.CellLink = FakeLink  # type: ignore[misc,assignment]
        try:
            self.server = HmiServer(self.cfg, self.auth)
        finally:
            server_mod.CellLink = real  # type: ignore[misc]
        self._runner = web.AppRunner(self.server.app, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, self.host, self.port).start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout_s: float = 60.0) -> Any:
        """Run ``coro`` on the server's loop and return its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def publish(self, status: CellStatus | dict[str, Any]) -> None:
        """The cell publishes ``status``: kept by the link and pushed to every websocket."""
        st = status if isinstance(status, CellStatus) else CellStatus.model_validate(status)

        async def push() -> None:
            self.link.status = st
            self.link.on_event({"type": "status", "status": st.model_dump(mode="json")})

        self.run(push())

    def event(self, event: dict[str, Any]) -> None:
        """Any other event of the link (``live``, ``report``, ``history``) pushed to the websockets."""

        async def push() -> None:
            self.link.on_event(dict(event))

        self.run(push())

    def stop(self) -> None:
        if self._runner is not None:
            self.run(self._runner.cleanup())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        self.loop.close()
        structlog.reset_defaults()
        for h in list(logging.getLogger().handlers):
            if getattr(h, "stream", None) is self.log:
                logging.getLogger().removeHandler(h)

    def log_lines(self) -> list[dict[str, Any]]:
        out = []
        for line in self.log.getvalue().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                out.append({"raw": line})
        return out

    def __enter__(self) -> LocalHmi:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
