"""Time-offset calibration: the latency that makes back-and-forth passes agree.

A timing error ``delta`` moves every point by the sensor's velocity times ``delta``: along the pass
direction, so its sign flips between forward and backward passes, and its size grows with the speed
(line-laser-and-sync.md sections 3.1 and 3.5). Over a surface that slopes along the passes this
shows as a height difference between the passes. For a height field sampled on a grid:

    z_p(x, y) = h(x, y) - a_p(x, y) * delta,   a_p = grad h . v_p,xy - v_p,z

for every pass ``p`` covering a cell (``v_p`` its mean sensor velocity there). Removing each cell's
common height by centring leaves one linear least-squares problem in ``delta``. The result is added
to the ``latency_ms`` the scan was assembled with, and the scan is re-assembled and re-estimated once
so the linearisation error vanishes. Several speeds make the estimate well conditioned and let the
report show that the residual no longer grows with speed.

Works on any organised cloud from :mod:`cellctl.acquisition` (per-profile times, pass ids); the scan
is the ``cellctl calibrate time-offset`` job: passes over a plane tilted along the passes, a sphere,
or a curved plate, at several speeds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.reassemble import reassemble

__all__ = ["TimeOffsetError", "TimeOffsetResult", "calibrate_time_offset", "estimate_time_offset"]


class TimeOffsetError(ValueError):
    """The scan cannot determine a time offset (too few passes, no overlap, no slope)."""


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """One linear estimate: ``delta_ms`` to add to the latency, its standard error, the height
    disagreement between passes before and after (RMS over overlapping cells, mm), cells used."""

    delta_ms: float
    std_ms: float
    disagreement_before_mm: float
    disagreement_after_mm: float
    cells: int
    per_speed_delta_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class TimeOffsetResult:
    """Calibrated ``latency_ms`` (cell.toml ``[laser] latency_ms``) with its residual report."""

    latency_ms: float
    std_ms: float
    start_latency_ms: float
    iterations: list[TimeOffsetEstimate]

    def report(self) -> dict:
        """Plain numbers for the console and the calibration record."""
        last = self.iterations[-1]
        return {
            "latency_ms": self.latency_ms,
            "std_ms": self.std_ms,
            "start_latency_ms": self.start_latency_ms,
            "disagreement_before_mm": self.iterations[0].disagreement_before_mm,
            "disagreement_after_mm": last.disagreement_after_mm,
            "cells": last.cells,
            "per_speed_residual_ms": last.per_speed_delta_ms,
        }


def _profile_velocity(cloud: AssembledScan) -> tuple[np.ndarray, np.ndarray]:
    """Sensor velocity (n, 3) mm/s at each profile, and its speed class (mm/s rounded to 50)."""
    n_ok = np.isfinite(cloud.sensor_pos_mm).all(axis=1)
    c = cloud.sensor_pos_mm.astype(np.float64)
    t = cloud.t_ns.astype(np.float64) * 1e-9
    v = np.zeros_like(c, dtype=np.float64)
    for pid in np.unique(cloud.pass_id[cloud.pass_id >= 0]):
        idx = np.flatnonzero((cloud.pass_id == pid) & (n_ok > 0))
        if len(idx) >= 3:
            v[idx] = np.gradient(c[idx].astype(np.float64), t[idx], axis=0)
    speed = np.linalg.norm(v[:, :2], axis=1)
    return v, np.round(speed / 50.0) * 50.0


def estimate_time_offset(
    cloud: AssembledScan, *, cell_mm: float = 2.0, min_speed_mm_s: float = 5.0, trim_mm: float = 0.5
) -> TimeOffsetEstimate:
    """Linear estimate of the timing error of an organised scan (see the module docstring).

    Args:
        cloud: the scan; profiles with ``pass_id >= 0`` take part.
        cell_mm: grid cell size of the height field (base frame x-y).
        min_speed_mm_s: profiles slower than this (ramps) are left out.
        trim_mm: cells whose passes disagree by more than this are outliers (edges, spikes) and dropped.

    Returns:
        The estimate; ``delta_ms`` is to be *added* to the latency the cloud was assembled with.
    """
    v, speed_class = _profile_velocity(cloud)
    prof_ok = (cloud.pass_id >= 0) & (np.linalg.norm(v[:, :2], axis=1) >= min_speed_mm_s)
    r, col = np.nonzero(cloud.valid & prof_ok[:, None])
    if len(r) == 0:
        raise TimeOffsetError("no valid points in passes moving faster than min_speed_mm_s")
    p = cloud.xyz_mm[r, col].astype(np.float64)
    pid = cloud.pass_id[r].astype(np.int64)
    vel = v[r]
    ij = np.floor(p[:, :2] / cell_mm).astype(np.int64)
    ij -= ij.min(axis=0)
    nx, ny = ij.max(axis=0) + 1
    cell = ij[:, 0] * ny + ij[:, 1]
    # mean height per cell over all passes -> gradient of the surface on the grid
    ncell = nx * ny
    cnt = np.bincount(cell, minlength=ncell)
    zc = np.bincount(cell, p[:, 2], ncell) / np.maximum(cnt, 1)
    zc_grid = np.where(cnt > 0, zc, np.nan).reshape(nx, ny)
    gx, gy = np.gradient(zc_grid, cell_mm)
    # per (cell, pass) means
    key = cell * (int(pid.max()) + 1) + pid
    ukey, inv, kcnt = np.unique(key, return_inverse=True, return_counts=True)
    z_cp = np.bincount(inv, p[:, 2]) / kcnt
    v_cp = np.stack([np.bincount(inv, vel[:, k]) / kcnt for k in range(3)], axis=1)
    sp_cp = np.bincount(inv, speed_class[r]) / kcnt
    c_cp = ukey // (int(pid.max()) + 1)
    g = np.stack([gx.ravel()[c_cp], gy.ravel()[c_cp]], axis=1)
    a_cp = g[:, 0] * v_cp[:, 0] + g[:, 1] * v_cp[:, 1] - v_cp[:, 2]
    ok = np.isfinite(a_cp) & (kcnt >= 2)
    # keep cells seen by at least two passes
    n_pass_in_cell = np.bincount(c_cp[ok], minlength=ncell)
    ok &= n_pass_in_cell[c_cp] >= 2
    if ok.sum() < 10:
        raise TimeOffsetError("fewer than 10 grid cells are covered by two passes: the passes must overlap")
    c_ok, z_ok, a_ok, sp_ok = c_cp[ok], z_cp[ok], a_cp[ok], sp_cp[ok]
    cnt_c = np.bincount(c_ok, minlength=ncell)
    zc_m = (np.bincount(c_ok, z_ok, ncell) / np.maximum(cnt_c, 1))[c_ok]
    ac_m = (np.bincount(c_ok, a_ok, ncell) / np.maximum(cnt_c, 1))[c_ok]
    dz, da = z_ok - zc_m, a_ok - ac_m
    keep = np.abs(dz) < trim_mm
    dz, da, sp_ok = dz[keep], da[keep], sp_ok[keep]
    denom = float(np.dot(da, da))
    if denom <= 0:
        raise TimeOffsetError("the surface has no slope along the passes: a timing error does not show")
    # z_p = h - a_p * delta  ->  dz = -da * delta
    delta_s = -float(np.dot(da, dz)) / denom
    resid = dz + da * delta_s
    dof = max(len(dz) - 1, 1)
    std_s = float(np.sqrt(np.dot(resid, resid) / dof / denom))
    per_speed = {}
    for s in np.unique(sp_ok):
        m = sp_ok == s
        dm = float(np.dot(da[m], da[m]))
        if dm > 0 and m.sum() >= 100:
            per_speed[f"{s:.0f}"] = float(-np.dot(da[m], resid[m]) / dm) * 1e3
    return TimeOffsetEstimate(
        delta_ms=delta_s * 1e3,
        std_ms=std_s * 1e3,
        disagreement_before_mm=float(np.sqrt(np.mean(dz**2))),
        disagreement_after_mm=float(np.sqrt(np.mean(resid**2))),
        cells=len(np.unique(c_ok[keep])),
        per_speed_delta_ms=per_speed,
    )


def calibrate_time_offset(
    job_dir: str | Path, *, iterations: int = 2, cell_mm: float = 2.0
) -> TimeOffsetResult:
    """Calibrate ``latency_ms`` from a back-and-forth scan's raw files.

    Re-assembles the job (whole-scan clock fits) with the current latency estimate, estimates the
    remaining timing error, and repeats ``iterations`` times.
    """
    base = reassemble(job_dir)
    latency = base.settings.latency_ms
    start = latency
    est: list[TimeOffsetEstimate] = []
    cloud = base.cloud
    for i in range(iterations):
        e = estimate_time_offset(cloud, cell_mm=cell_mm)
        est.append(e)
        latency += e.delta_ms
        if i + 1 < iterations:
            cloud = reassemble(job_dir, {"latency_ms": latency}).cloud
    return TimeOffsetResult(latency_ms=latency, std_ms=est[-1].std_ms, start_latency_ms=start, iterations=est)
