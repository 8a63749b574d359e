"""The cell's Zenoh key space (docs/api.md): every key expression, built from the cell's prefix.

Everything lives under ``CellConfig.key_prefix`` (default ``cell/<cell_id>``); the payload models
each key carries are in :mod:`cellctl.api.models`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: the daemon's control queryables (``Keys.control``)
ControlAction = Literal["pause", "resume", "abort", "reset", "reanalyse"]
CONTROL_ACTIONS: tuple[str, ...] = ("pause", "resume", "abort", "reset", "reanalyse")


@dataclass(frozen=True)
class Keys:
    """The key expressions of one cell, built from its prefix (``CellConfig.key_prefix``)."""

    prefix: str

    # daemon side
    @property
    def trigger(self) -> str:
        """Queryable: JSON TriggerRequest in, TriggerAccepted or ApiError out."""
        return f"{self.prefix}/scan/trigger"

    def control(self, action: ControlAction) -> str:
        """Queryable: empty payload (or ControlRequest JSON), ControlReply or ApiError out."""
        return f"{self.prefix}/control/{action}"

    @property
    def state(self) -> str:
        """Publication: CellStatus JSON, on every change and periodically."""
        return f"{self.prefix}/state"

    @property
    def stats(self) -> str:
        """Queryable: empty in, DaemonStats JSON out."""
        return f"{self.prefix}/stats"

    @property
    def daemon_alive(self) -> str:
        """Liveliness token of the daemon."""
        return f"{self.prefix}/alive/daemon"

    # workers
    def worker_alive(self, worker_id: str = "*") -> str:
        """Liveliness token of one worker (``*``: all of them)."""
        return f"{self.prefix}/alive/workers/{worker_id}"

    def worker_info(self, worker_id: str = "*") -> str:
        """Queryable on each worker: WorkerAnnouncement JSON."""
        return f"{self.prefix}/workers/{worker_id}/info"

    def worker_job(self, worker_id: str, job_id: str = "*") -> str:
        """Publication to one worker: the cloud (binary) with the JobSpec JSON as attachment."""
        return f"{self.prefix}/workers/{worker_id}/jobs/{job_id}"

    def worker_stream(
        self, worker_id: str, job_id: str = "*", attempt: int | str = "*", seq: int | str = "*"
    ) -> str:
        """Publication to one worker: one chunk of a streamed job's cloud (binary, StreamChunk
        attachment), for one attempt."""
        return f"{self.prefix}/workers/{worker_id}/stream/{job_id}/{attempt}/{seq}"

    def worker_stream_end(self, worker_id: str, job_id: str = "*", attempt: int | str = "*") -> str:
        """Publication to one worker: StreamEnd JSON, the streamed cloud is complete."""
        return f"{self.prefix}/workers/{worker_id}/stream/{job_id}/{attempt}/end"

    def job_cloud(self, job_id: str = "*") -> str:
        """Queryable on the daemon: a streamed job's whole cloud (binary), for a worker missing a chunk."""
        return f"{self.prefix}/jobs/{job_id}/cloud"

    def worker_cancel(self, worker_id: str, job_id: str = "*") -> str:
        """Publication to one worker: stop analysing this job (it was given to another worker)."""
        return f"{self.prefix}/workers/{worker_id}/cancel/{job_id}"

    # jobs
    def job_event(self, job_id: str = "*") -> str:
        """Publication by the worker holding a job: JobEvent JSON (accepted, heartbeat, done, ...)."""
        return f"{self.prefix}/jobs/{job_id}/event"

    def live_cloud(self, job_id: str = "*") -> str:
        """Publication by the daemon during a scan: LiveCloudChunk JSON (thinned points, for displays)."""
        return f"{self.prefix}/jobs/{job_id}/live"

    def report(self, job_id: str = "*") -> str:
        """Publication: ReportEnvelope JSON (large, CongestionControl.BLOCK)."""
        return f"{self.prefix}/reports/{job_id}"

    # transfers (cellctl.api.transfer)
    def design(self, sha256: str = "*") -> str:
        """Queryable on the daemon: a design's bytes by SHA-256 (of the jobs it submitted)."""
        return f"{self.prefix}/designs/{sha256}"

    def result_chunk(self, job_id: str = "*", attempt: int | str = "*", index: int | str = "*") -> str:
        """Publication by the worker: one chunk of a job's result bundle (ResultChunk attachment)."""
        return f"{self.prefix}/results/{job_id}/{attempt}/{index}"

    @staticmethod
    def last_chunk(key: str) -> str:
        """The last chunk of a key expression (the job id of a job/report key, a worker id, ...)."""
        return str(key).rsplit("/", 1)[-1]
