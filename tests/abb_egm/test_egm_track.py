"""EGM with a linear track: the track's position travels in ``externalJoints`` (mm) both ways.

Codec round trips, then the real endpoint against the controller simulator over loopback UDP: the
simulator's track follows the endpoint's reference by the arm's control law and limits, and what the
endpoint sees of it comes only over EGM. (The wire fixtures of /work/shared/testdata/egm hold no
external axes; the decode test builds its message with the generated protobuf classes instead.)
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from drivers.abb_egm import egm_pb2
from drivers.abb_egm.codec import (
    EgmDecodeError,
    EgmEncodeError,
    MciState,
    MessageType,
    RobotMessage,
    SensorMessage,
    decode_robot,
    decode_sensor,
    encode_robot,
    encode_sensor,
)
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.kinematics import RobotKinematics
from drivers.abb_egm.limits import LinearTrack
from drivers.abb_egm.sim.egm import EVENT_EGM_JOINT_LIMIT, EgmControllerSim, EgmSimConfig
from drivers.abb_egm.sim.model import ControllerModel
from drivers.runtime import precise_event_loop
from tests.support.waits import wait_until

Q_START = np.array([0.0, 10.0, -10.0, 0.0, 30.0, 0.0])
TRACK = LinearTrack(
    origin_mm=[0.0, -1000.0, 0.0], direction=[1.0, 0.0, 0.0], travel_min_mm=0.0, travel_max_mm=3000.0,
    speed_max_mm_s=400.0, accel_max_mm_s2=2000.0,
)  # fmt: skip
TRACK_START_MM = 1000.0


def run(coro_fn: Callable[[], Awaitable[None]]) -> None:
    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        runner.run(coro_fn())


async def start_pair(model: ControllerModel | None = None, n_external: int = 1):
    ep = EgmEndpoint(EgmEndpointConfig(port=0, n_external=n_external))
    _, port = await ep.start()
    cfg = EgmSimConfig(
        sensor_port=port, q_start_deg=tuple(Q_START), seed=1, track=TRACK, track_start_mm=TRACK_START_MM
    )
    sim = EgmControllerSim(cfg, model=model)
    await sim.start()
    await ep.wait_for_feedback(1.0)
    return sim, ep


# ---- codec ------------------------------------------------------------------------------------


def test_robot_message_external_joints_round_trip_in_feedback_and_planned():
    msg = RobotMessage(
        seqno=3, tm_ms=12, mtype=MessageType.DATA, feedback_q_deg=Q_START, planned_q_deg=Q_START + 1.0,
        feedback_external_joints=np.array([1234.5]), planned_external_joints=np.array([1240.25]),
    )  # fmt: skip
    back = decode_robot(encode_robot(msg))
    np.testing.assert_array_equal(back.feedback_external_joints, [1234.5])
    np.testing.assert_array_equal(back.planned_external_joints, [1240.25])
    np.testing.assert_array_equal(back.feedback_q_deg, Q_START)
    # absent on the wire stays absent
    plain = decode_robot(encode_robot(RobotMessage(seqno=1, mtype=MessageType.DATA, feedback_q_deg=Q_START)))
    assert plain.feedback_external_joints is None and plain.planned_external_joints is None


def test_sensor_message_external_joints_round_trip_in_planned_and_speed_ref():
    msg = SensorMessage(
        seqno=4, tm_ms=9, planned_q_deg=Q_START, speed_ref_q_deg_s=np.zeros(6),
        planned_external_joints=np.array([2500.0]), speed_ref_external_joints=np.array([-150.0]),
    )  # fmt: skip
    back = decode_sensor(encode_sensor(msg))
    np.testing.assert_array_equal(back.planned_external_joints, [2500.0])
    np.testing.assert_array_equal(back.speed_ref_external_joints, [-150.0])


def test_external_joints_decode_from_the_protobuf_fields_egm_defines():
    # built field by field with the generated classes: feedBack.externalJoints (3), planned.externalJoints (3)
    m = egm_pb2.EgmRobot()
    m.header.seqno, m.header.tm, m.header.mtype = 7, 100, egm_pb2.EgmHeader.MSGTYPE_DATA
    m.feedBack.joints.joints.extend(Q_START.tolist())
    m.feedBack.externalJoints.joints.extend([812.0])
    m.planned.joints.joints.extend(Q_START.tolist())
    m.planned.externalJoints.joints.extend([815.5])
    back = decode_robot(m.SerializeToString())
    assert back.feedback_external_joints.tolist() == [812.0]
    assert back.planned_external_joints.tolist() == [815.5]
    s = egm_pb2.EgmSensor()
    s.header.seqno, s.header.tm, s.header.mtype = 1, 2, egm_pb2.EgmHeader.MSGTYPE_CORRECTION
    s.planned.externalJoints.joints.extend([90.0])
    s.speedRef.externalJoints.joints.extend([5.0])
    got = decode_sensor(s.SerializeToString())
    assert got.planned_external_joints.tolist() == [90.0] and got.speed_ref_external_joints.tolist() == [5.0]


def test_more_than_six_external_axes_or_a_non_finite_track_is_refused():
    with pytest.raises(EgmEncodeError, match="externalJoints"):
        encode_sensor(SensorMessage(planned_external_joints=np.zeros(7)))
    with pytest.raises(EgmEncodeError, match="non-finite"):
        encode_sensor(SensorMessage(planned_external_joints=np.array([np.nan])))
    m = egm_pb2.EgmRobot()
    m.header.mtype = egm_pb2.EgmHeader.MSGTYPE_DATA
    m.feedBack.joints.joints.extend(Q_START.tolist())
    m.feedBack.externalJoints.joints.extend([0.0] * 7)
    with pytest.raises(EgmDecodeError, match=r"feedBack\.externalJoints"):
        decode_robot(m.SerializeToString())


# ---- against the simulator --------------------------------------------------------------------


def test_track_follows_the_reference_and_its_feedback_comes_back_in_external_joints():
    async def main():
        sim, ep = await start_pair()
        try:
            assert ep.latest.external_joints.tolist() == [TRACK_START_MM]
            target = np.concatenate([[TRACK_START_MM + 25.0], Q_START + np.array([1.0, 0, 0, 0, 0, 0])])
            ep.command_joints(target)
            await wait_until(lambda: np.abs(sim.axes_mm_deg - target).max() < 0.01, 3.0)
            await ep.wait_for_feedback(0.5)
            np.testing.assert_allclose(ep.latest.axes_mm_deg, target, atol=0.02)
            # the cartesian feedback is the flange in the world frame, carriage included
            kin = RobotKinematics(track=TRACK)
            np.testing.assert_allclose(ep.latest.pos_mm, kin.fk(ep.latest.axes_mm_deg).pos_mm, atol=1e-6)
            # the history rows are axes_mm_deg, the track first
            rows = ep.history.arrays().q_deg
            assert rows.shape[1] == 7
            assert rows[0, 0] == pytest.approx(TRACK_START_MM) and rows[-1, 0] == pytest.approx(
                target[0], abs=0.05
            )
            # the simulator's true trajectory, which the sensor simulator reads, carries it too
            assert sim.trajectory.arrays()[1].shape[1] == 7
        finally:
            await sim.stop()
            await ep.close()

    run(main)


def test_track_moves_by_the_same_control_law_as_a_joint():
    async def main():
        sim, ep = await start_pair()
        try:
            # the same small step on the track (mm) and on joint 1 (deg): within every speed limit
            # the controller's law makes the two responses the same numbers
            start = sim.axes_mm_deg
            target = start + np.array([2.0, 2.0, 0, 0, 0, 0, 0])
            ep.command_joints(target)
            await wait_until(lambda: np.abs(sim.axes_mm_deg - target).max() < 1e-3, 3.0)
            q = sim.trajectory.arrays()[1]
            moving = np.abs(q[:, 0] - start[0]) > 1e-9
            np.testing.assert_allclose(q[moving, 0] - start[0], q[moving, 1] - start[1], atol=1e-9)
        finally:
            await sim.stop()
            await ep.close()

    run(main)


def test_track_speed_is_held_to_its_limit():
    async def main():
        sim, ep = await start_pair()
        try:
            target = sim.axes_mm_deg + np.array([150.0, 0, 0, 0, 0, 0, 0])  # 150 mm x k=5: 750 mm/s asked
            ep.command_joints(target)
            await wait_until(lambda: abs(sim.axes_mm_deg[0] - target[0]) < 0.01, 3.0)
            t, q = sim.trajectory.arrays()
            v = np.abs(np.diff(q[:, 0]) / np.diff(t))
            assert v.max() <= TRACK.speed_max_mm_s * (1 + 1e-9)
            assert v.max() > 0.9 * TRACK.speed_max_mm_s  # it did run at the limit
        finally:
            await sim.stop()
            await ep.close()

    run(main)


def test_track_reference_beyond_its_travel_puts_egm_in_error_and_the_track_stays_inside():
    async def main():
        model = ControllerModel()
        model.motors_on()
        model.start_rapid()
        sim, ep = await start_pair(model)
        try:
            ep.command_joints(np.concatenate([[TRACK.travel_max_mm + 5.0], Q_START]))
            await wait_until(lambda: ep.latest.mci_state is MciState.ERROR, 0.5)
            assert any(e.code == EVENT_EGM_JOINT_LIMIT for e in model.events)
            assert "track" in sim.ended_sessions[-1][0]
            assert sim.axes_mm_deg[0] == pytest.approx(TRACK_START_MM, abs=1e-9)
        finally:
            await sim.stop()
            await ep.close()

    run(main)


def test_a_joint_reference_without_the_track_is_ignored_by_a_robot_on_a_track():
    async def main():
        sim, ep = await start_pair(n_external=0)  # this endpoint does not know about the track
        try:
            ep.command_joints(Q_START + np.array([3.0, 0, 0, 0, 0, 0]))
            await wait_until(lambda: sim.stats.sensor_ignored > 20, 0.2)
            np.testing.assert_allclose(
                sim.axes_mm_deg, np.concatenate([[TRACK_START_MM], Q_START]), atol=1e-9
            )
        finally:
            await sim.stop()
            await ep.close()

    run(main)
