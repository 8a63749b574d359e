"""`cellctl reassemble` and `cellctl calibrate time-offset` on a recorded (synthetic) job."""

from __future__ import annotations

import shutil

import numpy as np
import plyfile
import pytest
import structlog

from analysis.cloud_export import read_e57, read_las
from cellctl.acquisition.clock_sync import ClockSyncConfig
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.reassemble import reassemble
from cellctl.calibration.record import CalibrationWriteError, set_toml_values
from cellctl.cli import main
from cellctl.config import load_config
from cellctl.jobstore.rawstore import RawWriter
from tests.support.synthetic_scan import feed, make_run


@pytest.fixture(autouse=True)
def _restore_logging():
    # cellctl.cli.main configures structlog onto the captured stderr of one test; put it back
    saved = structlog.get_config()
    yield
    structlog.configure(**saved)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    run = make_run(6.0)
    s = AcquisitionSettings(
        epoch_ns=run.epoch_ns, latency_ms=-2.2, sensor_sync_config=ClockSyncConfig(min_drift_span_s=3.0)
    )  # 3 ms below the right 0.8 ms
    d = tmp_path_factory.mktemp("cmd") / "job"
    with RawWriter(d, {"acquisition": s.to_json()}, fsync=False) as w:
        acq = Acquisition(s, w)
        for k, (a, b) in enumerate([(0.05, 1.25), (1.25, 3.75), (3.75, 6.25)]):
            acq.begin_pass(k, run.epoch_ns + round(a * 1e9))
            acq.end_pass(run.epoch_ns + round(b * 1e9))
        feed(acq, run)
    return d


def test_reassemble_command_writes_ply_las_and_e57_of_the_final_cloud(job, tmp_path, capsys):
    assert main(["reassemble", str(job), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    ref = reassemble(job)
    assert ref.cloud.digest() in out
    v = plyfile.PlyData.read(str(tmp_path / "cloud.ply"))["vertex"].data
    assert len(v) == ref.cloud.n_valid
    las = read_las(tmp_path / "cloud.las", require=["pass_id", "profile_index", "point_index", "t_s"])
    e57 = read_e57(tmp_path / "cloud.e57", require=["profile_index", "point_index", "t_s"])
    assert len(las["xyz_mm"]) == len(e57["xyz_mm"]) == ref.cloud.n_valid
    assert "robot base frame" in str(las["frame"]) and "robot base frame" in str(e57["frame"])


def test_reassemble_command_names_a_directory_without_raw_files(tmp_path, capsys):
    assert main(["reassemble", str(tmp_path)]) == 2
    assert "job.json" in capsys.readouterr().err


def test_calibrate_time_offset_writes_the_latency_into_cell_toml(job, tmp_path, repo_root, capsys):
    cfg = tmp_path / "cell.toml"
    shutil.copy(repo_root / "cell.toml", cfg)
    before = cfg.read_text()
    assert main(["calibrate", "time-offset", str(job), "--config", str(cfg), "--write"]) == 0
    latency = load_config(cfg).laser.latency_ms
    assert latency == pytest.approx(0.8, abs=0.2)
    # only that value changed; comments and layout stay
    changed = [
        (a, b) for a, b in zip(before.splitlines(), cfg.read_text().splitlines(), strict=True) if a != b
    ]
    assert len(changed) == 1 and changed[0][1].startswith("latency_ms = ") and "#" in changed[0][1]
    assert (job / "calibration-time-offset.json").exists()


def test_a_value_the_config_rejects_is_never_written(tmp_path, repo_root):
    cfg = tmp_path / "cell.toml"
    shutil.copy(repo_root / "cell.toml", cfg)
    before = cfg.read_text()
    with pytest.raises(CalibrationWriteError, match="validate"):
        set_toml_values(cfg, "robot.sensor_in_flange", {"pos_mm": [0.0, float("nan"), 1.0]})
    assert cfg.read_text() == before
    assert np.isfinite(load_config(cfg).robot.sensor_in_flange.pos_mm).all()
