"""A job the daemon is running: its live objects (the motion execution, the acquisition session, the
task, the live cloud) beside its record (:class:`~cellctl.jobstore.jobs.JobRecord`), which the job
store keeps."""

from __future__ import annotations

import asyncio

from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.session import AcquisitionSession
from cellctl.api.models import MotionCounters
from cellctl.jobstore.jobs import JobRecord
from cellctl.motion.link import RemoteExecution


class ActiveJob:
    """A job the daemon is running (queued, scanning or analysing): its live objects beside its record."""

    def __init__(self, record: JobRecord) -> None:
        self.record = record
        self.executor: RemoteExecution | None = None
        self.motion: MotionCounters | None = None  # the motion process's counters of this job
        self.profiles = 0
        self.points = 0
        self.fraction = 0.0
        self.stage = "queued"
        self.worker_id: str | None = None
        self.stop_reason: str | None = None  # "shutdown", "abort" or "disk"
        self.cloud: AssembledScan | None = None  # the live cloud of a finished scan, until published
        self.task: asyncio.Task[None] | None = None
        self.session: AcquisitionSession | None = None  # while the scan acquires
