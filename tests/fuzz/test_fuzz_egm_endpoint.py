"""Fuzz the EGM endpoint (drivers/abb_egm/endpoint.py) over a real loopback UDP socket.

Mutated ``EgmRobot`` datagrams are interleaved with valid ones. The endpoint must never die, must
count what it cannot use as malformed (every datagram is either received or malformed), and must
answer every valid datagram with an ``EgmSensor`` whatever came before it.
"""

from __future__ import annotations

import asyncio
import socket

import numpy as np
import pytest
from fuzzlib import fuzz_settings, mutated
from hypothesis import given
from hypothesis import strategies as st

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


def _robot(seqno: int, q_deg=(1.0, 2.0, 3.0, 4.0, 30.0, 6.0)) -> bytes:
    return encode_robot(
        RobotMessage(
            seqno=seqno,
            tm_ms=seqno * 4,
            mtype=MessageType.DATA,
            feedback_q_deg=np.asarray(q_deg, dtype=float),
            feedback_pos_mm=np.array([1500.0, 10.0, 1700.0]),
            feedback_quat_wxyz=np.array([1.0, 0.0, 0.0, 0.0]),
            feedback_time_us=1_700_000_000_000_000 + seqno * 4032,
            planned_q_deg=np.asarray(q_deg, dtype=float),
            motor_state=MotorState.ON,
            mci_state=MciState.RUNNING,
            rapid_exec_state=RapidState.RUNNING,
            utilization_pct=10.0,
        )
    )


SEEDS = (_robot(5), _robot(6, (10.0, -20.0, 30.0, 0.0, 45.0, 90.0)), _robot(0))


@st.composite
def _junk(draw: st.DrawFn) -> bytes:
    seed = draw(st.sampled_from(SEEDS))
    return draw(mutated(seed, SEEDS))


async def _settle(ep: EgmEndpoint, sent: int, replied: int, timeout_s: float = 10.0) -> None:
    """Wait until ``sent`` datagrams are accounted for and one more reply went out (counters only)."""
    for _ in range(int(timeout_s / 0.001)):
        st_ = ep.stats
        if st_.received + st_.malformed >= sent and st_.replies_sent > replied:
            return
        await asyncio.sleep(0.001)


async def _exchange(junk: list[bytes], reply_thread: bool) -> tuple[list[int], dict, int]:
    """Send junk[i] then a valid packet, for every i; returns replies seen after each valid packet."""
    ep = EgmEndpoint(EgmEndpointConfig(port=0, reply_thread=reply_thread, malformed_log_interval_s=60.0))
    addr = await ep.start()
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    replies_per_step = []
    sent = replied = 0
    try:
        for i, bad in enumerate(junk):
            sock.sendto(bad, addr)
            sock.sendto(_robot(1000 + i), addr)
            sent += 2
            # both datagrams are accounted for once received + malformed covers them, and the valid
            # one has been answered (the reply counter moves after the send)
            await _settle(ep, sent, replied)
            expected, replied = ep.stats.replies_sent - replied, ep.stats.replies_sent
            n = 0
            for _ in range(expected):  # every reply counted was really sent, and is a valid EgmSensor
                data, _ = await asyncio.wait_for(loop.sock_recvfrom(sock, 4096), 5.0)
                decode_sensor(data)
                n += 1
            replies_per_step.append(n)
        return replies_per_step, ep.stats.snapshot(), sent
    finally:
        sock.close()
        await ep.close()


@pytest.mark.parametrize("reply_thread", [False, True], ids=["loop", "reply_thread"])
@fuzz_settings(30)
@given(junk=st.lists(_junk(), min_size=1, max_size=6))
def test_egm_endpoint_survives_mutated_packets_counts_them_and_answers_every_valid_one(junk, reply_thread):
    replies, stats, sent = asyncio.run(asyncio.wait_for(_exchange(junk, reply_thread), 60))
    assert all(n >= 1 for n in replies), replies  # the valid packet of each step got its answer
    assert stats["received"] + stats["malformed"] == sent


@fuzz_settings(40)
@given(data=st.binary(max_size=2048))
def test_egm_endpoint_counts_random_datagrams_and_still_answers(data):
    replies, stats, sent = asyncio.run(asyncio.wait_for(_exchange([data], False), 60))
    assert replies[0] >= 1
    assert stats["received"] + stats["malformed"] == sent
