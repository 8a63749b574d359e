"""The HMI's one path into the cell: a Zenoh client session (``cellctl.api``), nothing else.

Follows the state publication, the live cloud and the reports; sends triggers and controls as
queries. What arrives is handed to ``on_event`` (the server pushes it to the browsers). The job
directories are read (never written) for the history and the downloads.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import structlog
from pydantic import ValidationError

from cellctl.api import (
    FINAL_JOB_STATES,
    ApiCallError,
    CellStatus,
    ControlReply,
    Keys,
    LiveCloudChunk,
    ReportEnvelope,
    TriggerAccepted,
    call,
)
from cellctl.api.session import (
    ZenohSetupError,
    build_zenoh_config,
    close_session,
    open_session,
    subscribe,
)
from cellctl.config import CellConfig

log = structlog.get_logger(__name__)

#: points of the live cloud kept per job for a page opened mid-scan
LIVE_KEEP_POINTS = 200_000


class CellLink:
    def __init__(
        self,
        cfg: CellConfig,
        on_event: Callable[[dict[str, Any]], None],
        *,
        live: bool = True,
        who: str = "hmi",
    ) -> None:
        """``live``: follow the live cloud too (the HMI's scan page; the OPC UA server does not);
        ``who``: the session's name in errors and logs."""
        self.cfg = cfg
        self.follow_live = live
        self.who = who
        self.keys = Keys(cfg.key_prefix)
        self.on_event = on_event
        self.session: Any = None
        self.status: CellStatus | None = None
        self.status_rx_monotonic = 0.0
        self.live_job: str | None = None
        self.live_points: list[np.ndarray] = []
        self.live_count = 0
        self.live_chunks = 0
        #: the sequence number of the last chunk kept in ``live_points`` (-1: none)
        self.live_seq = -1
        self.ended: set[str] = set()
        self.on_job_end: Callable[[str], None] | None = None
        #: every well-formed report publication, whole (the OPC UA server keeps the latest)
        self.on_report: Callable[[ReportEnvelope], None] | None = None
        self._subs: list[Any] = []

    async def start(self, timeout_s: float = 60.0) -> None:
        """Open the session (retrying until the daemon listens) and follow the cell."""
        zcfg = lambda: build_zenoh_config(self.cfg.zenoh, role="connect", key_prefix=self.cfg.key_prefix)  # noqa: E731
        deadline = time.monotonic() + timeout_s
        while self.session is None:
            try:
                self.session = await asyncio.to_thread(open_session, zcfg(), what=f"{self.who} session")
            except ZenohSetupError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.5)
        s = self.session
        self._subs = [
            subscribe(s, self.keys.state, self._on_state),
            *([subscribe(s, self.keys.live_cloud("*"), self._on_live)] if self.follow_live else []),
            subscribe(s, self.keys.report("*"), self._on_report),
        ]

    async def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs = []
        await asyncio.to_thread(close_session, self.session)
        self.session = None

    # ------------------------------------------------------------------ inbound
    def _on_state(self, sample: Any) -> None:
        try:
            st = CellStatus.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            log.warning("hmi_state_malformed")
            return
        self.status = st
        self.status_rx_monotonic = time.monotonic()
        for j in st.jobs():
            if j.state in FINAL_JOB_STATES and j.job_id not in self.ended:
                self.ended.add(j.job_id)
                if self.on_job_end is not None:
                    self.on_job_end(j.job_id)
        self.on_event({"type": "status", "status": st.model_dump(mode="json")})

    def _on_live(self, sample: Any) -> None:
        try:
            chunk = LiveCloudChunk.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        if chunk.job_id != self.live_job:
            self.live_job, self.live_points, self.live_count, self.live_seq = chunk.job_id, [], 0, -1
        if self.live_count < LIVE_KEEP_POINTS:
            if chunk.xyz_mm:
                self.live_points.append(np.asarray(chunk.xyz_mm, np.float32))
                self.live_count += len(chunk.xyz_mm)
            self.live_seq = chunk.seq
        self.live_chunks += 1
        self.on_event({"type": "live", "job_id": chunk.job_id, "seq": chunk.seq, "profiles": chunk.profiles,
                       "xyz_mm": chunk.xyz_mm})  # fmt: skip

    def _on_report(self, sample: Any) -> None:
        try:
            env = ReportEnvelope.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        if self.on_report is not None:
            self.on_report(env)
        verdict = env.report.verdict if env.report else None
        self.on_event({"type": "report", "job_id": env.job_id, "plate_id": env.plate_id, "ok": env.ok,
                       "verdict": verdict, "error": env.error})  # fmt: skip

    def live_cloud(self, job_id: str) -> tuple[list[list[float]], int]:
        """The job's live cloud so far and the sequence number of its last chunk (-1: none); a
        page adds the chunks after that one that reach it meanwhile."""
        if job_id != self.live_job or not self.live_points:
            return [], self.live_seq if job_id == self.live_job else -1
        return np.concatenate(self.live_points).tolist(), self.live_seq

    # ------------------------------------------------------------------ outbound
    async def trigger(self, body: str) -> TriggerAccepted:
        return await call(self.session, self.keys.trigger, body, TriggerAccepted, timeout_s=30.0)

    async def control(self, action: str, body: str) -> ControlReply:
        return await call(self.session, self.keys.control(action), body, ControlReply, timeout_s=30.0)


__all__ = ["LIVE_KEEP_POINTS", "ApiCallError", "CellLink"]
