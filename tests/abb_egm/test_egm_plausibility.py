"""Feedback that decodes but cannot be the robot (a datagram corrupted past the UDP checksum) never
reaches the pose history; a real change (a hard stop) is taken once the next sample confirms it."""

from __future__ import annotations

import numpy as np
import pytest

from tests.abb_egm.test_egm_endpoint import Q0, robot, run


@pytest.mark.parametrize("reply_thread", [False, True])
def test_a_lone_joint_jump_is_dropped_and_counted(reply_thread):
    async def body(ep, ctl):
        for k in range(8):
            q = Q0 + 0.1 * k
            if k == 5:
                q = q.copy()
                q[1] += 3.0  # one corrupted joint value, 3 deg off the motion
            ctl.send(robot(k, q=q))
            await ctl.recv()
        a = ep.history.arrays()
        assert list(a.seqno) == [0, 1, 2, 3, 4, 6, 7]
        np.testing.assert_allclose(a.q_deg[:, 1], Q0[1] + 0.1 * a.seqno)
        assert ep.stats.implausible == 1 and ep.stats.malformed == 1
        assert ep.latest.seqno == 7

    run(body, reply_thread=reply_thread)


@pytest.mark.parametrize("reply_thread", [False, True])
def test_a_hard_stop_confirmed_by_the_next_sample_is_kept(reply_thread):
    async def body(ep, ctl):
        seq = [Q0 + 0.1 * k for k in range(5)] + [Q0 + 0.45] * 4  # moving, then stopped dead
        for k, q in enumerate(seq):
            ctl.send(robot(k, q=q))
            await ctl.recv()
        a = ep.history.arrays()
        assert list(a.seqno) == list(range(9))
        assert ep.stats.implausible == 0
        np.testing.assert_allclose(a.q_deg[-1], Q0 + 0.45)

    run(body, reply_thread=reply_thread)


def test_non_finite_or_absurd_joints_never_reach_the_history():
    async def body(ep, ctl):
        for k in range(3):
            ctl.send(robot(k, q=Q0))
            await ctl.recv()
        bad = Q0.copy()
        bad[0] = 1e30
        ctl.send(robot(3, q=bad))
        await ctl.recv()
        assert len(ep.history.arrays()) == 3 and ep.stats.implausible == 1

    run(body)


def test_a_corrupted_controller_time_or_seqno_jump_is_dropped_and_the_stream_goes_on():
    async def body(ep, ctl):
        for k in range(4):
            ctl.send(robot(k, q=Q0))
            await ctl.recv()
        ctl.send(robot(4, q=Q0, t_us=1_700_000_000_000_000 + 4 * 4032 + 9_000_000))  # clock 9 s off
        await ctl.recv()
        ctl.send(robot(5_000_000, q=Q0))  # a seqno from nowhere
        await ctl.recv()
        for k in range(5, 9):
            ctl.send(robot(k, q=Q0))
            await ctl.recv()
        a = ep.history.arrays()
        assert list(a.seqno) == [0, 1, 2, 3, 5, 6, 7, 8]
        assert ep.stats.implausible == 2 and ep.latest.seqno == 8

    run(body)


T0_US = 1_700_000_000_000_000
PERIOD_US = 4032


@pytest.mark.parametrize("late_cycles", [[3], [2, 5], [3, 3, 3]])
def test_late_samples_with_their_true_times_are_kept(late_cycles):
    """A sender that fell behind (the simulator on a busy machine) sends one message for several
    servo cycles: seqno +1, but the joints and the controller time moved on by those cycles. Real
    feedback, consistent in itself: kept (it used to be dropped as "jump not confirmed" when two such
    samples came in a row, thinning the pose history where the machine was busiest)."""

    async def body(ep, ctl):
        cycle = 0
        plan = [1] * 5 + list(late_cycles) + [1] * 5
        for seqno, step in enumerate(plan):
            cycle += step
            ctl.send(robot(seqno, q=Q0 + 0.1 * cycle, t_us=T0_US + cycle * PERIOD_US))
            await ctl.recv()
        a = ep.history.arrays()
        assert list(a.seqno) == list(range(len(plan)))
        assert ep.stats.implausible == 0

    run(body)


def test_a_lone_sample_with_a_time_that_did_not_advance_is_dropped():
    async def body(ep, ctl):
        for k in range(4):
            ctl.send(robot(k, q=Q0 + 0.1 * k, t_us=T0_US + k * PERIOD_US))
            await ctl.recv()
        ctl.send(robot(4, q=Q0 + 0.4, t_us=T0_US + 3 * PERIOD_US))  # the clock stood still
        await ctl.recv()
        for k in range(5, 8):
            ctl.send(robot(k, q=Q0 + 0.1 * k, t_us=T0_US + k * PERIOD_US))
            await ctl.recv()
        a = ep.history.arrays()
        assert list(a.seqno) == [0, 1, 2, 3, 5, 6, 7]
        assert ep.stats.implausible == 1

    run(body)
