"""Small real analysis callables for the worker tests (imported by dotted path in the worker's child)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np


def centroid_after_sleep(cloud: dict[str, np.ndarray], job: dict[str, Any]) -> dict[str, Any]:
    """Record the call, sleep ``job['sleep_s']``, return the cloud's point count and centroid (mm)."""
    record = job.get("record_path")
    if record:
        with Path(record).open("a") as f:
            f.write(f"start {job['job_id']} {os.getpid()}\n")
    time.sleep(float(job.get("sleep_s", 0.0)))
    xyz = cloud["xyz_mm"].astype(np.float64)
    out = {
        "job_id": job["job_id"],
        "plate_id": job["plate_id"],
        "n_points": xyz.shape[0],
        "centroid_mm": xyz.mean(axis=0),
        "passes": np.unique(cloud["pass_id"]) if "pass_id" in cloud else [],
        "pid": os.getpid(),
    }
    if record:
        with Path(record).open("a") as f:
            f.write(f"done {job['job_id']} {os.getpid()}\n")
    return out


def always_raises(cloud: dict[str, np.ndarray], job: dict[str, Any]) -> dict[str, Any]:
    """An analysis that fails on its input, deterministically."""
    raise ValueError(f"plate {job['plate_id']}: no plate surface in {cloud['xyz_mm'].shape[0]} points")


def blas_environment(cloud: dict[str, np.ndarray], job: dict[str, Any]) -> dict[str, Any]:
    """The BLAS thread settings the analysis process runs with."""
    return {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
