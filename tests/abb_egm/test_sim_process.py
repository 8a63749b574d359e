"""The simulated controller as its own process: addresses on stdout, EGM and RWS served, clean exit."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from drivers.abb_egm.codec import MciState, MotorState
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.limits import LinearTrack
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.abb_egm.sim.controller import ABB_DEFAULT_PASSWORD, ControllerSim, ControllerSimConfig
from drivers.abb_egm.sim.controller import main as sim_main
from drivers.abb_egm.sim.egm import EgmSimConfig
from drivers.runtime import precise_event_loop

pytestmark = pytest.mark.process  # the simulator as `python -m drivers.abb_egm.sim`

REPO = Path(__file__).resolve().parents[2]


def _spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "drivers.abb_egm.sim", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"},
    )


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sim_process_prints_its_ports_serves_egm_and_rws_and_exits_cleanly_on_signal(sig):
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0))
        _, port = await ep.start()
        proc = _spawn("--egm-port", str(port), "--rws-port", "0", "--start")
        try:
            line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 30.0)
            addresses = json.loads(line)
            assert addresses["egm_sensor"] == ["127.0.0.1", port]
            state = await ep.wait_for_feedback(5.0)
            assert state.motor_state is MotorState.ON
            await ep.wait_for_feedback(1.0)
            assert ep.latest.mci_state is MciState.RUNNING and ep.ok_to_command
            assert list(ep.controller_address) == addresses["egm_local"]
            url = addresses["rws_url"] + "/rw/panel/ctrlstate?json=1"
            async with aiohttp.ClientSession() as http, http.get(url) as resp:
                assert resp.status == 401
                assert resp.headers["WWW-Authenticate"].startswith("Digest")
            proc.send_signal(sig)
            rc = await asyncio.wait_for(asyncio.to_thread(proc.wait), 10.0)
            assert rc == 0, proc.stderr.read()
            assert "controller_sim_shutdown" in proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            await ep.close()

    asyncio.run(main())


def test_sim_entry_point_rejects_a_bad_fault_value_with_a_clear_message(capsys):
    assert sim_main(["--egm-port", "6511", "--loss", "1.5"]) == 2
    err = capsys.readouterr().err
    assert "loss_fraction" in err and "Traceback" not in err


TRACK = LinearTrack(
    origin_mm=[0.0, -1000.0, 0.0], direction=[1.0, 0.0, 0.0], travel_min_mm=0.0, travel_max_mm=3000.0,
    speed_max_mm_s=400.0, accel_max_mm_s2=2000.0,
)  # fmt: skip


@pytest.mark.parametrize(
    ("profile", "track"),
    [("rws1", None), ("rws1", TRACK), ("rws2", TRACK)],
    ids=["arm", "track", "track-rws2"],
)
def test_composed_sim_starts_egm_when_the_program_starts_and_reports_positions_to_rws(profile, track):
    """Driven only through its protocols: motors and program through RWS, motion through EGM; the
    joints RWS reports are the ones the EGM feedback carried (two independent observations). With a
    track, its position comes back in the jointtarget's and robtarget's ``eax_a`` (mm), the other
    external axes unused; without one, all six are unused."""

    async def main():
        n_ext = 0 if track is None else 1
        ep = EgmEndpoint(EgmEndpointConfig(port=0, n_external=n_ext))
        _, port = await ep.start()
        egm_cfg = EgmSimConfig(sensor_port=port, track=track, track_start_mm=1000.0)
        sim = ControllerSim(ControllerSimConfig(rws_profile=profile), egm_cfg)
        addresses = await sim.start()
        assert addresses["rws_url"].startswith("http")
        tls = {} if profile == "rws1" else {"tls_ca_file": sim.rws.cert_path}
        rws = RwsClient(RwsClientConfig(base_url=addresses["rws_url"], profile=profile,
                                        username="Default User", password=ABB_DEFAULT_PASSWORD, **tls))  # fmt: skip
        try:
            await ep.wait_for_feedback(10.0)
            assert not ep.ok_to_command
            await rws.motors_on()
            await rws.start_rapid()
            for _ in range(500):
                await ep.wait_for_feedback(10.0)
                if ep.ok_to_command:
                    break
            assert ep.ok_to_command
            step = np.array([2.0, 0, 0, 0, 0, 0]) if track is None else np.array([25.0, 2.0, 0, 0, 0, 0, 0])
            target = ep.latest.axes_mm_deg + step
            ep.command_joints(target)
            for _ in range(2500):  # until the feedback reached the target (about 0.3 s idle)
                await ep.wait_for_feedback(10.0)
                if np.abs(ep.latest.axes_mm_deg - target).max() < 0.01:
                    break
            fed_back = ep.latest.axes_mm_deg
            np.testing.assert_allclose(fed_back, target, atol=0.01)
            joints = await rws.get_mechunit_joints()
            # the arm holds the target: what RWS reads now is what EGM fed back
            np.testing.assert_allclose(joints.q_deg, fed_back[n_ext:], atol=0.01)
            assert joints.q_deg[0] > 1.0
            np.testing.assert_allclose(await rws.get_joint_position(), joints.q_deg, atol=0.01)
            pose = await rws.get_cartesian()
            if track is None:
                assert joints.external_axes_mm == pose.external_axes_mm == (None,) * 6
            else:
                # the track: eax_a in mm, the same in the robtarget, the others unused
                assert joints.external_axes_mm[0] == pytest.approx(fed_back[0], abs=0.01)
                assert joints.external_axes_mm[0] > 1020.0
                assert joints.external_axes_mm[1:] == pose.external_axes_mm[1:] == (None,) * 5
                assert pose.external_axes_mm[0] == pytest.approx(joints.external_axes_mm[0], abs=0.01)
        finally:
            await rws.close()
            await sim.stop()
            await ep.close()

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        runner.run(main())


def test_sim_process_fault_channel_sets_egm_faults_over_tcp_and_refuses_bad_requests():
    """The fault channel of ``--fault-port``: one JSON line in, one out, on the same connection;
    a refused request changes nothing and leaves the channel serving. The effect is observed over
    EGM (``stop_sending``: the feedback stops, and resumes when it is switched off)."""

    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0))
        _, port = await ep.start()
        proc = _spawn("--egm-port", str(port), "--start", "--fault-port", "0",
                      "--q-start-deg", "0", "10", "-10", "0", "30", "0")  # fmt: skip
        try:
            addresses = json.loads(await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 30.0))
            await ep.wait_for_feedback(10.0)
            np.testing.assert_allclose(ep.latest.q_deg, [0.0, 10.0, -10.0, 0.0, 30.0, 0.0], atol=1e-6)
            reader, writer = await asyncio.open_connection(*addresses["fault"])

            async def ask(line: bytes) -> dict:
                writer.write(line + b"\n")
                await writer.drain()
                return json.loads(await asyncio.wait_for(reader.readline(), 10.0))

            state = await ask(b"{}")
            assert state["ok"] and state["egm"]["stop_sending"] is False and state["stats"]["sent"] > 0
            bad = await ask(json.dumps({"egm": {"bogus_knob": 1}}).encode())
            assert not bad["ok"] and "bogus_knob" in bad["error"]
            assert not (await ask(json.dumps({"egm": {"loss_fraction": 2.0}}).encode()))["ok"]
            assert not (await ask(json.dumps({"rws": {}}).encode()))["ok"]
            assert "not a JSON line" in (await ask(b"{nope"))["error"]
            stopped = await ask(json.dumps({"egm": {"stop_sending": True}}).encode())
            assert stopped["ok"] and stopped["egm"]["stop_sending"] is True
            assert stopped["egm"]["loss_fraction"] == 0.0  # the refused request changed nothing
            await asyncio.sleep(0.1)  # stays: what was in flight lands before nothing more may come
            with pytest.raises(TimeoutError):
                await ep.wait_for_feedback(0.5)
            assert (await ask(json.dumps({"egm": {"stop_sending": False}}).encode()))["ok"]
            await ep.wait_for_feedback(10.0)
            writer.close()
            proc.send_signal(signal.SIGTERM)
            assert await asyncio.wait_for(asyncio.to_thread(proc.wait), 10.0) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            await ep.close()

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        runner.run(main())
