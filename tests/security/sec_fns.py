"""A small real analysis callable for the worker started by the security tests (imported by dotted path)."""

from __future__ import annotations

from typing import Any

import numpy as np


def point_count(cloud: dict[str, np.ndarray], job: dict[str, Any]) -> dict[str, Any]:
    """The cloud's point count and centroid (mm): enough to prove the job went round trip."""
    xyz = cloud["xyz_mm"].astype(np.float64)
    return {"job_id": job["job_id"], "n_points": int(xyz.shape[0]), "centroid_mm": xyz.mean(axis=0).tolist()}
