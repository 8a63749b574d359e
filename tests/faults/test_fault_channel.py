"""The simulator's fault-control channel (``<prefix>/sim/faults``) over loopback, against a real `cellctl sim`.

What each knob does is checked through the simulators' own protocols where one is at hand (RWS over
HTTP); the rest through the reply's knobs and counters. The fault-injection cases in this directory
check what the daemon makes of them.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess

import pytest

from cellctl.daemon.wiring import rws_client_config
from cellctl.simcell.faults import (
    FaultChannelError,
    FaultRequestError,
    parse_assignments,
    parse_fault_request,
)
from drivers.abb_egm.rws_client import RwsClient, RwsError
from tests.support.faultcell import REPO, FaultCell

pytestmark = pytest.mark.e2e  # the simulator cell runs as its own process


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("faultsim")
    cell = FaultCell.create(out, start=False)
    cell.start(run=False, worker=False)
    try:
        yield cell
    finally:
        codes = cell.stop()
        assert all(code == 0 for code in codes.values()), codes


def _rws(cell: FaultCell, timeout_s: float = 2.0) -> RwsClient:
    password = os.environ.get("CELL_RWS_PASSWORD", "robotics")
    return RwsClient(rws_client_config(cell.cfg.robot, password, timeout_s=timeout_s))


def test_ready_line_names_the_fault_endpoint_and_an_empty_request_only_reports(sim: FaultCell):
    assert sim.ready["fault_control"] == sim.cfg.sim.fault_listen
    st = sim.fault_sync()
    assert st.applied == []
    assert st.egm["loss_fraction"] == 0.0 and st.egm["stop_sending"] is False
    assert st.rws == {"errors": {}, "delays_s": {}, "serving": True}
    assert st.laser["disconnect_after_frames"] is None
    assert st.stats["egm"]["cycles"] > 0  # the controller is cycling


def test_egm_knobs_stay_in_force_and_a_partial_update_keeps_the_others(sim: FaultCell):
    async def go():
        a = await sim.fault(egm={"loss_fraction": 0.05, "burst_ms": 50})
        b = await sim.fault(egm={"duplicate_fraction": 0.1})
        c = await sim.fault(clear=True)
        return a, b, c

    a, b, c = asyncio.run(go())
    assert a.applied == ["egm"] and a.egm["loss_fraction"] == 0.05 and a.egm["burst_ms"] == 50.0
    assert b.egm["loss_fraction"] == 0.05 and b.egm["duplicate_fraction"] == 0.1
    assert c.egm["loss_fraction"] == 0.0 and c.egm["duplicate_fraction"] == 0.0


def test_bad_requests_get_an_error_naming_the_knob_and_the_channel_keeps_serving(sim: FaultCell):
    async def go():
        errors = {}
        for name, body in {
            "unknown_section": {"robot": {"x": 1}},
            "unknown_knob": {"egm": {"bogus": 1}},
            "out_of_range": {"egm": {"loss_fraction": 1.5}},
            "bad_action": {"controller": {"action": "explode"}},
            "nested": {"laser": {"corrupt": {"mode": "noise"}}},
        }.items():
            with pytest.raises(FaultChannelError) as exc:
                await sim.fault(body)
            errors[name] = (exc.value.error.code, exc.value.error.field)
        # raw bytes: not JSON, and too large
        from cellctl.api.session import async_get
        from cellctl.simcell.faults import sim_faults_key

        await sim.fault()  # opens the session
        raw = {}
        for name, payload in {
            "not_json": b"{egm",
            "too_large": b"{" + b" " * 20000 + b"}",
            "list": b"[1]",
        }.items():
            replies = await async_get(sim._fault_session, sim_faults_key(sim.cfg.key_prefix), payload=payload)
            assert replies and replies[0].ok is None
            raw[name] = json.loads(replies[0].err.payload.to_bytes())
        after = await sim.fault(egm={"loss_fraction": 0.0})
        return errors, raw, after

    errors, raw, after = asyncio.run(go())
    assert errors == {
        "unknown_section": ("invalid", "robot"),
        "unknown_knob": ("invalid", "egm.bogus"),
        "out_of_range": ("invalid", "egm.loss_fraction"),
        "bad_action": ("invalid", "controller.action"),
        "nested": ("invalid", "laser.corrupt.mode"),
    }
    assert raw["not_json"]["code"] == "malformed" and raw["not_json"]["field"] == "payload"
    assert raw["too_large"]["code"] == "too_large"
    assert raw["list"]["code"] == "malformed"
    assert after.applied == ["egm"]


def test_controller_actions_are_seen_through_rws_and_a_refused_action_changes_nothing(sim: FaultCell):
    async def go():
        seen = []
        async with _rws(sim) as rws:
            for action in ("motors_on", "emergency_stop", "reset_emergency_stop", "motors_on", "guard_stop",
                           "reset_guard_stop"):  # fmt: skip
                st = await sim.fault(controller={"action": action})
                seen.append((action, st.controller["ctrl_state"], await rws.get_ctrl_state()))
            with pytest.raises(FaultChannelError) as refused:
                await sim.fault(controller={"action": "reset_emergency_stop"}, egm={"loss_fraction": 0.5})
            st = await sim.fault()
            return seen, refused.value, st

    seen, refused, st = asyncio.run(go())
    assert seen == [
        ("motors_on", "motoron", "motoron"),
        ("emergency_stop", "emergencystop", "emergencystop"),
        ("reset_emergency_stop", "emergencystopreset", "emergencystopreset"),
        ("motors_on", "motoron", "motoron"),
        ("guard_stop", "guardstop", "guardstop"),
        ("reset_guard_stop", "motoroff", "motoroff"),
    ]
    assert refused.error.code == "not_allowed" and refused.error.field == "controller.action"
    assert st.egm["loss_fraction"] == 0.0  # the refused request applied nothing


def test_rws_errors_delays_and_a_stopped_server_are_what_an_rws_client_meets(sim: FaultCell):
    async def go():
        out = {}
        await sim.fault(rws={"error_status": 503})
        async with _rws(sim) as rws:
            with pytest.raises(RwsError) as e503:
                await rws.get_ctrl_state()
        out["503"] = e503.value.status
        await sim.fault(rws={"error_status": 0, "delay_s": 3.0})
        async with _rws(sim, timeout_s=1.0) as rws:
            with pytest.raises(RwsError) as slow:
                await rws.get_ctrl_state()
        out["slow"] = type(slow.value).__name__
        st = await sim.fault(rws={"delay_s": 0, "serving": False})
        out["down_state"] = st.rws
        async with _rws(sim) as rws:
            with pytest.raises(RwsError) as refused:
                await rws.get_ctrl_state()
        out["refused"] = refused.value.status
        st = await sim.fault(rws={"serving": True})
        out["up_state"] = st.rws
        async with _rws(sim) as rws:
            out["after"] = await rws.get_ctrl_state()
        return out

    out = asyncio.run(go())
    assert out["503"] == 503
    assert out["slow"] == "RwsTimeoutError"
    assert out["down_state"]["serving"] is False and out["refused"] == 0  # no HTTP answer at all
    assert out["up_state"] == {"errors": {}, "delays_s": {}, "serving": True}
    assert out["after"] in ("motoron", "motoroff", "guardstop", "emergencystop", "emergencystopreset")


def test_laser_knobs_are_in_force_and_clear_switches_them_off(sim: FaultCell):
    async def go():
        a = await sim.fault(laser={"disconnect_after_frames": 40, "corrupt": {"groups": 2, "mode": "framing"},
                                   "stall_s": 5.0, "clock_jump_ms": 250.0, "drop_frames": 3})  # fmt: skip
        b = await sim.fault(laser={"clock_jump_ms": -50.0})
        c = await sim.fault(clear=True)
        return a, b, c

    a, b, c = asyncio.run(go())
    assert a.laser["disconnect_after_frames"] == 40 and a.laser["corrupt_groups"] == 2
    assert a.laser["corrupt_mode"] == "framing" and a.laser["drop_frames"] == 3
    assert 4.0 < a.laser["stall_remaining_s"] <= 5.0
    assert b.laser["clock_jump_ms"] == pytest.approx(200.0)
    assert c.laser["disconnect_after_frames"] is None and c.laser["stall_remaining_s"] == 0.0
    assert c.laser["corrupt_groups"] == 0 and c.laser["drop_frames"] == 0


def test_cli_sends_knobs_and_prints_the_state_or_a_clear_error(sim: FaultCell, cellctl_exe):
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    base = [*cellctl_exe, "sim", "fault", "--config", str(sim.config_path)]
    ok = subprocess.run([*base, "egm.jitter_ms=2", "--json", '{"egm": {"delay_ms": 1}}'],
                        capture_output=True, text=True, timeout=120, env=env)  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    state = json.loads(ok.stdout)
    assert state["egm"]["jitter_ms"] == 2.0 and state["egm"]["delay_ms"] == 1.0
    bad = subprocess.run([*base, "egm.bogus=1"], capture_output=True, text=True, timeout=120, env=env)
    assert bad.returncode == 1 and "egm.bogus" in bad.stderr and "unknown fault knob" in bad.stderr
    syntax = subprocess.run([*base, "egm"], capture_output=True, text=True, timeout=120, env=env)
    assert syntax.returncode == 2 and "section.knob=value" in syntax.stderr
    sim.fault_sync(clear=True)


def test_assignments_become_the_nested_payload_and_bad_ones_name_the_item():
    items = ["egm.loss_fraction=0.05", "controller.action=motors_off", "laser.corrupt.groups=3", "clear=true"]
    assert parse_assignments(items) == {
        "egm": {"loss_fraction": 0.05},
        "controller": {"action": "motors_off"},
        "laser": {"corrupt": {"groups": 3}},
        "clear": True,
    }
    with pytest.raises(FaultRequestError) as exc:
        parse_assignments(["egm.=1"])
    assert exc.value.field == "egm.=1"
    with pytest.raises(FaultRequestError) as exc:
        parse_fault_request(b'{"laser": {"stall_s": -1}}')
    assert exc.value.field == "laser.stall_s"


def test_cli_without_a_simulator_says_so_instead_of_hanging(tmp_path, cellctl_exe):
    from tests.support.faultcell import fault_cell_config

    cfg = fault_cell_config(tmp_path)
    r = subprocess.run([*cellctl_exe, "sim", "fault", "--config", str(cfg), "--timeout", "2"],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 1
    assert "cellctl sim" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_fault_control_off_serves_no_channel(tmp_path):
    cell = FaultCell(tmp_path, fault_cell_config_off(tmp_path))
    try:
        from cellctl.commands.demo_cmd import wait_ready_line

        p = cell.procs.start("sim", "sim")
        ready = wait_ready_line(tmp_path / "logs" / "sim.out", p, 120.0)
        assert ready["fault_control"] is None
        with pytest.raises(FaultChannelError):
            asyncio.run(_quick_fault(cell))
    finally:
        assert all(c == 0 for c in cell.stop().values())


def fault_cell_config_off(out):
    from tests.support.faultcell import fault_cell_config

    return fault_cell_config(out, sim__fault_control=False)


async def _quick_fault(cell: FaultCell):
    from cellctl.api.session import ZenohSetupError, close_session
    from cellctl.simcell.faults import open_fault_session, send_faults

    try:
        session = await asyncio.to_thread(open_fault_session, cell.cfg, role="connect")
    except ZenohSetupError as exc:
        raise FaultChannelError(str(exc)) from None
    try:
        return await send_faults(session, cell.cfg.key_prefix, {}, timeout_s=2.0)
    finally:
        close_session(session)
