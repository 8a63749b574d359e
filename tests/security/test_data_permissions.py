"""The data directory and job directories are private to the service user and its group (0o750)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from cellctl.jobstore.jobs import DIR_MODE, JobRecord, JobStore, JobStoreError


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


@pytest.fixture
def open_umask():
    """A permissive umask, so the modes checked below are the ones the store sets, not the umask's."""
    old = os.umask(0)
    yield
    os.umask(old)


def test_data_jobs_and_job_directories_are_created_0o750_whatever_the_umask(tmp_path, open_umask):
    store = JobStore(tmp_path / "data")
    store.create(
        JobRecord("20260101T000000-abcd", "P1", "plate.stl", "/designs/plate.stl", {"pos_mm": [0, 0, 0]})
    )
    assert DIR_MODE == 0o750
    assert _mode(tmp_path / "data") == 0o750
    assert _mode(tmp_path / "data" / "jobs") == 0o750
    assert _mode(store.job_dir("20260101T000000-abcd")) == 0o750


def test_an_existing_jobs_directory_open_to_everybody_is_tightened(tmp_path):
    (tmp_path / "data" / "jobs").mkdir(parents=True)
    os.chmod(tmp_path / "data" / "jobs", 0o777)
    JobStore(tmp_path / "data")
    assert _mode(tmp_path / "data" / "jobs") == 0o750


def test_an_existing_data_directory_open_to_others_is_reported_not_silently_used(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    os.chmod(data, 0o755)
    with capture_logs() as logs:
        JobStore(data)
    assert any(e["event"] == "data_dir_open_to_others" and e["mode"] == "755" for e in logs)


def test_a_data_directory_that_cannot_be_created_is_a_job_store_error_naming_it(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(JobStoreError, match="cannot create a private directory"):
        JobStore(blocker / "data")


def test_raw_directory_and_files_are_group_readable_only_whatever_the_umask(tmp_path, open_umask):
    """Issue 24: ``raw/`` was 0o755 with 0o644 files, so anybody on the machine read the raw scans."""
    from cellctl.jobstore.rawstore import STREAMS, RawWriter

    raw = tmp_path / "jobs" / "J" / "raw"
    w = RawWriter(raw, {"job_id": "J"}, fsync=False)
    w.close()
    assert _mode(raw) == 0o750
    assert {p.name: _mode(p) for p in raw.iterdir()} == {
        **{f"{s}.craw": 0o640 for s in STREAMS},
        "job.json": 0o640,
    }
