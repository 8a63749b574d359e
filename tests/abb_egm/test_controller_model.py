"""Controller model: panel states, the CellEgm program model, RAPID literals, IO, event log."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.abb_egm import rapid_values as rv
from drivers.abb_egm.rapid_values import (
    JointTarget,
    RapidValueError,
    format_bool,
    format_jointtarget,
    format_num,
    format_string,
    parse_bool,
    parse_jointtarget,
    parse_num,
    parse_string,
)
from drivers.abb_egm.sim.model import (
    EVENT_EGM_COMM_TIMEOUT,
    AccessDenied,
    ControllerModel,
    StateRefused,
    SymbolNotFound,
)

T = "T_ROB1"
RAPID_FILE = Path(__file__).resolve().parents[2] / "drivers" / "abb_egm" / "rapid" / "CellEgm.mod"


def running_model() -> ControllerModel:
    m = ControllerModel()
    m.motors_on()
    m.start_rapid()
    return m


# ---- panel ------------------------------------------------------------------------------------


def test_motors_on_is_refused_during_emergency_stop_until_reset() -> None:
    m = ControllerModel()
    m.emergency_stop()
    with pytest.raises(StateRefused, match="emergencystop"):
        m.motors_on()
    m.reset_emergency_stop()
    assert m.ctrl_state == "emergencystopreset"
    m.motors_on()
    assert m.ctrl_state == "motoron"


def test_motors_on_is_refused_in_manual_mode() -> None:
    m = ControllerModel(opmode="MANR")
    with pytest.raises(StateRefused, match="MANR"):
        m.motors_on()


def test_start_is_refused_with_motors_off_in_auto() -> None:
    m = ControllerModel()
    with pytest.raises(StateRefused, match="motors are not on") as err:
        m.start_rapid()
    assert err.value.code < 0
    assert m.rapid_state == "stopped"


def test_guard_stop_stops_the_program_and_needs_a_reset() -> None:
    m = running_model()
    m.guard_stop()
    assert (m.ctrl_state, m.rapid_state, m.egm_wanted) == ("guardstop", "stopped", False)
    with pytest.raises(StateRefused):
        m.motors_on()
    m.reset_guard_stop()
    m.motors_on()
    m.start_rapid()
    assert m.egm_wanted  # the suspended session continues


def test_reset_pp_is_refused_while_running() -> None:
    m = running_model()
    with pytest.raises(StateRefused, match="running"):
        m.reset_pp()


def test_opmode_change_stops_program_and_motors() -> None:
    m = running_model()
    m.set_opmode("MANR")
    assert (m.opmode, m.ctrl_state, m.rapid_state) == ("MANR", "motoroff", "stopped")


# ---- EGM program model ------------------------------------------------------------------------


def test_egm_is_wanted_only_with_motors_on_program_running_and_end_false() -> None:
    m = ControllerModel()
    assert not m.egm_wanted
    m.motors_on()
    assert not m.egm_wanted
    m.start_rapid()
    assert m.egm_wanted
    assert m.get_num(T, None, "egm_status") == 1
    m.stop_rapid()
    assert not m.egm_wanted
    m.start_rapid()  # continues inside EGMRunJoint
    assert m.egm_wanted
    m.motors_off()
    assert not m.egm_wanted and m.rapid_state == "stopped"


def test_writing_the_end_variable_ends_the_session_and_the_program() -> None:
    m = running_model()
    changes: list[tuple[str, dict]] = []
    m.subscribe(lambda k, d: changes.append((k, d)))
    m.set_bool(T, None, "egm_end", True)
    assert not m.egm_wanted
    assert m.rapid_state == "stopped"
    assert m.get_num(T, None, "egm_status") == 2
    assert ("egm", {"wanted": False}) in changes
    assert ("execution", {"ctrlexecstate": "stopped", "pp": "main"}) in changes
    # The next start is a fresh session: main resets egm_end.
    m.start_rapid()
    assert m.egm_wanted and m.get_bool(T, None, "egm_end") is False


def test_end_signal_ends_the_session_and_is_cleared_by_the_module() -> None:
    m = running_model()
    m.set_io("DO_EGM_END", 1)
    assert not m.egm_wanted and m.rapid_state == "stopped"
    assert m.get_num(T, None, "egm_status") == 2
    assert m.get_io("DO_EGM_END") == 0


def test_end_written_while_stopped_takes_effect_on_restart() -> None:
    m = running_model()
    m.stop_rapid()
    m.set_bool(T, None, "egm_end", True)
    assert m.get_num(T, None, "egm_status") == 1  # the trap has not run yet
    m.start_rapid()
    assert m.rapid_state == "stopped" and m.get_num(T, None, "egm_status") == 2


def test_comm_timeout_logs_41822_and_runs_the_error_handler() -> None:
    m = running_model()
    m.egm_session_ended("no EgmSensor for 1.0 s", EVENT_EGM_COMM_TIMEOUT)
    ev = m.events[0]
    assert (ev.code, ev.msgtype, ev.title) == (41822, 3, "No data from the UdpUc device")
    assert m.get_num(T, None, "egm_status") == -41822
    assert m.rapid_state == "stopped" and not m.egm_wanted
    assert m.egm_params is None


def test_other_egm_error_sets_status_minus_one_and_logs_its_code() -> None:
    m = running_model()
    m.egm_session_ended("joint 2 reference beyond its limit", 41820)
    assert m.events[0].code == 41820
    assert m.get_num(T, None, "egm_status") == -1
    assert m.rapid_state == "stopped"


def test_egm_params_are_read_from_the_rapid_variables_at_start() -> None:
    m = ControllerModel()
    m.set_num(T, None, "egm_comm_timeout_s", 2.5)
    m.set_num(T, None, "egm_pos_corr_gain", 0.5)
    m.set_num(T, None, "egm_max_speed_dev_dps", 200)
    m.motors_on()
    m.start_rapid()
    p = m.egm_params
    assert p is not None
    assert (p.comm_timeout_s, p.pos_corr_gain, p.max_speed_deviation_deg_s) == (2.5, 0.5, 200.0)
    m.set_num(T, None, "egm_comm_timeout_s", 9)  # changes during a session wait for the next one
    assert m.egm_params is not None and m.egm_params.comm_timeout_s == 2.5


def test_rapid_module_declares_every_variable_the_model_uses() -> None:
    """The simulator's program model and CellEgm.mod must not drift apart."""
    text = RAPID_FILE.read_text()
    m = ControllerModel()
    declared = {name: rtype for rtype, name in re.findall(r"PERS\s+(\w+)\s+(\w+)\s*:=", text)}
    names = [n for (t, mod, n) in m._vars if t == T and mod == "CellEgm"]
    assert len(names) == len(declared) == 10
    for name in names:
        assert name in declared, f"{name} missing from CellEgm.mod"
        assert declared[name] == m.var_info(T, "CellEgm", name).rapid_type
    assert re.search(r"^MODULE\s+CellEgm\b", text, re.M)
    assert "-41822" in text and f'EGM_DEVICE:="{"EGM_DAEMON"}"' in text
    for instr in ("EGMGetId", "EGMSetupUC", "EGMActJoint", "EGMRunJoint", "EGMStop", "EGMReset"):
        assert instr in text
    assert rv.SIGNAL_END in text


def test_rapid_module_defaults_equal_the_model_defaults() -> None:
    text = RAPID_FILE.read_text()
    m = ControllerModel()
    for rtype, name, value in re.findall(r"PERS\s+(\w+)\s+(\w+)\s*:=\s*([^;]+);", text):
        literal = m.get_var(T, "CellEgm", name)
        if rtype == "num":
            assert parse_num(literal) == parse_num(value), name
        else:
            assert parse_bool(literal) == parse_bool(value), name


# ---- variables, IO, events, listeners ---------------------------------------------------------


def test_unknown_variable_and_signal_raise_symbol_not_found_naming_them() -> None:
    m = ControllerModel()
    with pytest.raises(SymbolNotFound, match="T_ROB1/nope"):
        m.get_var(T, None, "nope")
    with pytest.raises(SymbolNotFound, match="DO_NOPE"):
        m.set_io("DO_NOPE", 1)


def test_malformed_literal_is_refused_and_value_kept() -> None:
    m = ControllerModel()
    with pytest.raises(RapidValueError, match="'yes'"):
        m.set_var(T, None, "egm_end", "yes")
    assert m.get_var(T, None, "egm_end") == "FALSE"


def test_const_and_input_signals_refuse_writes() -> None:
    m = ControllerModel()
    m.define_var(T, "CellEgm", "EGM_LIMIT", "num", "3", storage="CONST")
    with pytest.raises(AccessDenied):
        m.set_num(T, None, "EGM_LIMIT", 4)
    with pytest.raises(AccessDenied) as err:
        m.set_io("DI_PLATE_PRESENT", 1)
    assert err.value.code == rv.RC_IO_ACCESS_DENIED
    m.set_io("DI_PLATE_PRESENT", 1, force=True)  # the simulator's own wiring may
    assert m.get_io("DI_PLATE_PRESENT") == 1
    with pytest.raises(RapidValueError):
        m.set_io("DO_EGM_END", 0.5)


def test_event_log_is_bounded_and_newest_first() -> None:
    m = ControllerModel(elog_capacity=5)
    for i in range(8):
        m.log_event(80000 + i, f"event {i}", "", "warning")
    codes = [e.code for e in m.events]
    assert codes == [80007, 80006, 80005, 80004, 80003]
    with pytest.raises(RapidValueError):
        m.log_event(1, "x", "y", "fatal")


def test_a_failing_listener_does_not_break_the_model() -> None:
    m = ControllerModel()
    seen: list[str] = []

    def broken(kind: str, data: dict) -> None:
        raise RuntimeError("listener bug")

    m.subscribe(broken)
    unsubscribe = m.subscribe(lambda k, d: seen.append(k))
    m.motors_on()
    assert "ctrlstate" in seen
    unsubscribe()
    m.motors_off()
    assert seen.count("ctrlstate") == 1


def test_position_defaults_to_the_all_zero_flange_pose() -> None:
    q, pos, quat = ControllerModel().position()
    np.testing.assert_allclose(q, 0)
    np.testing.assert_allclose(pos, [1580, 0, 1765])
    np.testing.assert_allclose(np.linalg.norm(quat), 1.0)


# ---- RAPID literal codec ----------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e12, max_value=1e12)


@given(finite)
def test_num_literal_round_trips(value: float) -> None:
    assert parse_num(format_num(value)) == pytest.approx(value, rel=1e-8, abs=1e-12)


@given(st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=80))
def test_string_literal_round_trips(value: str) -> None:
    assert parse_string(format_string(value)) == value


@given(st.lists(st.floats(min_value=-400, max_value=400, allow_nan=False), min_size=6, max_size=6))
def test_jointtarget_literal_round_trips(q: list[float]) -> None:
    jt = parse_jointtarget(format_jointtarget(np.array(q)))
    np.testing.assert_allclose(jt.robax_deg, q, rtol=1e-8, atol=1e-9)
    assert np.all(jt.extax == 9e9)


def test_literal_formats_match_rws() -> None:
    assert format_bool(True) == "TRUE" and parse_bool("false") is False
    assert format_num(9e9) == "9E+09" and format_num(2.0) == "2" and format_num(0.5) == "0.5"
    assert format_string('a"b') == '"a""b"'
    jt = JointTarget(np.arange(6.0))
    assert format_jointtarget(jt) == "[[0,1,2,3,4,5],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]"


@pytest.mark.parametrize(
    ("parser", "text"),
    [
        (parse_num, "1,5"),
        (parse_num, ""),
        (parse_bool, "1"),
        (parse_string, "abc"),
        (parse_string, '"a"b"'),
        (parse_jointtarget, "[[1,2,3],[4,5,6]]"),
        (parse_jointtarget, "[1,2,3,4,5,6]"),
    ],
)
def test_malformed_literals_raise_rapid_value_error_with_the_text(parser, text: str) -> None:
    with pytest.raises(RapidValueError) as err:
        parser(text)
    assert repr(text) in str(err.value) or text in str(err.value)


def test_non_finite_and_overlong_values_are_refused() -> None:
    with pytest.raises(RapidValueError):
        format_num(float("nan"))
    with pytest.raises(RapidValueError):
        format_string("x" * 81)
    with pytest.raises(RapidValueError):
        format_jointtarget(np.zeros(5))
