"""The installed `cellctl` console script, run as a user runs it (subprocess)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from cellctl import __version__
from tests.support.ports import free_port

pytestmark = pytest.mark.process  # the console script run as a user runs it


def _run(exe: list[str], *args: str, cwd: Path | None = None, env: dict | None = None):
    return subprocess.run([*exe, *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=60)


def test_version(cellctl_exe: list[str]) -> None:
    r = _run(cellctl_exe, "--version")
    assert r.returncode == 0 and r.stdout.strip() == f"cellctl {__version__}"


def test_help_lists_config(cellctl_exe: list[str]) -> None:
    r = _run(cellctl_exe, "--help")
    assert r.returncode == 0 and "config" in r.stdout


def test_config_check_shipped_file_prints_ok(cellctl_exe: list[str], repo_root: Path) -> None:
    r = _run(cellctl_exe, "config", "check", "cell.toml", cwd=repo_root)
    assert (r.returncode, r.stdout.strip(), r.stderr) == (0, "ok", "")


def test_config_check_defaults_to_cell_toml_in_working_directory(
    cellctl_exe: list[str], repo_root: Path
) -> None:
    r = _run(cellctl_exe, "config", "check", cwd=repo_root)
    assert r.returncode == 0 and r.stdout.strip() == "ok"


def test_config_check_broken_file_gives_one_line_per_error_and_exit_2(
    cellctl_exe: list[str], tmp_path: Path
) -> None:
    bad = tmp_path / "cell.toml"
    bad.write_text("[robot]\negm_port = 0\nrws_password = 'robotics'\n[laser]\nfoo = 1\n")
    r = _run(cellctl_exe, "config", "check", str(bad))
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 3, lines
    assert all(line.startswith(f"{bad}: ") for line in lines)
    assert "Traceback" not in r.stderr and "robotics" not in r.stderr


def test_config_check_missing_file(cellctl_exe: list[str], tmp_path: Path) -> None:
    r = _run(cellctl_exe, "config", "check", str(tmp_path / "none.toml"))
    assert r.returncode == 2 and r.stderr.strip() == f"{tmp_path / 'none.toml'}: no such file"


def test_config_check_syntax_error(cellctl_exe: list[str], tmp_path: Path) -> None:
    bad = tmp_path / "cell.toml"
    bad.write_text("[cell\n")
    r = _run(cellctl_exe, "config", "check", str(bad))
    assert r.returncode == 2 and "line 1, column" in r.stderr and "Traceback" not in r.stderr


def test_unknown_command_exits_2_with_one_line(cellctl_exe: list[str]) -> None:
    r = _run(cellctl_exe, "frobnicate")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def test_config_check_names_each_bad_daemon_key_on_its_own_line(
    cellctl_exe: list[str], tmp_path: Path
) -> None:
    bad = tmp_path / "cell.toml"
    bad.write_text("[daemon]\nqueue_max = -1\nsettle_s = 'long'\nqueue_size = 3\n")
    r = _run(cellctl_exe, "config", "check", str(bad))
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 3, lines
    assert any(f"{bad}: daemon.queue_max = -1: " in line for line in lines)
    assert any(f"{bad}: daemon.settle_s = 'long': " in line for line in lines)
    assert f"{bad}: daemon.queue_size: unknown key" in lines


def test_abort_without_a_daemon_exits_3_saying_so(cellctl_exe: list[str], repo_root: Path) -> None:
    import os

    port = free_port()  # a loopback port nobody listens on
    env = {**os.environ, "CELL_ZENOH__LISTEN": f'["tcp/127.0.0.1:{port}"]'}
    r = _run(cellctl_exe, "abort", "--job", "20261122T000000-aaaa0001", "--config", str(repo_root / "cell.toml"),
             env=env)  # fmt: skip
    assert r.returncode == 3, r.stderr
    assert "cellctl abort: error: cannot open Zenoh" in r.stderr and "Traceback" not in r.stderr
