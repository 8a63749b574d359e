"""`cellctl scan / status / run` refuse clearly when their input or their peer is missing."""

from __future__ import annotations

import subprocess

import pytest

from tests.support.e2e_cell import tiny_cell_config

pytestmark = pytest.mark.process  # the console script in a subprocess


def _cellctl(cellctl_exe, *args, timeout=60):
    return subprocess.run([*cellctl_exe, *args], capture_output=True, text=True, timeout=timeout)


def test_scan_with_a_malformed_placement_exits_2_naming_the_option(cellctl_exe, tmp_path):
    cfg = tiny_cell_config(tmp_path)
    r = _cellctl(cellctl_exe, "scan", "--config", str(cfg), "--plate", "p1", "--design", "demo-plate.ply",
                 "--placement", "1500,abc")  # fmt: skip
    assert r.returncode == 2
    assert "--placement" in r.stderr and "1500,abc" in r.stderr


def test_status_without_a_daemon_exits_3_and_says_so(cellctl_exe, tmp_path):
    cfg = tiny_cell_config(tmp_path)  # fresh free ports: nothing listens there
    r = _cellctl(cellctl_exe, "status", "--config", str(cfg), "--timeout-s", "1")
    assert r.returncode == 3
    assert "cannot open Zenoh" in r.stderr


def test_run_without_the_rws_password_exits_2_naming_the_variable(cellctl_exe, tmp_path):
    import os

    cfg = tiny_cell_config(tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "CELL_RWS_PASSWORD"}
    r = subprocess.run([*cellctl_exe, "--log-format", "json", "run", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=60, env=env)  # fmt: skip
    assert r.returncode == 2
    assert "CELL_RWS_PASSWORD" in r.stderr + r.stdout
