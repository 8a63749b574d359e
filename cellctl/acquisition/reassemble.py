"""Rebuild a scan's cloud from its raw files, bit for bit the same as the live assembly.

The raw files hold every input of the live pipeline with a job-wide sequence number; replaying them
in that order through a fresh :class:`~cellctl.acquisition.pipeline.Acquisition` repeats every
computation. The recorded clock fits are compared with the recomputed ones: a mismatch means the
code or the files changed, and is reported rather than hidden.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import structlog

from cellctl.acquisition.assembly import ScanCloud
from cellctl.acquisition.pipeline import (
    KIND_CLOCK_FIT,
    KIND_PASS_BEGIN,
    KIND_PASS_END,
    KIND_PROFILES,
    KIND_ROBOT,
    Acquisition,
    AcquisitionSettings,
    batch_from_arrays,
    fit_from_arrays,
)
from cellctl.acquisition.rawstore import RawFormatError, RawReader, ReadReport

__all__ = ["ReassemblyResult", "reassemble"]

log = structlog.get_logger(__name__)


@dataclass
class ReassemblyResult:
    """The rebuilt cloud and how the files looked.

    Attributes:
        cloud: the organised scan.
        settings: the acquisition settings from ``job.json``.
        read: per-stream chunk/record counts and torn tails.
        fits_recorded, fits_matching: clock fits in the files and how many the replay reproduced exactly.
        quality: clock fit reports and counters of the replay.
    """

    cloud: ScanCloud
    settings: AcquisitionSettings
    read: ReadReport
    fits_recorded: int = 0
    fits_matching: int = 0
    quality: dict = field(default_factory=dict)


def reassemble(job_dir: str | Path) -> ReassemblyResult:
    """Replay a job's raw files into a cloud.

    Raises:
        RawFormatError: not a job directory, or a record that cannot be interpreted.
    """
    reader = RawReader(job_dir)
    settings = AcquisitionSettings.from_json(reader.meta["acquisition"])
    acq = Acquisition(settings, writer=None)
    recorded = []
    for rec in reader.records():
        a = rec.arrays
        if rec.kind == KIND_ROBOT:
            acq.feed_robot(a["t_host_ns"], a["t_ctrl_us"], a["q_deg"])
        elif rec.kind == KIND_PROFILES:
            acq.feed_profiles(batch_from_arrays(a))
        elif rec.kind == KIND_PASS_BEGIN:
            acq.begin_pass(int(a["pass_id"]), int(a["t_ns"]))
        elif rec.kind == KIND_PASS_END:
            acq.end_pass(int(a["t_ns"]))
        elif rec.kind == KIND_CLOCK_FIT:
            recorded.append(fit_from_arrays(a))
        else:
            raise RawFormatError(f"{job_dir}: record {rec.seq} in {rec.stream} has unknown kind {rec.kind}")
    acq.finish()
    matching = sum(1 for r, m in zip(recorded, acq.fits, strict=False) if r == m)
    if matching != len(recorded):
        log.warning("reassemble_fit_mismatch", job=str(job_dir), recorded=len(recorded), matching=matching)
    return ReassemblyResult(
        cloud=acq.cloud(),
        settings=settings,
        read=reader.report,
        fits_recorded=len(recorded),
        fits_matching=matching,
        quality=acq.quality(),
    )
