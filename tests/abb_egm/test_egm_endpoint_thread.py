"""The endpoint's dedicated reply thread: lifecycle, scheduling, hand-over to the loop, and the
simulator's kernel-stamped reply latency measured against it (all over loopback sockets)."""

from __future__ import annotations

import asyncio
import os
import socket
import sys
import threading

import numpy as np
import pytest
from structlog.testing import capture_logs

from drivers.abb_egm.codec import (
    MciState,
    MessageType,
    MotorState,
    RapidState,
    RobotMessage,
    decode_sensor,
    encode_robot,
)
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig
from drivers.runtime import precise_event_loop
from tests.support.waits import wait_until

Q0 = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])


def robot(seqno: int, q=Q0) -> bytes:
    return encode_robot(
        RobotMessage(
            seqno=seqno,
            tm_ms=seqno * 4,
            mtype=MessageType.DATA,
            feedback_q_deg=np.asarray(q, dtype=float),
            feedback_time_us=1_700_000_000_000_000 + seqno * 4032,
            motor_state=MotorState.ON,
            mci_state=MciState.RUNNING,
            rapid_exec_state=RapidState.RUNNING,
        )
    )


def controller_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    return s


async def exchange(ctl: socket.socket, addr, payload: bytes):
    """Send one EgmRobot and wait (off the loop, so the loop stays free) for the reply."""
    ctl.sendto(payload, addr)
    data, _ = await asyncio.to_thread(ctl.recvfrom, 4096)
    return decode_sensor(data)


async def handled(ep: EgmEndpoint, n: int, wait_s: float = 5.0) -> None:
    """Until the reply thread has finished ``n`` datagrams (it answers first, records after)."""
    await wait_until(lambda: ep.stats.handled >= n, wait_s / 10, f"the reply thread finishing {n} datagrams")


def reply_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "egm-reply"]


def test_reply_thread_answers_from_its_own_thread_and_close_ends_it():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        addr = await ep.start()
        ctl = controller_socket()
        try:
            assert ep.reply_thread_native_id not in (None, threading.get_native_id())
            assert len(reply_threads()) == 1
            replies = [await exchange(ctl, addr, robot(k)) for k in range(3)]
            assert [r.seqno for r in replies] == [0, 1, 2]
            await handled(ep, 3)
            assert ep.stats.replies_sent == 3 and ep.latest.seqno == 2
        finally:
            ctl.close()
            await ep.close()
        assert reply_threads() == []
        assert ep.reply_thread_native_id is None

    asyncio.run(main())


def test_close_ends_the_reply_thread_while_the_controller_keeps_sending():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        addr = await ep.start()
        stop = threading.Event()

        def flood():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            k = 0
            while not stop.is_set():
                s.sendto(robot(k), addr)
                k += 1
                stop.wait(0.0005)
            s.close()

        sender = threading.Thread(target=flood)
        sender.start()
        try:
            # the flood is under way (bounded generously: a loaded machine only delays it)
            await wait_until(lambda: ep.stats.received > 10, 3.0, "the flood under way")
            await asyncio.wait_for(ep.close(), 30.0)
            assert reply_threads() == []
        finally:
            stop.set()
            sender.join()

    asyncio.run(main())


def test_reply_thread_takes_the_configured_realtime_priority_and_cpus_or_says_why_not():
    async def main():
        cfg = EgmEndpointConfig(port=0, reply_thread=True, reply_thread_priority=7, reply_thread_cpus=(0,))
        with capture_logs() as logs:
            ep = EgmEndpoint(cfg)
            addr = await ep.start()
            ctl = controller_socket()
            try:
                await exchange(ctl, addr, robot(0))  # the thread has configured itself by now
                tid = ep.reply_thread_native_id
                policy = os.sched_getscheduler(tid)
                cpus = os.sched_getaffinity(tid)
                assert os.sched_getscheduler(0) != os.SCHED_FIFO  # only the reply thread
                # the thread's log lines reach the loop in order: the affinity's, then the priority's
                await wait_until(
                    lambda: any(e["event"].startswith("egm_reply_thread_realtime") for e in logs),
                    0.05,
                    "the reply thread's priority logged",
                )
            finally:
                ctl.close()
                await ep.close()
        events = {e["event"] for e in logs}
        if policy == os.SCHED_FIFO:
            assert "egm_reply_thread_realtime" in events
        else:
            assert "egm_reply_thread_realtime_refused" in events
        if "egm_reply_thread_affinity_refused" not in events:
            assert cpus == {0}

    asyncio.run(main())


def test_commands_from_the_loop_reach_the_reply_thread_between_two_packets():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        addr = await ep.start()
        ctl = controller_socket()
        try:
            first = await exchange(ctl, addr, robot(0))
            np.testing.assert_array_equal(first.planned_q_deg, Q0)  # holds where the session started
            for k in range(1, 20):
                target = Q0 + 0.5 * k
                ep.command_joints(target)
                reply = await exchange(ctl, addr, robot(k))
                np.testing.assert_array_equal(reply.planned_q_deg, target)
            ep.hold()
            np.testing.assert_array_equal((await exchange(ctl, addr, robot(20))).planned_q_deg, Q0)
        finally:
            ctl.close()
            await ep.close()

    asyncio.run(main())


def test_wait_for_feedback_returns_a_sample_received_after_the_call():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        addr = await ep.start()
        ctl = controller_socket()
        try:
            first = asyncio.ensure_future(ep.wait_for_feedback(5.0))
            await asyncio.sleep(0)  # the wait is registered
            await exchange(ctl, addr, robot(0))
            assert (await first).seqno == 0  # handed over to the loop
            waiter = asyncio.ensure_future(ep.wait_for_feedback(5.0))
            await asyncio.sleep(0.02)  # stays: time passing in which nothing must happen
            assert not waiter.done()  # the sample already handed over is not "the next"
            ctl.sendto(robot(1), addr)
            state = await waiter
            assert state.seqno == 1
            assert ep.latest.seqno == 1
        finally:
            ctl.close()
            await ep.close()

    asyncio.run(main())


def test_an_error_while_handling_one_datagram_does_not_end_the_reply_thread():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        addr = await ep.start()
        ctl = controller_socket()
        real_append = ep.history.append
        calls = []

        def flaky_append(*args):
            calls.append(1)
            if len(calls) == 2:
                raise RuntimeError("history bug")
            real_append(*args)

        ep.history.append = flaky_append
        try:
            with capture_logs() as logs:
                for k in range(4):
                    assert (await exchange(ctl, addr, robot(k))).seqno == k
                await handled(ep, 4)
                await wait_until(  # the error's log line is handed to the loop
                    lambda: any(e["log_level"] == "error" for e in logs), 0.05, "the error logged"
                )
            assert [e["event"] for e in logs if e["log_level"] == "error"] == ["egm_reply_thread_error"]
            assert len(ep.history) == 3
        finally:
            ctl.close()
            await ep.close()

    asyncio.run(main())


def test_switch_interval_is_lowered_while_the_endpoint_runs_and_restored_on_close():
    before = sys.getswitchinterval()

    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True, switch_interval_s=2e-4))
        await ep.start()
        try:
            assert sys.getswitchinterval() == pytest.approx(2e-4)
        finally:
            await ep.close()

    asyncio.run(main())
    assert sys.getswitchinterval() == before


def test_simulator_follows_the_reply_thread_and_stamps_replies_in_the_kernel():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True))
        _, port = await ep.start()
        sim = EgmControllerSim(EgmSimConfig(sensor_port=port, seed=3))
        await sim.start()
        try:
            await ep.wait_for_feedback(2.0)
            target = np.array([10.0, -5.0, 8.0, 0.0, 35.0, 20.0])
            ep.command_joints(target)
            loop = asyncio.get_running_loop()
            give_up = loop.time() + 30.0  # idle: about 1 s; a loaded machine starves the simulator
            while np.abs(sim.q_deg - target).max() >= 0.05 and loop.time() < give_up:
                await ep.wait_for_feedback(5.0)  # paced by the controller, however slow it runs
            np.testing.assert_allclose(sim.q_deg, target, atol=0.05)
            np.testing.assert_allclose(ep.latest.q_deg, target, atol=0.5)
            user_us, _ = sim.reply_latency()
            kernel_us, _ = sim.reply_latency(kernel=True)
        finally:
            await sim.stop()
            await ep.close()
        assert user_us.size > 10 and kernel_us.shape == user_us.shape
        if sim.kernel_rx_stamps:
            assert np.isfinite(kernel_us).all()
            # the kernel stamps a reply when it arrives, before the simulator wakes up to read it
            assert (kernel_us > 0).all() and (kernel_us <= user_us + 1.0).all()
        else:
            assert np.isnan(kernel_us).all()

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        runner.run(main())


def test_spinning_reply_thread_answers_every_packet_of_a_steady_stream_and_after_a_gap():
    async def main():
        ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=True, reply_spin_us=300.0))
        addr = await ep.start()
        ctl = controller_socket()

        def controller(seqnos, period_s):
            replies = []
            for k in seqnos:
                ctl.sendto(robot(k), addr)
                replies.append(decode_sensor(ctl.recvfrom(4096)[0]).seqno)
                threading.Event().wait(period_s)
            return replies

        try:
            steady = await asyncio.to_thread(controller, range(0, 40), 0.004)
            # a pause far longer than the cadence: the thread spins once in vain, then blocks again
            await asyncio.sleep(0.15)
            after_gap = await asyncio.to_thread(controller, range(40, 45), 0.004)
        finally:
            ctl.close()
            await ep.close()
        assert steady == list(range(40)) and after_gap == list(range(40, 45))
        assert ep.stats.lost == 0 and ep.stats.replies_sent == 45
        assert reply_threads() == []

    asyncio.run(main())
