"""Conformance: `cellctl sim` driven by abb-robot-client (PyPI), an RWS 1.0 + EGM client nobody here wrote.

abb-robot-client is used with real IRC5 controllers; it compares Content-Type strings exactly, reads
errors from ``_embedded.status``, finds the subscription's websocket by a regex over the 201 XHTML
body and parses events with line-bound regexes. Everything goes over loopback to the `cellctl sim`
process: its RWS 1.0 server (HTTP, digest) and its EGM side (the controller is the UDP client and
sends to ``[robot] egm_host:egm_port`` of cell.toml, where abb-robot-client's ``EGM`` listens).
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
import time
from pathlib import Path

import abb_robot_client.rws as rws_mod
import numpy as np
import pytest

from cellctl.commands.demo_cmd import Processes, demo_config, to_toml, wait_ready_line
from cellctl.config import load_config

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sim_cell(tmp_path_factory):
    """`cellctl sim` on free loopback ports; yields (rws base URL, EGM UDP port, config)."""
    out = tmp_path_factory.mktemp("abbclient")
    cfg = demo_config(load_config(REPO / "cell.toml").model_dump(mode="json"), out)
    cfg["sim"]["fault_control"] = False
    (out / "logs").mkdir()
    path = out / "cell.toml"
    path.write_text(to_toml(cfg), encoding="utf-8")
    env = dict(os.environ, CELL_RWS_PASSWORD="robotics")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    procs = Processes(out / "logs", path, env)
    try:
        proc = procs.start("sim", "sim")
        ready = wait_ready_line(out / "logs" / "sim.out", proc, 120.0)
        assert ready["rws_profile"] == "rws1"
        yield ready["rws_url"], cfg["robot"]["egm_port"], cfg
    finally:
        codes = procs.stop_all()
        assert codes.get("sim") == 0, (out / "logs" / "sim.log").read_text()[-3000:]


def test_abb_robot_client_reads_the_controller_and_runs_an_egm_session_on_the_simulator(sim_cell):
    base_url, egm_port, cfg = sim_cell
    rws = rws_mod.RWS(base_url, "Default User", "robotics")
    events: queue.Queue = queue.Queue()
    sub = None
    # abb-robot-client's EGM listens in a child process (see abb_client_egm_guidance.py)
    guidance = subprocess.Popen(
        [
            sys.executable,
            str(Path(__file__).with_name("abb_client_egm_guidance.py")),
            str(egm_port),
            "2.0",
            "30",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert json.loads(guidance.stdout.readline()) == {"ready": True}
        # panel, execution, position
        assert rws.get_controller_state() == "motoroff"
        assert rws.get_operation_mode() == "AUTO"
        assert rws.get_execution_state().ctrlexecstate == "stopped"
        jt = rws.get_jointtarget()
        np.testing.assert_allclose(jt.robax, cfg["sim"]["egm_q_start_deg"], atol=1e-6)
        tasks = rws.get_tasks()
        assert tasks["T_ROB1"].active and tasks["T_ROB1"].motiontask

        # RAPID variable round trip (a CellEgm setting the session does not depend on)
        before = rws.get_rapid_variable_num("egm_cond_time_s")
        rws.set_rapid_variable_num("egm_cond_time_s", 123456.5)
        assert rws.get_rapid_variable_num("egm_cond_time_s") == 123456.5
        rws.set_rapid_variable_num("egm_cond_time_s", before)
        assert rws.get_rapid_variable("egm_end") == "FALSE"

        # the controller's error body reaches abb-robot-client as its ABBException with the code
        with pytest.raises(rws_mod.ABBException) as err:
            rws.get_rapid_variable("no_such_variable")
        assert err.value.code == -1073414146

        # a wrong password is refused
        wrong = rws_mod.RWS(base_url, "Default User", "not-the-password")
        # abb-robot-client raises a bare Exception for an HTTP error status (not its ABBException)
        with pytest.raises(Exception, match=r"^Robot returning HTTP error 401$") as refused:
            wrong.get_controller_state()
        assert type(refused.value) is Exception

        # subscription: websocket with robapi2_subscription, XHTML events
        sub = rws.subscribe(
            [
                rws_mod.SubscriptionResourceRequest(
                    rws_mod.SubscriptionResourceType.ControllerState,
                    rws_mod.SubscriptionResourcePriority.Medium,
                ),
                rws_mod.SubscriptionResourceRequest(
                    rws_mod.SubscriptionResourceType.ExecutionState,
                    rws_mod.SubscriptionResourcePriority.Medium,
                ),
            ],
            events.put,
        )
        time.sleep(0.5)  # the websocket opens on abb-robot-client's thread

        # motors on; the event log shows it
        rws.set_controller_state("motoron")
        assert rws.get_controller_state() == "motoron"
        log = rws.read_event_log()
        assert log and log[0].code == 10011 and log[0].msgtype == 1 and log[0].title

        # start RAPID: CellEgm enters EGMRunJoint, EGM joint guidance moves axis 1 by 2 degrees
        rws.start(cycle="once", tasks=["T_ROB1"])  # CellEgm enters EGMRunJoint
        assert rws.get_execution_state().ctrlexecstate == "running"
        out, _ = guidance.communicate(timeout=60)
        result = json.loads(out.strip().splitlines()[-1])
        assert result["q0"] is not None, "no EgmRobot of a running session reached abb-robot-client"
        q0, q = np.array(result["q0"]), np.array(result["q"])
        assert abs(q[0] - (q0[0] + 2.0)) < 0.02, (q0, q)
        np.testing.assert_allclose(q[1:], q0[1:], atol=0.02)
        np.testing.assert_allclose(rws.get_jointtarget().robax[0], q0[0] + 2.0, atol=0.05)

        # stop
        rws.stop()
        assert rws.get_execution_state().ctrlexecstate == "stopped"
        seen = []
        with_deadline = time.monotonic() + 5.0
        while time.monotonic() < with_deadline and not (
            rws_mod.ControllerState("motoron") in seen
            and rws_mod.RAPIDExecutionState("running", "") in seen
            and rws_mod.RAPIDExecutionState("stopped", "") in seen
        ):
            with contextlib.suppress(queue.Empty):
                seen.append(events.get(timeout=0.2))
        assert rws_mod.ControllerState("motoron") in seen, seen
        assert rws_mod.RAPIDExecutionState("running", "") in seen, seen
        assert rws_mod.RAPIDExecutionState("stopped", "") in seen, seen
    finally:
        if sub is not None:
            sub.close()
        if guidance.poll() is None:
            guidance.kill()
            guidance.wait()
        rws.close()
