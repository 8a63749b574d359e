"""What an operator types, as the README says it (issue 24's smaller findings): a report by job id or
job directory, a job directory given to reassemble, a command piped into ``head``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from analysis.templates import DetectionLayout
from cellctl.jobstore.rawstore import RawWriter
from tests.support.results_fixture import write_synthetic_results

pytestmark = pytest.mark.process  # each test runs `cellctl`

REPO = Path(__file__).resolve().parents[2]


def _cellctl(*args: str, cwd: Path, **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-m", "cellctl", *args], cwd=cwd, env=env, capture_output=True, text=True,
        timeout=240, **kw,
    )  # fmt: skip


def _job(tmp_path: Path) -> tuple[Path, str]:
    (tmp_path / "cell.toml").write_text(f'[cell]\nid = "c1"\ndata_dir = "{tmp_path / "data"}"\n')
    job_id = "20260101T000000-0a1b2c3d"
    job_dir = tmp_path / "data" / "jobs" / job_id
    write_synthetic_results(
        job_dir / "results", n_points=3_000, layout=DetectionLayout(1, 100.0, 1, 100.0, False)
    )
    (job_dir / "report.json").write_text(
        (job_dir / "results" / "report.json").read_text()
    )  # the daemon's copy
    return job_dir, job_id


def test_report_takes_a_job_id_and_a_job_directory_as_the_readme_says(tmp_path):
    job_dir, job_id = _job(tmp_path)
    by_id = _cellctl("report", job_id, cwd=tmp_path)
    assert by_id.returncode == 0, by_id.stderr[-2000:]
    assert (job_dir / "results" / "report.html").exists()
    (job_dir / "results" / "report.html").unlink()
    by_dir = _cellctl("report", str(job_dir), cwd=tmp_path)
    assert by_dir.returncode == 0, by_dir.stderr[-2000:]
    assert (job_dir / "results" / "report.html").exists()


def test_reassemble_of_a_job_directory_reads_its_raw_directory_or_says_what_is_missing(tmp_path):
    job_dir = tmp_path / "jobs" / "J"
    w = RawWriter(job_dir / "raw", {"job_id": "J"}, fsync=False)  # raw files without acquisition settings
    w.close()
    (job_dir / "job.json").write_text('{"job_id": "J", "state": "interrupted"}')
    out = _cellctl("reassemble", str(job_dir), cwd=tmp_path)
    assert out.returncode == 2, out
    assert "Traceback" not in out.stderr and "KeyError" not in out.stderr, out.stderr
    assert "no 'acquisition' settings" in out.stderr and str(job_dir / "raw") in out.stderr


def test_a_reader_that_goes_away_ends_the_command_without_a_traceback(tmp_path):
    """``cellctl ... | head``: the pipe closes under the command (here: `config check` printing ok
    into a pipe already closed)."""
    (tmp_path / "cell.toml").write_text('[cell]\nid = "c1"\n')
    r, w = os.pipe()
    os.close(r)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    p = subprocess.run(
        [sys.executable, "-m", "cellctl", "config", "check", "cell.toml"], cwd=tmp_path, env=env,
        stdout=w, stderr=subprocess.PIPE, text=True, timeout=60,
    )  # fmt: skip
    os.close(w)
    assert "Traceback" not in p.stderr and "BrokenPipeError" not in p.stderr, p.stderr
    assert p.returncode == 141
