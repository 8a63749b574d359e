"""The plate history index: rebuilt from job directories, rounds per plate, `cellctl history`."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cellctl.jobstore.history import History, format_history
from tests.support.reports import report_json

REPO = Path(__file__).resolve().parents[2]


def _job(
    data: Path, job_id: str, plate: str, created: str, zmax: list[float] | None, state: str = "done"
) -> None:
    d = data / "jobs" / job_id
    d.mkdir(parents=True)
    rec = {"job_id": job_id, "plate_id": plate, "design": "p.ply", "design_path": "/x/p.ply",
           "placement": {"pos_mm": [1500.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
           "state": state, "created_utc": created, "history": [{"state": state, "t_utc": created, "message": "m"}],
           "info": {}}  # fmt: skip
    (d / "job.json").write_text(json.dumps(rec))
    if zmax is not None:
        lines = [
            {
                "family": "transverse",
                "index": k + 1,
                "name": f"T{k + 1}",
                "zmax_mm": z,
                "sz_avg_mm": z / 2,
                "pass": abs(z) <= 3,
            }
            for k, z in enumerate(zmax)
        ]
        verdict = "pass" if all(abs(z) <= 3 for z in zmax) else "fail"
        (d / "report.json").write_text(report_json(lines, verdict, plate_id=plate))


def test_rebuild_rounds_previous_round_and_index_job(tmp_path: Path) -> None:
    _job(tmp_path, "j1", "P1", "2026-11-01T10:00:00Z", [4.0, 2.0])
    _job(tmp_path, "j2", "P2", "2026-11-01T11:00:00Z", [1.0])
    _job(tmp_path, "j3", "P1", "2026-11-02T10:00:00Z", [2.5, 1.0])
    _job(tmp_path, "j4", "P1", "2026-11-02T11:00:00Z", None, state="aborted")
    (tmp_path / "jobs" / "junk").mkdir()  # no job.json: skipped
    h = History(tmp_path)
    try:
        assert h.rebuild() == 4
        assert [j["job_id"] for j in h.jobs()] == ["j4", "j3", "j2", "j1"]
        assert [j["job_id"] for j in h.jobs(plate_id="P1", verdict="fail")] == ["j1"]
        assert [j["job_id"] for j in h.jobs(date="2026-11-01")] == ["j2", "j1"]
        rounds = h.rounds("P1")
        assert [(r["round"], r["job_id"], r["verdict"]) for r in rounds] == [
            (1, "j1", "fail"),
            (2, "j3", "pass"),
        ]
        assert rounds[0]["lines"][0]["zmax_mm"] == 4.0 and rounds[0]["max_abs_zmax_mm"] == 4.0
        assert h.previous_round("j3")["job_id"] == "j1" and h.previous_round("j1") is None
        _job(tmp_path, "j5", "P1", "2026-11-03T10:00:00Z", [1.0, 0.5])
        assert h.index_job("j5")["verdict"] == "pass"
        assert len(h.rounds("P1")) == 3
        text = format_history(h, "P1")
        assert "3 round(s)" in text and "4.00!" in text and "T2" in text
        assert "no analysed rounds" in format_history(h, "nope")
    finally:
        h.close()
    assert (tmp_path / "history.sqlite").exists()


@pytest.mark.process
def test_cellctl_history_prints_a_plates_rounds(tmp_path: Path) -> None:
    data = tmp_path / "data"
    _job(data, "j1", "P1", "2026-11-01T10:00:00Z", [4.0])
    _job(data, "j2", "P1", "2026-11-02T10:00:00Z", [1.5])
    cfg = REPO / "cell.toml"
    env = dict(os.environ, CELL_CELL__DATA_DIR=str(data))  # the environment overrides cell.toml
    out = subprocess.run(
        [sys.executable, "-m", "cellctl", "history", "P1", "--config", str(cfg)], capture_output=True, text=True,
        env=env, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "2 round(s)" in out.stdout and "4.00!" in out.stdout and "1.50" in out.stdout


@pytest.mark.process
def test_cellctl_history_reads_without_writing_and_names_a_missing_data_dir(tmp_path: Path) -> None:
    data = tmp_path / "data"
    _job(data, "j1", "P1", "2026-11-01T10:00:00Z", [4.0])
    cmd = [sys.executable, "-m", "cellctl", "history", "--config", str(REPO / "cell.toml")]
    out = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, CELL_CELL__DATA_DIR=str(data)),
                         timeout=60)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "j1" in out.stdout
    assert not (data / "history.sqlite").exists()  # an inspector's read leaves the daemon's files alone
    missing = tmp_path / "nowhere"
    out = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, CELL_CELL__DATA_DIR=str(missing)),
                         timeout=60)  # fmt: skip
    assert out.returncode == 2
    assert "no job directory here" in out.stderr and "Traceback" not in out.stderr
    assert not missing.exists()
