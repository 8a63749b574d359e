"""Small real analysis callables for the worker tests (imported by dotted path in the worker's child).

They take the typed job like the product's analysis: what a test wants them to do (sleep, record
the call) comes in the job's ``design`` file (JSON), what they saw of the cloud goes to
``observed.json`` in the job's ``out_dir``, and what they return is a schema-valid Report.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from analysis.cloud_io import ScanCloud
from analysis.contracts.job import AnalysisJob, Report
from analysis.pipeline import CloudStream, analyse_job


def behaviour(job: AnalysisJob) -> dict[str, Any]:
    """The test's instructions for this job (the design file's JSON; none when it does not exist)."""
    path = Path(job.design)
    return json.loads(path.read_text()) if path.is_file() else {}


def observe(job: AnalysisJob, **seen: Any) -> None:
    """Write what the analysis saw to ``<out_dir>/observed.json`` (a test reads it back)."""
    if job.out_dir:
        out = Path(job.out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "observed.json").write_text(json.dumps(seen))


def minimal_report(job: AnalysisJob, points: int) -> Report:
    """A report that fits the schema and judges no line (so it fails): the ids, the inputs, zeros."""
    zero4 = [[0.0] * 4 for _ in range(4)]
    return Report.model_validate(
        {
            "plate_id": job.plate_id, "job_id": job.job_id, "cell_id": job.cell_id, "verdict": "fail",
            "registration": {
                "coarse_rms_mm": 0.0, "icp_rms_mm": 0.0, "nonpen_rms_mm": 0.0, "penetration_points": 0,
                "penetration_points_before": 0, "surface_points": 0, "surface_cell_mm": 0.0,
                "raw_points_below_4sigma": 0, "transform": zero4, "corner_shift": 0,
            },
            "corners_mm": [[0.0] * 3 for _ in range(4)], "plate_size_mm": [0.0, 0.0], "lines": [],
            "tolerances": {}, "coverage": {"fraction": 0.0, "holes_mm2": 0.0},
            "surface": {"points": 0, "noise_sigma_mm": 0.0},
            "inputs": {"points": points, "design": job.design, "placement": job.placement},
        }
    )  # fmt: skip


def centroid_after_sleep(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """Record the call, sleep ``sleep_s``, observe the cloud's point count, centroid (mm) and passes."""
    todo = behaviour(job)
    record = todo.get("record_path")
    if record:
        with Path(record).open("a") as f:
            f.write(f"start {job.job_id} {os.getpid()}\n")
    time.sleep(float(todo.get("sleep_s", 0.0)))  # stays: the analysis's duration is what a test sets
    gate = todo.get("gate_path")  # held until the test opens the gate (writes the file)
    while gate and not Path(gate).exists():
        time.sleep(0.02)  # stays: the poll of a wait on the gate file (an event), in the worker's child
    xyz = cloud.xyz_mm
    passes = np.unique(cloud.pass_id).tolist() if cloud.organised else []
    observe(job, job_id=job.job_id, n_points=xyz.shape[0], centroid_mm=xyz.mean(axis=0).tolist(),
            passes=passes, pid=os.getpid())  # fmt: skip
    if record:
        with Path(record).open("a") as f:
            f.write(f"done {job.job_id} {os.getpid()}\n")
    return minimal_report(job, xyz.shape[0])


def always_raises(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """An analysis that fails on its input, deterministically."""
    raise ValueError(f"plate {job.plate_id}: no plate surface in {len(cloud)} points")


def not_a_report(cloud: ScanCloud, job: AnalysisJob) -> dict[str, Any]:
    """An analysis whose result does not fit the report schema (an unknown field, no verdict)."""
    return {"job_id": job.job_id, "n_points": len(cloud)}


def _numpy_openblas_threads() -> int | None:
    """The threads numpy's own OpenBLAS (loaded with numpy, before any analysis code) will use: asked
    of the library itself through its exported getter; None when numpy carries no OpenBLAS."""
    import ctypes

    with open("/proc/self/maps") as maps:
        paths = {line.split()[-1] for line in maps if "openblas" in line and line.rstrip().endswith(".so")}
    for path in sorted(paths):
        lib = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_"):
            getter = getattr(lib, name, None)
            if getter is not None:
                return int(getter())
    return None


def blas_environment(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """Observe the BLAS thread settings the analysis process runs with, and what numpy's OpenBLAS
    took from them."""
    observe(
        job,
        **{k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")},
        numpy_openblas_threads=_numpy_openblas_threads(),
    )
    return minimal_report(job, len(cloud))


class _CentroidStream:
    """The stream of :func:`centroid_streamed`: the chunks kept; ``ahead`` makes the result early and
    keeps it while no later chunk adds a point (as :class:`analysis.pipeline.CloudStream` does)."""

    def __init__(self, job: AnalysisJob) -> None:
        self.job = job
        self.clouds: list[ScanCloud] = []
        self.ahead_points: int | None = None
        self.kept: Report | None = None

    @property
    def points(self) -> int:
        return sum(len(c) for c in self.clouds)

    def add(self, cloud: ScanCloud) -> None:
        self.clouds.append(cloud)
        if len(cloud):
            self.kept = None

    def _result(self, **seen: Any) -> Report:
        xyz = np.concatenate([c.xyz_mm for c in self.clouds])
        passes = sorted({int(p) for c in self.clouds if c.organised for p in np.unique(c.pass_id)})
        observe(self.job, job_id=self.job.job_id, n_points=xyz.shape[0], centroid_mm=xyz.mean(axis=0).tolist(),
                passes=passes, ahead_points=self.ahead_points, **seen)  # fmt: skip
        return minimal_report(self.job, xyz.shape[0])

    def ahead(self) -> None:
        self.ahead_points = self.points
        if self.job.out_dir:  # the test waits on this file: the early result is being made
            Path(self.job.out_dir).mkdir(parents=True, exist_ok=True)
            (Path(self.job.out_dir) / "ahead_started").write_text(str(self.ahead_points))
        time.sleep(
            float(behaviour(self.job).get("ahead_sleep_s", 0.0))
        )  # stays: a slow early result, set by the test
        self.kept = self._result(made="ahead")

    def finish(self) -> Report:
        if self.kept is not None:
            return self.kept
        return self._result(made="finish")


def centroid_streamed(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """:func:`centroid_after_sleep` for a whole cloud; a streamed one goes through its ``stream``."""
    return centroid_after_sleep(cloud, job)


centroid_streamed.stream = _CentroidStream  # type: ignore[attr-defined]


#: how long :func:`product_analysis_held` holds a job before the product's analysis runs
HOLD_S = 60.0


class _HeldCloudStream(CloudStream):
    """The product's streamed analysis, held :data:`HOLD_S` at its end (and none made ahead of it)."""

    def ahead(self) -> None:
        return None

    def finish(self) -> dict[str, Any]:
        time.sleep(HOLD_S)  # stays: the hold is the point (a worker mid-analysis when it is killed)
        return super().finish()


def product_analysis_held(cloud: ScanCloud, job: AnalysisJob) -> dict[str, Any]:
    """The product's analysis (:func:`analysis.pipeline.analyse_job`) after :data:`HOLD_S`: a worker
    that is surely mid-analysis when a test kills it (the real analysis of the fault cell's small
    plate takes well under a second, from the last pass)."""
    time.sleep(HOLD_S)  # stays: the hold is the point
    return analyse_job(cloud, job)


product_analysis_held.stream = _HeldCloudStream  # type: ignore[attr-defined]
