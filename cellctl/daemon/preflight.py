"""Pre-flight of the data directory: writable, and room for the planned scan's raw data, before motion.

A scan whose raw files cannot be written is worse than no scan: the arm would sweep the plate and
the profiles would be lost. So the daemon checks, before the EGM program starts, that

* the jobs directory accepts a new file (a real write + fsync + unlink of a small probe, because a
  read-only mount, a full disk or a quota show up only when bytes are written), and
* the free space (``statvfs``, what an unprivileged writer may use) covers the scan's raw-data
  estimate plus the ``[daemon] min_free_mb`` margin.

The estimate is deliberately pessimistic: every profile stored with its own x row (the uniform-row
saving of the raw format ignored), the sensor streaming for the whole scan plus the settle time,
times a safety factor for pauses and slower-than-planned execution.
"""

from __future__ import annotations

import contextlib
import errno
import os
from dataclasses import dataclass
from pathlib import Path

import structlog

log = structlog.get_logger(__name__)

#: stored bytes per profile point, worst case: float32 x + float32 z + one valid bit
_BYTES_PER_POINT = 8.125
#: per-profile scalars (frame index, times, encoder, status, exposure, host stamp), the array table
#: and record framing (measured: 3.87 kB a 500-point profile stored one per record; this gives 4.3 kB)
_BYTES_PER_PROFILE = 256
#: one joint-feedback sample (host ns, controller us, 6 joints + spare axes as float64) and framing
_BYTES_PER_FEEDBACK = 128
#: the spilled scan's bytes a point (float32 xyz, bool valid) and a published point's on the wire
_SPILL_BYTES_PER_POINT = 13
_PUBLISHED_BYTES_PER_POINT = 28
_PROBE_BYTES = 4096


class PreflightError(Exception):
    """The data directory cannot take the planned scan; names the directory, what failed and by how much.

    ``field`` is the configuration key to look at (``cell.data_dir`` or ``daemon.min_free_mb``).
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


@dataclass(frozen=True)
class RawEstimate:
    """Raw-data estimate of one scan: ``profiles`` expected and ``bytes`` on disk (pessimistic)."""

    profiles: int
    bytes: int


@dataclass(frozen=True)
class DiskCheck:
    """What the pre-flight found: ``free_bytes`` usable in ``data_dir``, ``need_bytes`` (estimate + margin)."""

    data_dir: str
    free_bytes: int
    need_bytes: int
    estimate_bytes: int

    def to_json(self) -> dict[str, float | str]:
        """For the job record: sizes in MB."""
        return {
            "data_dir": self.data_dir,
            "free_mb": round(self.free_bytes / 1e6, 1),
            "need_mb": round(self.need_bytes / 1e6, 1),
            "estimate_mb": round(self.estimate_bytes / 1e6, 1),
        }


def raw_bytes_estimate(
    scan_time_s: float,
    *,
    rate_hz: float,
    points_per_profile: int,
    settle_s: float = 0.0,
    egm_rate_hz: float = 250.0,
    safety: float = 1.5,
) -> RawEstimate:
    """Pessimistic raw-data size of a scan.

    Args:
        scan_time_s: planned execution time of the scan, s (``plan.scan_time_s``).
        rate_hz: profile rate of the sensor, Hz. points_per_profile: points per profile.
        settle_s: sensor streaming before the arm moves, s. egm_rate_hz: joint feedback rate, Hz.
        safety: factor for pauses and execution slower than planned (>= 1).
    """
    if not (scan_time_s >= 0 and rate_hz > 0 and points_per_profile > 0 and safety >= 1):
        raise ValueError(
            f"raw_bytes_estimate: scan_time_s={scan_time_s}, rate_hz={rate_hz}, "
            f"points_per_profile={points_per_profile}, safety={safety} out of range"
        )
    t_s = (scan_time_s + settle_s) * safety
    profiles = int(t_s * rate_hz) + 1
    per_profile = _BYTES_PER_PROFILE + _BYTES_PER_POINT * points_per_profile
    total = profiles * per_profile + t_s * egm_rate_hz * _BYTES_PER_FEEDBACK
    return RawEstimate(profiles=profiles, bytes=int(total))


def expected_profiles(scan_time_s: float, *, rate_hz: float, settle_s: float = 0.0) -> int:
    """Profiles the acquisition reserves its whole-scan arrays for: the plan's time, the settle and
    10 s of margin at the sensor's rate, and a tenth more."""
    return round((scan_time_s + settle_s + 10.0) * rate_hz * 1.1)


def spill_bytes_estimate(profiles: int, *, points_per_profile: int, publish_step: int) -> int:
    """Disk the daemon's spill files take while a scan is acquired and published (issue 42,
    :mod:`cellctl.acquisition.spill`): the scan's ``xyz_mm`` float32 and ``valid`` (13 bytes a point,
    reserved for ``profiles`` at the start) and its streamed chunks (28 bytes a published point,
    every ``publish_step``-th point). Taken out of the free space the raw files need: the reserve is
    allocated when the scan starts."""
    points = profiles * points_per_profile
    return int(points * _SPILL_BYTES_PER_POINT + points * _PUBLISHED_BYTES_PER_POINT / max(publish_step, 1))


def probe_writable(directory: str | Path) -> None:
    """Write, fsync and remove a small probe file in ``directory`` (created if missing).

    Raises PreflightError naming the directory and the OS error (read-only, full, permission).
    """
    d = Path(directory)
    probe = d / f".preflight-{os.getpid()}"
    try:
        d.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, b"\0" * _PROBE_BYTES)
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        what = {
            errno.EROFS: "is on a read-only file system",
            errno.ENOSPC: "is full",
            errno.EDQUOT: "is over its quota",
            errno.EACCES: "is not writable by this process",
            errno.EPERM: "is not writable by this process",
            errno.EFBIG: "refuses writes (file size limit)",
        }.get(exc.errno or 0, "cannot be written")
        raise PreflightError("cell.data_dir", f"{d} {what} ({exc.strerror or exc})") from None
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()


def free_bytes(directory: str | Path) -> int:
    """Bytes an unprivileged writer may still use on ``directory``'s file system."""
    st = os.statvfs(directory)
    return int(st.f_bavail) * int(st.f_frsize)


def check_data_dir(directory: str | Path, estimate_bytes: int, min_free_mb: float) -> DiskCheck:
    """The whole pre-flight: writable, and free space >= ``estimate_bytes`` + ``min_free_mb``.

    Returns the DiskCheck; raises PreflightError before any motion when the scan would not fit.
    """
    probe_writable(directory)
    free = free_bytes(directory)
    need = int(estimate_bytes + min_free_mb * 1e6)
    check = DiskCheck(str(directory), free, need, int(estimate_bytes))
    if free < need:
        raise PreflightError(
            "daemon.min_free_mb",
            f"{directory} has {free / 1e6:.1f} MB free; the scan needs {need / 1e6:.1f} MB "
            f"(raw data estimate {estimate_bytes / 1e6:.1f} MB + min_free_mb {min_free_mb:g} MB)",
        )
    log.info("preflight_ok", **check.to_json())
    return check
