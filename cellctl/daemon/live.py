"""The live cloud for displays: a thinned stream of the points a scan assembles (``Keys.live_cloud``).

Every ``profile_step``-th profile, ``points_per_profile`` points along its line, flushed at most every
``period_s`` as one :class:`~cellctl.api.LiveCloudChunk`. Published with the default congestion
control (DROP): a slow display loses chunks, it never holds up the scan.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import structlog

from cellctl.api import LiveCloudChunk

log = structlog.get_logger(__name__)


class LiveCloudFeed:
    """Collects assembled batches of one job and puts them, thinned, every ``period_s``."""

    def __init__(
        self,
        session: Any,
        key: str,
        job_id: str,
        *,
        rate_hz: float,
        profiles_per_s: float = 20.0,
        points_per_profile: int = 32,
        period_s: float = 0.5,
    ) -> None:
        self.session = session
        self.key = key
        self.job_id = job_id
        self.profile_step = max(1, round(rate_hz / profiles_per_s))
        self.points_per_profile = points_per_profile
        self.period_s = period_s
        self.seq = 0
        self._parts: list[np.ndarray] = []
        self._last = time.monotonic()

    def add(self, batches: list[Any], profiles: int) -> None:
        """Assembled batches (``AssembledBatch``) just made; ``profiles``: the scan's count so far."""
        for ab in batches:
            rows = np.nonzero(ab.profile_index % self.profile_step == 0)[0]
            if not rows.size:
                continue
            w = ab.xyz_mm.shape[1]
            cols = np.arange(0, w, max(1, w // self.points_per_profile))
            xyz = ab.xyz_mm[rows][:, cols].reshape(-1, 3)
            ok = ab.valid[rows][:, cols].reshape(-1)
            self._parts.append(xyz[ok])
        if time.monotonic() - self._last >= self.period_s:
            self.flush(profiles)

    def flush(self, profiles: int) -> None:
        self._last = time.monotonic()
        pts = np.concatenate(self._parts) if self._parts else np.empty((0, 3), np.float32)
        self._parts.clear()
        chunk = LiveCloudChunk(
            job_id=self.job_id, seq=self.seq, profiles=profiles, xyz_mm=np.round(pts, 1).tolist()
        )
        self.seq += 1
        try:
            self.session.put(self.key, chunk.model_dump_json(), encoding="application/json")
        except Exception as exc:  # a display stream: never let it disturb the scan
            log.warning("live_cloud_put_failed", error=str(exc))
