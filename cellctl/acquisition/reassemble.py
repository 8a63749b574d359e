"""Rebuild a scan's cloud from its raw files, bit for bit the same as the live assembly.

The raw files hold every input of the live pipeline with a job-wide sequence number; replaying them
in that order through a fresh :class:`~cellctl.acquisition.pipeline.Acquisition` repeats every
computation. Two clouds come out of the same files:

* the **live** cloud (``final=False``): the online clock fits as they were while scanning, bit for
  bit what the cell assembled on the fly (the recorded clock fits are compared with the recomputed
  ones: a mismatch means the code or the files changed, and is reported rather than hidden);
* the **final** cloud (``final=True``, the default and what the cell publishes): the lower envelope
  over the whole scan's pairs gives one fit per clock, which then stamps every profile. Early
  profiles no longer depend on the few pairs seen before them, and the drift is estimated over the
  whole span. Deterministic in the files, so ``cellctl reassemble`` reproduces it bit for bit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import structlog

from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.clock_sync import ClockFit, FrameTimeline
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
from cellctl.jobstore.rawstore import RawFormatError, RawReader, ReadReport

__all__ = ["ReassemblyResult", "final_fits", "reassemble"]

log = structlog.get_logger(__name__)


@dataclass
class ReassemblyResult:
    """The rebuilt cloud and how the files looked.

    Attributes:
        cloud: the organised scan.
        settings: the acquisition settings from ``job.json``.
        read: per-stream chunk/record counts and torn tails.
        fits_recorded, fits_matching: clock fits in the files and how many the replay reproduced exactly.
        quality: clock fit reports (of the fits used) and counters of the replay.
        final: whether the whole-scan clock fits were used (see :func:`reassemble`).
        fits: the whole-scan fits used (``sensor``, ``robot``, ``frames``); empty for the live replay.
    """

    cloud: AssembledScan
    settings: AcquisitionSettings
    read: ReadReport
    fits_recorded: int = 0
    fits_matching: int = 0
    quality: dict = field(default_factory=dict)
    final: bool = True
    fits: dict = field(default_factory=dict)


def _replay(records, acq: Acquisition, job_dir) -> list[tuple[str, ClockFit]]:
    recorded = []
    for rec in records:
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
    return recorded


def _clocks_pass(records, settings: AcquisitionSettings, fixed: dict) -> Acquisition:
    acq = Acquisition(settings, clocks_only=True, fixed_fits=fixed)
    if "frames" not in fixed:
        acq._timeline = FrameTimeline(window=2**62)  # every frame of the scan in one regression
    for rec in records:
        a = rec.arrays
        if rec.kind == KIND_ROBOT:
            acq.feed_robot(a["t_host_ns"], a["t_ctrl_us"], a["q_deg"])
        elif rec.kind == KIND_PROFILES:
            acq.feed_profiles(batch_from_arrays(a))
    return acq


def final_fits(records, settings: AcquisitionSettings) -> dict:
    """Clock fits over the whole scan: every pair, one envelope per clock (the scan's best estimate);
    with the ms counter first the frame-time regression over every frame, which then defines the
    sensor times the envelope is fitted to."""
    whole = replace(
        settings,
        sensor_sync_config=replace(settings.sensor_sync_config, window_s=1e9),
        robot_sync_config=replace(settings.robot_sync_config, window_s=1e9),
    )
    fits: dict = {}
    if settings.sensor_clock == "ms":
        line = _clocks_pass(records, whole, {})._timeline.line()
        if line is not None:
            fits["frames"] = line
    acq = _clocks_pass(records, whole, dict(fits))
    for name, sync in (("sensor", acq.sensor_sync), ("robot", acq.robot_sync)):
        fit = sync.refit_now()
        if fit is not None:
            fits[name] = fit
    return fits


def reassemble(job_dir: str | Path, overrides: dict | None = None, *, final: bool = True) -> ReassemblyResult:
    """Rebuild a job's cloud from its raw files.

    Args:
        job_dir: the job directory (``job.json`` and the ``*.craw`` files).
        overrides: acquisition settings to change for this replay (for example a calibrated
            ``latency_ms`` or hand-eye, or ``sensor_sync="none"`` to see what synchronisation buys).
        final: True (the scan's cloud): clock fits over the whole scan, computed first, stamp every
            profile; this is what the cell publishes and it is deterministic in the raw files. False:
            repeat the live pipeline exactly (online fits, as the profiles arrived), bit for bit the
            cloud assembled while scanning.

    Raises:
        RawFormatError: not a job directory, or a record that cannot be interpreted.
    """
    job_dir = Path(job_dir)
    if not (job_dir / "profiles.craw").exists() and (job_dir / "raw" / "profiles.craw").exists():
        job_dir = job_dir / "raw"  # the daemon's job directory stands for its raw/ directory
    reader = RawReader(job_dir)
    if not isinstance(reader.meta.get("acquisition"), dict):
        raise RawFormatError(
            f"{job_dir / 'job.json'}: no 'acquisition' settings: not the raw directory of a scan"
        )
    settings = AcquisitionSettings.from_json({**reader.meta["acquisition"], **(overrides or {})})
    records = reader.records()
    fixed = final_fits(records, settings) if final else {}
    # the scan's per-point arrays in a file beside the raw ones (a 6 m plate's 2.2 GB out of memory)
    # (in memory when the directory is read-only: an archived job)
    spill = job_dir if os.access(job_dir, os.W_OK) else False
    acq = Acquisition(settings, writer=None, fixed_fits=fixed, spill_dir=spill)
    recorded = _replay(records, acq, job_dir)
    acq.finish()
    matching = sum(1 for r, m in zip(recorded, acq.fits, strict=False) if r == m)
    if matching != len(recorded) and not overrides:
        log.warning("reassemble_fit_mismatch", job=str(job_dir), recorded=len(recorded), matching=matching)
    quality = acq.quality()
    for name, fit in fixed.items():
        if isinstance(fit, ClockFit):
            quality[f"{name}_clock"] = fit.report()
    return ReassemblyResult(
        cloud=acq.cloud(),
        settings=settings,
        read=reader.report,
        fits_recorded=len(recorded),
        fits_matching=matching,
        quality=quality,
        final=final,
        fits=fixed,
    )
