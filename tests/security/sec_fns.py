"""A small real analysis callable for the worker started by the security tests (imported by dotted path)."""

from __future__ import annotations

from analysis.cloud_io import ScanCloud
from analysis.contracts.job import AnalysisJob, Report
from tests.support.zworker_fns import minimal_report


def point_count(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """A report recording the cloud's point count: enough to prove the job went round trip."""
    return minimal_report(job, len(cloud))
