"""The daemon's job store writes job.json on a writer thread: ordered, read-your-writes, errors kept."""

from __future__ import annotations

import shutil

import pytest

from cellctl.api import JobState
from cellctl.daemon.jobs import JobRecord, JobStore, JobStoreError


def _record(job_id: str) -> JobRecord:
    return JobRecord(job_id=job_id, plate_id="P1", design="d.ply", design_path="/d.ply", placement={})


def test_background_saves_land_in_order_and_load_sees_the_last(tmp_path):
    store = JobStore(tmp_path, background_saves=True)
    try:
        rec = store.create(_record("20260101T000000-a"))
        for i in range(50):
            store.set_state(rec, JobState.SCANNING, f"step {i}", profiles=i)
        loaded = store.load(rec.job_id)
        assert loaded.info["profiles"] == 49
        assert len(loaded.history) == 51
    finally:
        store.close()
    assert JobStore(tmp_path).load(rec.job_id).info["profiles"] == 49


def test_a_failed_background_write_is_raised_by_the_next_flush(tmp_path):
    store = JobStore(tmp_path, background_saves=True)
    try:
        rec = store.create(_record("20260101T000000-b"))
        shutil.rmtree(store.job_dir(rec.job_id))  # the write has nowhere to go
        store.set_state(rec, JobState.SCANNING, "lost")
        with pytest.raises(JobStoreError, match="cannot write the job record"):
            store.flush()
        store.flush()  # reported once
    finally:
        store.close()
