"""`cellctl report JOB_OR_DIR [--open]` as a user runs it: the installed command in a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from analysis.templates import DetectionLayout
from cellctl.commands import report_cmd
from tests.support.reports import report_dict
from tests.support.results_fixture import write_synthetic_results
from tests.support.waits import wait_until_sync

TINY = DetectionLayout(transverse_offsets_mm=(900.0,), longitudinal_offsets_mm=(), diagonals=False)


def _run(cmd: list[str], cwd: Path, **env_overrides: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[2])
    env.update(env_overrides)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=240)


@pytest.mark.slow
def test_report_regenerates_a_job_found_under_the_configured_data_dir_and_opens_it(
    cellctl_exe, tmp_path: Path
) -> None:
    job_dir = tmp_path / "store" / "jobs" / "job-42"
    write_synthetic_results(job_dir, n_points=3000, layout=TINY)
    (tmp_path / "cell.toml").write_text(f'[cell]\nid = "c1"\ndata_dir = "{tmp_path / "store"}"\n')
    # a desktop whose xdg-open records what it was asked to open
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    opened = tmp_path / "opened.txt"
    (bin_dir / "xdg-open").write_text(f'#!/bin/sh\nprintf "%s" "$1" > "{opened}"\n')
    (bin_dir / "xdg-open").chmod(0o755)
    res = _run(
        [*cellctl_exe, "report", "job-42", "--open", "--config", "cell.toml"],
        tmp_path,
        DISPLAY=":0",
        PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == [str(job_dir / n) for n in ("report.csv", "report.html", "report.pdf")]
    html = (job_dir / "report.html").read_text(encoding="utf-8")
    assert "T1" in html and "FAIL" in html  # the line through the 3.6 mm dent fails the 3 mm limit
    wait_until_sync(
        lambda: opened.exists() and opened.read_text(), 1.0, "the detached opener writing its file"
    )
    assert opened.read_text() == str(job_dir / "report.html")


def test_open_without_a_desktop_declines_so_the_path_is_printed(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert report_cmd._open(tmp_path / "report.html") is False


@pytest.mark.process
def test_report_refuses_an_unknown_job_and_a_broken_results_dir(cellctl_exe, tmp_path: Path) -> None:
    (tmp_path / "cell.toml").write_text(f'[cell]\ndata_dir = "{tmp_path / "store"}"\n')
    res = _run([*cellctl_exe, "report", "nope", "--config", "cell.toml"], tmp_path)
    assert res.returncode == 2
    assert "nope: neither a directory nor a job in" in res.stderr

    bad = tmp_path / "bad"
    bad.mkdir()
    broken = report_dict(
        [{"family": "transverse", "index": 1, "zmax_mm": 1.0, "sz_avg_mm": 0.5, "pass": True}]
    )
    broken["lines"][0] = {"family": "x"}
    (bad / "report.json").write_text(json.dumps(broken))
    res = _run([*cellctl_exe, "report", str(bad)], tmp_path)
    assert res.returncode == 2
    assert "report.json: lines[0].family: Input should be 'transverse'" in res.stderr
    assert not (bad / "report.html").exists()


@pytest.mark.slow
def test_report_json_answers_with_the_written_files_as_one_typed_object(tmp_path: Path, capsys) -> None:
    """``cellctl report --json``: the daemon's render child tells its files in one RenderAnswer line."""
    import argparse

    from cellctl.daemon.render import RenderAnswer

    layout = DetectionLayout(transverse_offsets_mm=(300.0,), longitudinal_offsets_mm=(), diagonals=False)
    write_synthetic_results(tmp_path, n_points=2000, layout=layout)
    args = argparse.Namespace(target=str(tmp_path), open=False, json=True, config="/nonexistent/cell.toml")
    assert report_cmd.run(args) == 0
    out = capsys.readouterr().out.splitlines()  # in this process structlog may print here too
    answer = RenderAnswer.model_validate_json(out[-1])
    assert not any(line.endswith((".csv", ".html", ".pdf")) for line in out)  # no path a line
    assert [Path(answer.csv).name, Path(answer.html).name, Path(answer.pdf).name] == [
        "report.csv", "report.html", "report.pdf"
    ]  # fmt: skip
    assert all(Path(p).is_file() for p in (answer.csv, answer.html, answer.pdf))


def test_export_writes_the_chosen_files_and_refuses_a_results_dir_without_the_deviation(
    tmp_path: Path, capsys
) -> None:
    """``cellctl export DIR --formats las,e57 --frames ship``: the two files, one path a line; a cloud.ply
    without the deviation (not a results cloud) is exit 2 with the file named."""
    import argparse

    from analysis.cloud_export import read_e57, read_las

    write_synthetic_results(tmp_path / "r", n_points=1500)
    args = argparse.Namespace(target=str(tmp_path / "r"), formats="las,e57", frames="ship", out=str(tmp_path / "x"),
                              config="/nonexistent/cell.toml")  # fmt: skip
    assert report_cmd.run_export(args) == 0
    out = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith(str(tmp_path))]
    assert [Path(p).name for p in out] == ["cloud-ship.las", "cloud-ship.e57"]
    assert len(read_las(out[0], require=["deviation_mm"])["xyz_mm"]) == 1500
    assert len(read_e57(out[1], require=["deviation_mm"])["xyz_mm"]) == 1500
    ply = tmp_path / "r" / "cloud.ply"
    ply.write_bytes(ply.read_bytes().replace(b"scalar_deviation", b"scalar_somethin1"))
    assert report_cmd.run_export(args) == 2
    assert "cloud.ply: not a results cloud" in capsys.readouterr().err
    bad = argparse.Namespace(**{**vars(args), "formats": "las,xyz"})
    assert report_cmd.run_export(bad) == 2
    assert "unknown export format" in capsys.readouterr().err
