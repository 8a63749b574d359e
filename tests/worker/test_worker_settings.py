"""Worker and dispatcher settings come from [analysis] / [zenoh] of cell.toml."""

from __future__ import annotations

import pytest

from cellctl.config import ConfigError, load_config, parse_config
from cellctl.daemon.dispatch import DispatchSettings
from cellctl.worker.child import AnalysisLoadError, resolve_callable
from cellctl.worker.settings import WorkerSettings


def test_shipped_cell_toml_gives_the_documented_defaults(repo_root):
    cfg = load_config(repo_root / "cell.toml")
    w = WorkerSettings.from_config(cfg)
    assert (w.analysis, w.heartbeat_s, w.worker_id) == ("analysis.pipeline:analyse_job", 1.0, "")
    d = DispatchSettings.from_config(cfg)
    assert (d.ack_timeout_s, d.heartbeat_timeout_s, d.job_timeout_s, d.max_attempts, d.shm_pool_mb) == (
        10.0,
        10.0,
        900.0,
        3,
        0,
    )


def test_command_line_overrides_win_and_none_means_not_given():
    cfg = parse_config({"analysis": {"callable": "pkg.mod:fn", "heartbeat_s": 2.0, "heartbeat_timeout_s": 5}})
    w = WorkerSettings.from_config(cfg, analysis=None, heartbeat_s=0.5, worker_id="w7")
    assert (w.analysis, w.heartbeat_s, w.worker_id) == ("pkg.mod:fn", 0.5, "w7")


@pytest.mark.parametrize(
    ("analysis", "needle"),
    [
        ({"heartbeat_s": 5.0, "heartbeat_timeout_s": 6.0}, "at least twice heartbeat_s"),
        ({"callable": "no colon"}, "analysis.callable"),
        ({"max_attempts": 0}, "analysis.max_attempts"),
    ],
)
def test_inconsistent_worker_settings_are_config_errors(analysis, needle):
    with pytest.raises(ConfigError, match=needle):
        parse_config({"analysis": analysis})


@pytest.mark.parametrize(
    ("path", "needle"),
    [
        ("nocolon", "expected 'package.module:function'"),
        ("no_such_module_xyz:fn", "cannot import no_such_module_xyz"),
        ("json:no_such_fn", "has no attribute 'no_such_fn'"),
        ("json:__doc__", "is not callable"),
    ],
)
def test_resolve_callable_names_what_is_wrong(path, needle):
    with pytest.raises(AnalysisLoadError, match=needle):
        resolve_callable(path)


def test_resolve_callable_finds_a_function():
    import json

    assert resolve_callable("json:dumps") is json.dumps


def test_worker_command_refuses_bad_arguments_before_starting_anything(tmp_path, capsys):
    from cellctl.cli import main

    assert main(["worker", "--config", str(tmp_path / "missing.toml")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "cell.toml").write_text('[cell]\nid = "c1"\n')
    assert main(["worker", "--config", str(tmp_path / "cell.toml"), "--worker-id", "bad/id"]) == 2
    assert "--worker-id 'bad/id'" in capsys.readouterr().err
    assert main(["worker", "--config", str(tmp_path / "cell.toml"), "--heartbeat-s", "0"]) == 2
    assert "--heartbeat-s must be positive" in capsys.readouterr().err
