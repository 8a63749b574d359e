"""Calibrations: time offset from back-and-forth passes, hand-eye from a sphere (synthetic and simulated)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cellctl.acquisition.clock_sync import ClockSyncConfig
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.poses import T_from_pos_rpy
from cellctl.calibration.hand_eye import (
    HandEyeError,
    StopCapture,
    calibrate_hand_eye,
    solve_hand_eye,
    sphere_capture_poses,
)
from cellctl.calibration.time_offset import TimeOffsetError, estimate_time_offset
from drivers.abb_egm.kinematics import RobotKinematics, fk_batch
from drivers.runtime import precise_event_loop
from tests.support.simcell import (
    Q_SEED_DEG,
    SimCell,
    SimCellConfig,
    sphere_scene,
    stop_and_shoot_path,
)
from tests.support.synthetic_scan import feed, make_run

SPHERE_C = np.array([1500.0, 100.0, 350.0])
SPHERE_R = 20.0
TRUE_POS, TRUE_RPY = (0.8, -1.2, 151.5), (0.3, -0.4, 0.6)


def _angle_deg(Ra, Rb):
    return float(np.rad2deg(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec())))


@pytest.mark.parametrize("error_ms", [-5.0, 0.0, 6.0])
def test_time_offset_estimate_finds_a_latency_error_from_back_and_forth_sweeps(error_ms):
    run = make_run(6.0)
    acq = Acquisition(
        AcquisitionSettings(
            epoch_ns=run.epoch_ns,
            latency_ms=0.8 + error_ms,  # 0.8 ms is right for the synthetic links
            sensor_sync_config=ClockSyncConfig(min_drift_span_s=3.0),
        )
    )
    for k, (a, b) in enumerate([(0.05, 1.25), (1.25, 3.75), (3.75, 6.25)]):  # the sweep's directions
        acq.begin_pass(k, run.epoch_ns + round(a * 1e9))
        acq.end_pass(run.epoch_ns + round(b * 1e9))
    feed(acq, run)
    est = estimate_time_offset(acq.cloud())
    assert est.delta_ms == pytest.approx(-error_ms, abs=0.2)
    if error_ms:
        assert est.disagreement_after_mm < 0.3 * est.disagreement_before_mm


def test_time_offset_needs_overlapping_passes():
    run = make_run(1.0)
    acq = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns))
    acq.begin_pass(0, run.epoch_ns)
    feed(acq, run)
    with pytest.raises(TimeOffsetError, match="overlap"):
        estimate_time_offset(acq.cloud())


def _synthetic_captures(T_true, n=12, noise=0.01, seed=0):
    rng = np.random.default_rng(seed)
    kin = RobotKinematics()
    q = Q_SEED_DEG.copy()
    caps = []
    for T_s in sphere_capture_poses(SPHERE_C, SPHERE_R, n=n, seed=seed):
        r = kin.ik(T_s @ np.linalg.inv(T_true), q)
        q = r.q_deg
        T_bf = fk_batch(q[None])[0]
        T_bs = T_bf @ T_true
        # the laser plane (sensor x-z) cut through the sphere: points on the circle, sensor frame
        c_s = np.linalg.inv(T_bs) @ np.append(SPHERE_C, 1.0)
        rr = np.sqrt(SPHERE_R**2 - c_s[1] ** 2)
        ang = rng.uniform(-0.8, 0.8, 400) + np.pi  # the arc facing the sensor (towards -z from the centre)
        s = np.column_stack([c_s[0] + rr * np.sin(ang), np.zeros(400), c_s[2] + rr * np.cos(ang)])
        s[:, 2] += rng.normal(0, noise, 400)
        caps.append(StopCapture(T_base_flange=T_bf, s_mm=s))
    return caps


def test_hand_eye_solver_recovers_a_known_mounting_from_synthetic_arcs():
    T_true = T_from_pos_rpy(TRUE_POS, TRUE_RPY)
    res = solve_hand_eye(_synthetic_captures(T_true), SPHERE_R, T_from_pos_rpy([0, 0, 150.0], [0, 0, 0]))
    assert np.linalg.norm(res.T_flange_sensor[:3, 3] - T_true[:3, 3]) < 0.02
    assert _angle_deg(res.T_flange_sensor[:3, :3], T_true[:3, :3]) < 0.01
    assert res.rms_mm < 0.02 and len(res.per_stop_rms_mm) == 12


def test_hand_eye_refuses_too_few_stops():
    caps = _synthetic_captures(T_from_pos_rpy(TRUE_POS, TRUE_RPY), n=4)
    with pytest.raises(HandEyeError, match="at least 6"):
        solve_hand_eye(caps, SPHERE_R, np.eye(4))


@pytest.mark.slow
def test_hand_eye_calibration_on_the_simulated_cell_is_within_a_tenth_mm_and_0_05_deg(tmp_path):
    cfg = SimCellConfig(true_sensor_in_flange_pos_mm=TRUE_POS, true_sensor_in_flange_rpy_deg=TRUE_RPY, seed=5)
    nominal = AcquisitionSettings()  # what cell.toml says: (0, 0, 150) mm, no rotation
    kin = RobotKinematics()
    q = Q_SEED_DEG.copy()
    stops = []
    for T_s in sphere_capture_poses(SPHERE_C, SPHERE_R, n=12):
        # the arm goes where the *configured* hand-eye says the sensor looks at the sphere
        r = kin.ik(T_s @ np.linalg.inv(nominal.T_flange_sensor), q)
        assert r.converged
        q = r.q_deg
        stops.append(q)
    path = stop_and_shoot_path(np.array(stops), move_s=0.5, dwell_s=0.8)

    async def main():
        async with SimCell(
            sphere_scene(SPHERE_C, SPHERE_R), cfg, nominal, tmp_path / "job", path.q_deg[0]
        ) as c:
            await c.run(path)

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        runner.run(main())
    res = calibrate_hand_eye(tmp_path / "job", SPHERE_R)
    T_true = cfg.T_flange_sensor
    assert np.linalg.norm(res.T_flange_sensor[:3, 3] - T_true[:3, 3]) < 0.1, res.report()
    assert _angle_deg(res.T_flange_sensor[:3, :3], T_true[:3, :3]) < 0.05, res.report()
    # A loaded machine stutters the simulators and spoils some dwells (the calibration drops them);
    # six good stops of twelve still determine the transform, and the accuracy above is what counts.
    assert res.rms_mm < 0.05 and res.n_stops >= 6
    assert np.linalg.norm(res.sphere_center_mm - SPHERE_C) < 0.1
