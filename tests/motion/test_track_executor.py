"""Planning and executing with the linear track: the carriage follows the passes, track and arm are
timed together, and pause / resume / abort ramp all seven axes, against the controller simulator
over loopback UDP (the same harness pieces as tests/motion/test_executor_sim.py)."""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.motion import ExecState, ExecutorConfig, MotionExecutor
from cellctl.planning import PlannerSettings, PlanRefused, plan_scan
from cellctl.planning.joint_path import track_positions
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.limits import LinearTrack
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig
from tests.motion.conftest import realtime_priority, run_async, wait_for_segment, wait_for_state

# Plans a 4 m track scan and runs the controller simulator in real time: with the cell tests, one
# at a time (unmarked, it ran in the unit tests' parallel part beside the numerical tests).
pytestmark = pytest.mark.slow

CYCLE_S = 0.004032
#: a track along world +y; the plate lies beside it (world x = 1500), its length along the rail
TRACK = LinearTrack(
    origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=4000.0,
    speed_max_mm_s=500.0, accel_max_mm_s2=1000.0, jerk_max_mm_s3=10000.0,
)  # fmt: skip
SETTINGS = PlannerSettings(
    speed_mm_s=200.0,
    placement_uncertainty_mm=5.0,
    placement_uncertainty_deg=0.5,
    track=TRACK,
    track_hold=False,  # these tests are of the carriage following the passes ([robot.track] hold = false)
)
PLACEMENT = Placement.on_bed(1500.0, 2000.0, 90.0, z_mm=300.0)


@pytest.fixture(scope="module")
def track_plan():
    mesh = design_mesh(plate_spec("sail", length_mm=300.0, width_mm=150.0), pitch_mm=5.0)
    return plan_scan(mesh, PLACEMENT, SETTINGS)


def test_the_track_follows_each_pass_along_the_rail_and_the_arm_keeps_its_reach(track_plan):
    q = track_plan.trajectory.q_deg
    assert q.shape[1] == 7
    sweeps = [s for s in track_plan.segments if s.kind == "scan"]
    for seg in sweeps:
        along = (seg.pos_mm - TRACK.origin_mm) @ TRACK.direction
        # the carriage moves with the sensor along the rail: the sensor's along-rail offset from the
        # base is the same everywhere on the pass
        np.testing.assert_allclose(along - seg.q_deg[:, 0], along[0] - seg.q_deg[0, 0], atol=1e-9)
        assert np.ptp(seg.q_deg[:, 0]) > 200.0
    # the plan's joint poses put the sensor where the passes are, in the world frame
    seg = sweeps[0]
    T = fk_batch(seg.q_deg, SETTINGS.T_flange_sensor, track=TRACK)
    np.testing.assert_allclose(T[:, :3, 3], seg.pos_mm, atol=0.1)
    # track and arm timed together: the sensor runs at the scan speed while the carriage carries it
    interior = track_plan.trajectory.segment == track_plan.segments.index(seg)
    qd = track_plan.trajectory.qd_deg_s[interior]
    assert np.abs(qd[:, 0]).max() == pytest.approx(SETTINGS.scan_speed_mm_s, rel=0.05)
    assert np.abs(qd[:, 0]).max() <= TRACK.speed_max_mm_s


def test_the_lead_keeps_the_carriage_inside_its_travel():
    # the plan's along-rail span from this origin is -44 .. 397 mm: abreast (lead 0) the carriage
    # would have to stand at -44 mm, before the travel's start
    short = LinearTrack(
        origin_mm=[0.0, 1800.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=600.0,
        speed_max_mm_s=500.0,
    )  # fmt: skip
    mesh = design_mesh(plate_spec("sail", length_mm=300.0, width_mm=150.0), pitch_mm=5.0)
    plan = plan_scan(mesh, PLACEMENT, SETTINGS.with_(track=short), with_coverage=False)
    s = plan.trajectory.q_deg[:, 0]
    assert s.min() >= 0.0 and s.max() <= 600.0
    # the whole travel was not needed: the lead moved off abreast to keep the carriage inside it
    along = np.concatenate([(seg.pos_mm - short.origin_mm) @ short.direction for seg in plan.segments])
    lead = along - np.concatenate([seg.q_deg[:, 0] for seg in plan.segments])
    np.testing.assert_allclose(lead, lead[0], atol=1e-9)
    assert lead[0] < -40.0
    assert track_positions(plan.segments, SETTINGS.with_(track=None)) is None


def test_a_plate_beyond_the_travel_and_the_reach_is_refused_with_the_reason():
    short = LinearTrack(
        origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=100.0,
        speed_max_mm_s=500.0,
    )  # fmt: skip
    mesh = design_mesh(plate_spec("sail", length_mm=300.0, width_mm=150.0), pitch_mm=5.0)
    with pytest.raises(PlanRefused, match="reach"):
        plan_scan(mesh, Placement.on_bed(1500.0, 6000.0, 90.0, z_mm=300.0), SETTINGS.with_(track=short))


async def _execute(plan, control, timeout_s: float = 120.0):
    endpoint = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0, n_external=1))
    _, port = await endpoint.start()
    start = plan.trajectory.q_deg[0]
    sim = EgmControllerSim(
        EgmSimConfig(
            sensor_port=port, q_start_deg=tuple(start[1:]), seed=1, track=TRACK, track_start_mm=start[0]
        )
    )
    await sim.start()
    try:
        cfg = ExecutorConfig.from_settings(SETTINGS, tracking_error_max_mm=25.0)
        executor = MotionExecutor.for_plan(endpoint, plan, SETTINGS, cfg)
        side = asyncio.get_running_loop().create_task(control(executor, sim))
        with realtime_priority():
            result = await asyncio.wait_for(executor.run(), timeout_s)
            side.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await side
            await asyncio.sleep(0.3)
    finally:
        await sim.stop()
        await endpoint.close()
    return result, sim.trajectory.arrays()


def _max_reference_jerk(result) -> np.ndarray:
    """Largest |third difference| / dt^3 per axis over runs of consecutive cycles of the references."""
    q, k = result.q_ref_deg, result.cycle
    consecutive = (np.diff(k[:-2]) == 1) & (np.diff(k[1:-1]) == 1) & (np.diff(k[2:]) == 1)
    j = np.abs(np.diff(q, n=3, axis=0)) / CYCLE_S**3
    return j[consecutive].max(axis=0)


def test_pause_resume_and_abort_ramp_all_seven_axes(track_plan):
    seen = {}

    async def control(executor: MotionExecutor, sim) -> None:
        await wait_for_segment(executor, "scan 1", 0.4)
        executor.pause()
        await wait_for_state(executor, "paused")
        # the endpoint answers each cycle with the reference prepared in the one before: the
        # reference the executor settled on is on the wire one cycle after the state says paused
        at_pause = executor.endpoint.reference_q_deg
        # the controller's law settles the last few tenths of a mm: wait until it has (<= 3 s)
        last, deadline = sim.axes_mm_deg, asyncio.get_running_loop().time() + 3.0
        while asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.1)
            now = sim.axes_mm_deg
            if np.max(np.abs(now - last)) < 0.002:
                break
            last = now
        seen["paused"] = sim.axes_mm_deg
        seen["reference"] = executor.endpoint.reference_q_deg
        seen["reference_at_pause"] = at_pause
        await asyncio.sleep(0.5)
        seen["after_wait"] = sim.axes_mm_deg
        seen["reference_after_wait"] = executor.endpoint.reference_q_deg
        executor.resume()
        await wait_for_state(executor, "running")
        await wait_for_segment(executor, "scan 1", 0.8)
        executor.abort()

    result, (_t, q) = run_async(_execute(track_plan, control))
    assert result.state == ExecState.ABORTED, result.fault
    assert result.q_ref_deg.shape[1] == 7
    # paused mid-pass with the carriage moving: every axis, the track included, held still
    np.testing.assert_array_equal(seen["reference_after_wait"], seen["reference"])
    np.testing.assert_allclose(seen["reference"], seen["reference_at_pause"], atol=1e-3)
    np.testing.assert_allclose(seen["after_wait"], seen["paused"], atol=0.05)
    assert np.ptp(result.q_ref_deg[:, 0]) > 50.0  # the track was moving in the pass it paused in
    # the stops and the restart are jerk-limited on all seven axes (the track's in mm/s^3)
    limits = np.concatenate([[TRACK.jerk_max_mm_s3], SETTINGS.joint_jerk_max_deg_s3])
    assert np.all(_max_reference_jerk(result) <= 1.05 * limits)
    # aborted at rest, and the track never left its travel
    assert np.max(np.abs(result.qd_ref_deg_s[-1])) < 1e-3
    assert q[:, 0].min() >= TRACK.travel_min_mm and q[:, 0].max() <= TRACK.travel_max_mm
