"""cell.toml validation: the shipped file, each rule with a bad value, env overrides, secrets."""

from __future__ import annotations

import re
import tomllib
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel, ValidationError

from cellctl.config import CellConfig, ConfigError, load_config, parse_config, resolve_secret


@pytest.fixture()
def shipped(repo_root: Path) -> dict:
    return tomllib.loads((repo_root / "cell.toml").read_text())


def _problems(data: dict) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(data, "test.toml")
    return info.value.problems


def _with(data: dict, section: str, **values) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    node = out
    for part in section.split("."):
        node[part] = dict(node.get(part, {}))
        node = node[part]
    node.update(values)
    return out


def test_shipped_cell_toml_validates(repo_root: Path) -> None:
    cfg = load_config(repo_root / "cell.toml")
    assert cfg.cell.id == "sim1"
    assert cfg.key_prefix == "cell/sim1"
    assert cfg.zenoh.multicast_scouting is False
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in cfg.zenoh.listen)


def _unset_fields(model: type[BaseModel], data: dict, text: str, path: str = "") -> list[str]:
    """Fields of ``model`` (recursively through nested sections) that ``data`` does not set. A field
    whose default is None (an optional file; TOML has no null) counts as set when a commented
    ``# name =`` line (or, for an optional section, a commented ``# [section]`` table) documents it."""
    unset = []
    for name, field in model.model_fields.items():
        key = field.alias or name
        where = f"{path}.{key}" if path else key
        if key not in data:
            documented = re.search(rf"^# ({re.escape(key)} = |\[{re.escape(where)}\])", text, re.MULTILINE)
            if not (field.default is None and documented):
                unset.append(where)
            continue
        nested = [a for a in (field.annotation, *typing.get_args(field.annotation))
                  if isinstance(a, type) and issubclass(a, BaseModel)]  # fmt: skip
        if nested and isinstance(data[key], dict):
            unset += _unset_fields(nested[0], data[key], text, where)
    return unset


def test_shipped_cell_toml_sets_every_field_explicitly(shipped: dict, repo_root: Path) -> None:
    # The shipped file documents the whole configuration: no field of any section, nested ones
    # included, is left to a default it does not show.
    assert _unset_fields(CellConfig, shipped, (repo_root / "cell.toml").read_text()) == []


def test_config_is_frozen(repo_root: Path) -> None:
    cfg = load_config(repo_root / "cell.toml")
    with pytest.raises(ValidationError, match="frozen"):
        cfg.robot.egm_port = 1  # type: ignore[misc]


@pytest.mark.parametrize(
    ("section", "values", "expected"),
    [
        ("robot", {"egm_port": 0}, "robot.egm_port = 0"),
        ("robot", {"egm_port": 70000}, "robot.egm_port = 70000"),
        ("robot", {"joint_lower_deg": [0, 0, 0]}, "robot.joint_lower_deg"),
        (
            "robot",
            {"joint_lower_deg": [190, -90, -180, -400, -125, -400]},
            "joint 1: joint_lower_deg (190.0)",
        ),
        ("robot", {"joint_margin_deg": 200.0}, "joint_margin_deg leaves no usable range"),
        ("robot", {"workspace_min_mm": [0, 0, 3000]}, "workspace z"),
        ("robot", {"joint_speed_max_deg_s": [1, 1, 1, 1, 1, -1]}, "robot.joint_speed_max_deg_s.5 = -1"),
        ("robot", {"tcp_speed_max_mm_s": 0}, "robot.tcp_speed_max_mm_s = 0"),
        ("robot", {"rws_url": "ftp://controller"}, "expected an http:// or https:// URL"),
        ("robot", {"rws_profile": "rws3"}, "robot.rws_profile = 'rws3'"),
        ("robot", {"rws_profile": "rws2"}, "rws2' (RobotWare 7) speaks HTTPS"),
        ("robot", {"tracking_error_max_mm": float("nan")}, "robot.tracking_error_max_mm"),
        ("robot", {"egm_reply_priority": 100}, "robot.egm_reply_priority = 100"),
        ("robot", {"egm_switch_interval_s": 0.1}, "robot.egm_switch_interval_s = 0.1"),
        ("robot", {"egm_reply_cpus": [-1]}, "robot.egm_reply_cpus.0 = -1"),
        ("robot", {"egm_reply_spin_us": 5000}, "robot.egm_reply_spin_us = 5000"),
        ("laser", {"depth_min_mm": 200.0}, "depth_min_mm (200.0) must be below depth_max_mm"),
        ("laser", {"points_per_profile": 1}, "laser.points_per_profile = 1"),
        ("laser", {"exposure_us": 9000.0}, "does not fit in one profile period"),
        ("scan", {"overlap_fraction": 0.95}, "scan.overlap_fraction = 0.95"),
        ("scan", {"speed_mm_s": "fast"}, "scan.speed_mm_s"),
        ("zenoh", {"listen": ["tcp/localhost"]}, "'tcp/localhost' is not a Zenoh endpoint"),
        ("zenoh", {"mode": "client", "connect": []}, "mode 'client' needs at least one 'connect'"),
        ("zenoh", {"key_prefix": "cell//x"}, "zenoh.key_prefix"),
        ("cell", {"id": "bad id!"}, "cell.id = 'bad id!'"),
        ("analysis.tolerances", {"deviation_standard_mm": 4.0}, "must not exceed deviation_limit_mm"),
        ("sim", {"rws_users": {"Default User": "robotics"}}, "expected the name of an environment variable"),
        ("sim.faults", {"egm_loss_fraction": 1.5}, "sim.faults.egm_loss_fraction = 1.5"),
        ("daemon", {"queue_max": -1}, "daemon.queue_max = -1"),
        ("daemon", {"queue_max": 1000}, "daemon.queue_max = 1000"),
        ("daemon", {"status_period_s": 0}, "daemon.status_period_s = 0"),
        ("daemon", {"settle_s": float("inf")}, "daemon.settle_s"),
        ("daemon", {"marker_period_s": 0.5}, "daemon.marker_period_s = 0.5"),
        ("daemon", {"write_html_report": "maybe"}, "daemon.write_html_report = 'maybe'"),
        ("forming", {"min_spacing_mm": 0}, "forming.min_spacing_mm = 0"),
        ("forming", {"edge_margin_mm": -5.0}, "forming.edge_margin_mm = -5.0"),
        ("forming", {"max_lines_per_round": 0}, "forming.max_lines_per_round = 0"),
        ("forming", {"max_lines_per_round": True}, "max_lines_per_round: expected a number"),
        ("forming", {"element_mm": 1.0}, "forming.element_mm"),
        ("forming", {"material": "wood"}, "material 'wood' is not in the coefficient table"),
        (
            "forming",
            {"heat_input_min_j_per_mm": 900.0, "heat_input_max_j_per_mm": 600.0},
            "heat_input_max_j_per_mm (600) must exceed heat_input_min_j_per_mm (900)",
        ),
        ("forming", {"heat_input_max_j_per_mm": 5000.0}, "not inside the coefficient table's 150-3000 J/mm"),
        (
            "forming",
            {"coefficients_file": "/nonexistent/table.toml"},
            "coefficients_file /nonexistent/table.toml: No such file or directory",
        ),
    ],
)
def test_bad_value_is_reported_with_its_path(
    shipped: dict, section: str, values: dict, expected: str
) -> None:
    problems = _problems(_with(shipped, section, **values))
    assert any(expected in p for p in problems), problems


def test_unknown_key_is_reported(shipped: dict) -> None:
    assert _problems(_with(shipped, "laser", colour="red")) == ["laser.colour: unknown key"]


def test_unknown_section_is_reported(shipped: dict) -> None:
    assert _problems({**shipped, "printer": {"a": 1}}) == ["printer: unknown key"]


def test_wrong_type_names_value_and_expectation(shipped: dict) -> None:
    (problem,) = _problems(_with(shipped, "robot", egm_port="six"))
    assert problem.startswith("robot.egm_port = 'six': Input should be a valid integer")


def test_password_in_file_is_refused_with_guidance(shipped: dict) -> None:
    (problem,) = _problems(_with(shipped, "robot", rws_password="robotics"))
    assert "rws_password_env" in problem and "robotics" not in problem


def test_every_error_is_reported_not_only_the_first(shipped: dict) -> None:
    problems = _problems(_with(_with(shipped, "robot", egm_port=0), "laser", rate_hz=-1))
    assert len(problems) == 2


def test_environment_overrides_file(shipped: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELL_ROBOT__EGM_PORT", "6599")
    monkeypatch.setenv("CELL_SIM__PLATE__KIND", "saddle")
    monkeypatch.setenv("CELL_ZENOH__LISTEN", '["tcp/127.0.0.1:7500"]')
    cfg = parse_config(shipped)
    assert cfg.robot.egm_port == 6599
    assert cfg.sim.plate.kind == "saddle"
    assert cfg.sim.plate.length_mm == shipped["sim"]["plate"]["length_mm"]  # the rest of the table kept
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7500"]


def test_bad_environment_override_is_reported_as_such(shipped: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CELL_ROBOT__EGM_PORT", "abc")
    (problem,) = _problems(shipped)
    assert problem.startswith("robot.egm_port (from the environment) = 'abc'")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "nope.toml")
    assert info.value.problems == ["no such file"]


def test_toml_syntax_error_gives_line_and_column(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("[cell]\nid = 'a'\n[robot\n")
    with pytest.raises(ConfigError) as info:
        load_config(p)
    (problem,) = info.value.problems
    assert "TOML syntax error" in problem and "line 3" in problem and "column" in problem


def test_non_utf8_file_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_bytes(b"[cell]\nid = '\xff'\n")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(p)


def test_secret_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TEST_SECRET_X", "s3cret")
    assert resolve_secret("TEST_SECRET_X", None, what="rws").get_secret_value() == "s3cret"
    assert "s3cret" not in repr(resolve_secret("TEST_SECRET_X", None, what="rws"))


def test_secret_file_wins_over_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TEST_SECRET_X", "from-env")
    f = tmp_path / "s"
    f.write_text("from-file\n")
    f.chmod(0o600)  # secrets files readable by others are refused
    assert resolve_secret("TEST_SECRET_X", f, what="rws").get_secret_value() == "from-file"


def test_missing_secret_names_the_variable_not_a_value(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TEST_SECRET_MISSING", raising=False)
    with pytest.raises(ConfigError, match="TEST_SECRET_MISSING is not set"):
        resolve_secret("TEST_SECRET_MISSING", None, what="rws")


def test_daemon_section_defaults_apply_when_the_section_is_absent(shipped: dict) -> None:
    cfg = parse_config({k: v for k, v in shipped.items() if k != "daemon"})
    assert cfg.daemon.queue_max == 4 and cfg.daemon.write_html_report is True


def test_daemon_unknown_key_is_reported(shipped: dict) -> None:
    assert _problems(_with(shipped, "daemon", queue_len=3)) == ["daemon.queue_len: unknown key"]


def test_daemon_section_is_overridden_from_the_environment(
    shipped: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CELL_DAEMON__QUEUE_MAX", "0")
    monkeypatch.setenv("CELL_DAEMON__REALTIME", "false")
    cfg = parse_config(shipped)
    assert cfg.daemon.queue_max == 0 and cfg.daemon.realtime is False
    assert cfg.daemon.settle_s == shipped["daemon"]["settle_s"]  # the rest of the table kept


def test_bad_daemon_environment_override_is_one_readable_line(
    shipped: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CELL_DAEMON__QUEUE_MAX", "lots")
    (problem,) = _problems(shipped)
    assert problem.startswith("daemon.queue_max (from the environment) = 'lots'")


# ---- issue 24, finding 5: configuration within physics, strict types, secrets never echoed


@pytest.mark.parametrize(
    ("section", "values", "expected"),
    [
        ("robot", {"tcp_speed_max_mm_s": 1e12}, "robot.tcp_speed_max_mm_s = 1000000000000.0"),
        ("robot", {"joint_lower_deg": [-1e9] * 6}, "leave the IRB 4600's range"),
        ("robot", {"joint_upper_deg": [1e9] * 6}, "leave the IRB 4600's range"),
        ("robot", {"joint_speed_max_deg_s": [1e6] * 6}, "exceeds the IRB 4600's"),
        ("robot", {"joint_accel_max_deg_s2": [1e9] * 6}, "beyond the bounds"),
        ("robot", {"workspace_min_mm": [-1e15] * 3}, "reaches beyond"),
        ("robot", {"egm_comm_timeout_s": 1e9}, "robot.egm_comm_timeout_s = 1000000000.0"),
        ("robot", {"rws_timeout_s": 1e9}, "robot.rws_timeout_s"),
        ("laser", {"rate_hz": True}, "expected a number, got a boolean"),
        ("laser", {"rate_hz": 1e9}, "laser.rate_hz"),
        ("robot", {"joint_margin_deg": False}, "expected a number, got a boolean"),
        ("robot", {"workspace_max_mm": [True, 2000.0, 2400.0]}, "expected a number, got a boolean"),
        ("analysis", {"job_timeout_s": 1e12}, "analysis.job_timeout_s"),
    ],
)
def test_values_no_irb_4600_or_sensor_can_have_are_refused(
    shipped: dict, section: str, values: dict, expected: str
):
    problems = _problems(_with(shipped, section, **values))
    assert any(expected in p for p in problems), problems


def test_the_shipped_limits_stay_inside_the_robot_model(shipped: dict):
    """cell.toml and the defaults pass the bounds, and what they set lies inside the IRB 4600 model:
    each joint's range within the model's, its speed within the model's top speed."""
    from drivers.abb_egm.limits import Q_MAX_DEG, Q_MIN_DEG, QD_MAX_DEG_S

    for robot in (parse_config(shipped, "cell.toml").robot, CellConfig().robot):
        for i in range(6):
            assert Q_MIN_DEG[i] <= robot.joint_lower_deg[i] < robot.joint_upper_deg[i] <= Q_MAX_DEG[i], i
            assert 0 < robot.joint_speed_max_deg_s[i] <= QD_MAX_DEG_S[i], i


@pytest.mark.parametrize(
    ("section", "key"), [("robot", "rws_password_env"), ("zenoh.access", "password_env")]
)
def test_a_password_typed_into_an_env_key_is_refused_and_never_echoed(shipped: dict, section: str, key: str):
    secret = "s3cr3t-Hunter2!"
    problems = _problems(_with(shipped, section, **{key: secret}))
    assert any(key in p and "not its value" in p for p in problems), problems
    assert not any(secret in p for p in problems), problems


def test_a_password_typed_into_sim_rws_users_is_never_echoed(shipped: dict):
    secret = "robotics-Pa55"
    problems = _problems(_with(shipped, "sim", rws_users={"Default User": secret}))
    assert problems and not any(secret in p for p in problems), problems


def test_an_empty_file_names_the_missing_section(tmp_path: Path):
    empty = tmp_path / "cell.toml"
    empty.write_text("# nothing here\n")
    with pytest.raises(ConfigError) as info:
        load_config(empty)
    assert any("[cell]" in p and "empty" in p for p in info.value.problems), info.value.problems


# ---- issue 43: every number and list bounded to what the hardware and the machine can hold


@pytest.mark.parametrize(
    ("section", "values", "expected"),
    [
        ("robot", {"egm_reply_cpus": list(range(1000)) * 1000}, "at most 1024 items"),
        ("robot", {"egm_reply_cpus": [2, 2]}, "a CPU is named twice"),
        ("zenoh", {"listen": ["tcp/127.0.0.1:7447"] * 1_000_000}, "at most 64 items"),
        ("zenoh", {"connect": ["tcp/127.0.0.1:7447"] * 65}, "at most 64 items"),
        ("router", {"listen": ["tcp/0.0.0.0:7447"] * 65}, "at most 64 items"),
        ("robot", {"egm_max_speed_deviation_deg_s": 1e30}, "fastest joint (360 deg/s)"),
        ("robot", {"egm_max_pos_deviation_deg": 1e30}, "more than any joint's whole range"),
        ("scan", {"speed_mm_s": 1e9}, "scan.speed_mm_s (1e+09 mm/s) is beyond the robot's TCP speed cap"),
        ("scan", {"transit_speed_mm_s": 1e9}, "scan.transit_speed_mm_s (1e+09 mm/s) is beyond"),
        ("locate", {"speed_mm_s": 1e9}, "locate.speed_mm_s (1e+09 mm/s) is beyond"),
        ("robot", {"tcp_speed_max_mm_s": 1e-300}, "below 1 mm/s: no scan would end"),
        (
            "robot.sensor_in_flange",
            {"pos_mm": [1e9, 0.0, 0.0]},
            "beyond 3000 mm (the IRB 4600 reaches 2.55 m)",
        ),
        ("scan", {"publish_max_points": 0}, "0 no longer turns the bound off"),
        ("scan", {"publish_max_points": 10**12}, "beyond 400000000"),
        ("laser", {"buffer_profiles": 10**12}, "beyond 1000000"),
        ("cell", {"data_dir": "/etc"}, "cell.data_dir: '/etc' is a system directory"),
        ("cell", {"data_dir": "/usr/local/cell"}, "(/usr)"),
        ("cell", {"designs_dir": "/"}, "cell.designs_dir: '/' is a system directory"),
        ("cell", {"designs_dir": "/proc/self"}, "(/proc)"),
        ("worker", {"data_dir": "/var/lib"}, "worker.data_dir: '/var/lib' is a system directory"),
    ],
)
def test_values_beyond_what_the_hardware_or_the_machine_can_hold_are_refused_with_a_reason(
    shipped: dict, section: str, values: dict, expected: str
):
    problems = _problems(_with(shipped, section, **values))
    assert any(expected in p for p in problems), problems
    assert all("\n" not in p and len(p) < 400 for p in problems)  # one readable line each


def test_a_track_may_take_a_position_deviation_up_to_its_travel_in_mm(shipped: dict):
    track = {"travel_min_mm": 0.0, "travel_max_mm": 8000.0}
    data = _with(_with(shipped, "sim", egm_track_start_mm=100.0), "robot", track=track)
    cfg = parse_config(_with(data, "robot", egm_max_pos_deviation_deg=8000.0))
    assert cfg.robot.egm_max_pos_deviation_deg == 8000.0
    problems = _problems(_with(data, "robot", egm_max_pos_deviation_deg=1e30))
    assert any("the longest track's travel in mm" in p for p in problems), problems


def test_a_directory_of_the_cells_own_is_accepted(shipped: dict, tmp_path: Path):
    for d in ("/var/lib/cellctl/data", "/home/cell/data", "data", str(tmp_path)):
        assert parse_config(_with(shipped, "cell", data_dir=d, designs_dir=d)).cell.data_dir == Path(d)


def test_config_check_refuses_a_secrets_file_others_may_read(shipped: dict, tmp_path: Path, capsys):
    import argparse

    from cellctl.commands.config_cmd import run_check

    secret = tmp_path / "rws.secret"
    secret.write_text("robotics\n")
    secret.chmod(0o644)
    lines = (Path(__file__).resolve().parents[2] / "cell.toml").read_text()
    cfg = tmp_path / "cell.toml"
    cfg.write_text(lines.replace("[robot]\n", f'[robot]\nrws_password_file = "{secret}"\n', 1))
    assert run_check(argparse.Namespace(file=str(cfg))) == 2  # "ok" before: only the daemon refused it
    err = capsys.readouterr().err
    assert "robot.rws_password_file: secrets file has mode 644" in err and "chmod 600" in err
    assert "robotics" not in err
    secret.chmod(0o600)
    assert run_check(argparse.Namespace(file=str(cfg))) == 0
    assert capsys.readouterr().out.strip() == "ok"
