"""`cellctl sim`: the simulated cell of cell.toml ``[sim]`` as one process, on loopback.

* the ABB controller simulator (:class:`drivers.abb_egm.sim.controller.ControllerSim`): EGM as the UDP client
  sending to ``[robot] egm_host:egm_port``, RWS served on ``[sim] rws_port``;
* the HD8 simulator (:class:`drivers.laser.sim.sensor.LaserSimulator`) on ``[laser] control_port`` /
  ``data_port``; its ``pose_at`` is the controller simulator's **true** trajectory composed with the
  mounting ``[robot.sensor_in_flange]``, so the daemon's acquisition is judged against the truth;
* the scene: the formed plate of ``[sim.plate]`` (design + the default forming error, or the
  surface of its ``mesh_file``) laid at ``[sim.placement]``, with bed and supports (:meth:`cellctl.simcell.truth.PlateTruth.scene`).

The truth (placement, plate, forming error) goes to ``<data_dir>/sim-truth.json``. With
``[sim] fault_control`` the process also serves the run-time fault knobs on ``<prefix>/sim/faults``
(its own Zenoh endpoint ``[sim] fault_listen``; :mod:`cellctl.simcell.faults`, docs/simulator.md). On start
the process prints one JSON line with its addresses on stdout (``fault_control``: the endpoint, or
null when off or not available); it runs until SIGTERM / SIGINT.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from analysis.design.mesh import MeshError
from cellctl.acquisition.poses import T_from_pos_rpy
from cellctl.config import CellConfig
from cellctl.simcell.truth import MeshPlateTruth, PlateTruth, mesh_plate_truth, plate_truth
from drivers.runtime import stop_on_signals

log = structlog.get_logger(__name__)


class SimCellError(Exception):
    """The simulated cell cannot start (port in use, bad [sim] values)."""


def sim_plate_truth(cfg: CellConfig) -> PlateTruth | MeshPlateTruth:
    """The formed plate of ``[sim.plate]`` at ``[sim.placement]`` (base frame, mm): a plate of
    ``kind`` with its forming error, or (``kind = "mesh"``) the surface of ``mesh_file``.
    Raises :class:`SimCellError` naming the key and file when the mesh plate cannot be used."""
    sp = cfg.sim.plate
    if sp.kind == "mesh":
        try:
            return mesh_plate_truth(
                sp.mesh_file,
                sp.design_file,
                thickness_mm=sp.thickness_mm,
                pos_mm=tuple(cfg.sim.placement.pos_mm),
                angle_deg=cfg.sim.placement.angle_deg,
            )
        except MeshError as exc:
            raise SimCellError(f"[sim.plate] mesh_file / design_file: {exc}") from None
    return plate_truth(
        sp.kind,
        pos_mm=tuple(cfg.sim.placement.pos_mm),
        angle_deg=cfg.sim.placement.angle_deg,
        forming_error=sp.forming_error == "default",
        length_mm=sp.length_mm,
        width_mm=sp.width_mm,
        thickness_mm=sp.thickness_mm,
        radius_x_mm=sp.radius_x_mm,
        radius_y_mm=sp.radius_y_mm,
    )


def truth_dict(cfg: CellConfig, truth: PlateTruth | MeshPlateTruth) -> dict[str, Any]:
    """What ``sim-truth.json`` holds: plate spec (a mesh plate: its files and the mesh's SHA-256),
    forming error, placement and the true hand-eye."""
    return json.loads(
        json.dumps(
            {
                "plate": truth.record() if isinstance(truth, MeshPlateTruth) else asdict(truth.spec),
                "forming_error": None if truth.error is None else asdict(truth.error),
                "placement": {
                    "pos_mm": list(cfg.sim.placement.pos_mm),
                    "angle_deg": cfg.sim.placement.angle_deg,
                },
                "T_base_plate": truth.T_base_plate.tolist(),
                "sensor_in_flange": cfg.robot.sensor_in_flange.model_dump(),
                "written_utc_s": time.time(),
            },
            default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o),
        )
    )


class SimulatedCell:
    """Controller + sensor simulators looking at the formed plate. ``await start()``, ``await stop()``."""

    def __init__(self, cfg: CellConfig, *, scene_pitch_mm: float = 4.0) -> None:
        self.cfg = cfg
        self.scene_pitch_mm = scene_pitch_mm
        self.truth = sim_plate_truth(cfg)
        self.controller: Any = None
        self.sensor: Any = None
        self.gige: Any = (
            None  # the GigE Vision device serving the sensor's profiles ([laser] protocol = "gige")
        )

    async def start(self) -> dict[str, Any]:
        """Build the scene, start both simulators; returns their addresses."""
        from drivers.abb_egm.kinematics import fk_batch
        from drivers.abb_egm.sim.controller import ABB_DEFAULT_PASSWORD, ControllerSim, ControllerSimConfig
        from drivers.abb_egm.sim.egm import EgmFaults, EgmSimConfig
        from drivers.abb_egm.sim.model import ControllerModel
        from drivers.laser.sim.sensor import LaserSimulator, SimConfig

        cfg, sim = self.cfg, self.cfg.sim
        users = tuple((u, os.environ.get(env, ABB_DEFAULT_PASSWORD)) for u, env in sim.rws_users.items())
        # the robot on its track: the true trajectory holds axes_mm_deg, the sensor sees world poses
        track = None if cfg.robot.track is None else cfg.robot.track.linear_track()
        f = sim.faults
        self.controller = ControllerSim(
            ControllerSimConfig(
                rws_port=sim.rws_port,
                rws_profile=cfg.robot.rws_profile,
                rws_users=users,
                rws_max_sessions=sim.rws_max_sessions,
            ),
            EgmSimConfig(
                sensor_host=cfg.robot.egm_host,
                sensor_port=cfg.robot.egm_port,
                cycle_s=sim.egm_cycle_ms * 1e-3,
                q_start_deg=tuple(sim.egm_q_start_deg),
                track=track,
                track_start_mm=sim.egm_track_start_mm,
                stream_when_idle=sim.egm_stream_when_idle,
                ctrl_clock_offset_s=1000.0,
                seed=sim.plate.seed,
            ),
            EgmFaults(
                loss_fraction=f.egm_loss_fraction,
                burst_ms=f.egm_burst_ms,
                delay_ms=f.egm_delay_ms,
                jitter_ms=f.egm_jitter_ms,
                duplicate_fraction=f.egm_duplicate_fraction,
                reorder_fraction=f.egm_reorder_fraction,
                corrupt_fraction=f.egm_corrupt_fraction,
                stop_sending=f.egm_stop_sending,
                rx_loss_fraction=f.egm_rx_loss_fraction,
            ),
            model=ControllerModel(opmode=sim.opmode),
        )
        scene = await asyncio.to_thread(self.truth.scene, self.scene_pitch_mm)
        mount = cfg.robot.sensor_in_flange
        T_fs = T_from_pos_rpy(mount.pos_mm, mount.rpy_deg)
        trajectory = self.controller.egm.trajectory

        def pose_at(t_true_s: np.ndarray) -> np.ndarray:
            # a controller cycle that fell behind the sensor's on a loaded machine: the arm's last
            # joint velocity continues for those milliseconds (as SimCell does) rather than fail
            q, _late = trajectory.q_deg_continued(t_true_s)
            return fk_batch(q, T_fs, track=track)

        las = cfg.laser
        self.sensor = LaserSimulator(
            scene,
            pose_at,
            config=SimConfig(
                width=las.points_per_profile,
                x_pitch_mm=las.line_width_mm / las.points_per_profile,
                z_min_mm=las.depth_min_mm,
                z_max_mm=las.depth_max_mm,
                rate_hz=las.rate_hz,
                exposure_ns=round(las.exposure_us * 1000),
                noise_sigma_mm=sim.depth_noise_mm,
                outlier_probability=sim.outlier_fraction,
                clock_drift_ppm=sim.clocks.sensor_drift_ppm,
                network_jitter_s=sim.clocks.network_jitter_ms * 1e-3,
                seed=sim.plate.seed,
            ),
            host=las.host,
            control_port=las.control_port,
            data_port=las.data_port,
        )
        # start-time laser faults of [sim.faults] (the run-time ones come over sim/faults)
        if f.laser_disconnect_after_frames > 0:
            self.sensor.disconnect_after(f.laser_disconnect_after_frames)
        self.sensor.faults.corrupt_probability = f.laser_corrupt_fraction
        self.sensor.faults.drop_probability = f.laser_drop_fraction
        try:
            await self.controller.start()
            now = time.monotonic()
            # the sensor clock runs sensor_offset_ms ahead of the host's
            self.sensor.jump_timestamp(
                now * 1e6 + sim.clocks.sensor_offset_ms * 1e3 - float(self.sensor.sensor_time_us(now))
            )
            if las.protocol == "gige":
                from drivers.laser.sim.gige_device import GigeSimDevice

                self.gige = GigeSimDevice(self.sensor, address=las.gige_device or las.host)
                await asyncio.to_thread(self.gige.start)
                ctl, dat = 0, 0
            else:
                ctl, dat = await self.sensor.start()
        except OSError as exc:
            await self.stop()
            raise SimCellError(f"cannot start the simulated cell: {exc}") from None
        addresses = {**self.controller.addresses(), "laser": [las.host, ctl, dat]}
        await asyncio.to_thread(self._write_truth)
        log.info("sim_ready", **{k: str(v) for k, v in addresses.items()})
        return addresses

    def _write_truth(self) -> Path:
        data_dir = Path(self.cfg.cell.data_dir)
        data_dir.mkdir(parents=True, exist_ok=True)
        path = data_dir / "sim-truth.json"
        path.write_text(json.dumps(truth_dict(self.cfg, self.truth), indent=2), encoding="utf-8")
        return path

    async def stop(self) -> None:
        """Stop the sensor first (it reads the controller's trajectory), then the controller."""
        if self.gige is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(self.gige.stop)
        if self.sensor is not None:
            with contextlib.suppress(Exception):
                await self.sensor.stop()
        if self.controller is not None:
            with contextlib.suppress(Exception):
                await self.controller.stop()


async def run_sim(cfg: CellConfig) -> int:
    """Run the simulated cell until SIGTERM / SIGINT; 0 on a clean stop, 2 if it cannot start."""
    stop = asyncio.Event()
    release_signals = stop_on_signals(stop)
    try:
        return await _serve_sim(cfg, stop)
    finally:
        release_signals()


async def _serve_sim(cfg: CellConfig, stop: asyncio.Event) -> int:
    cell = SimulatedCell(cfg)
    try:
        addresses = await cell.start()
    except SimCellError as exc:
        log.error("sim_start_failed", error=str(exc))
        return 2
    # After start: the renderer processes already exist and keep normal priority.
    from drivers.runtime import realtime_other_threads, use_realtime_loop

    if use_realtime_loop(cfg.sim.loop_priority):
        # the renderer pool's result and feeder threads take the GIL: at normal priority one of them
        # preempted while holding it would hold the controller's loop back with it (the fault
        # channel's Zenoh session, opened after this from a normal-priority executor thread, stays
        # at normal priority: it answers a person, not a cycle)
        raised, refused = realtime_other_threads(cfg.sim.loop_priority)
        log.info("sim_threads_realtime", raised=raised, refused=refused[:3])
    fault_session = None
    if cfg.sim.fault_control:
        from cellctl.simcell.faults import serve_fault_control

        served = await serve_fault_control(cfg, cell)
        if served is not None:
            fault_session = served[0]
    fault_endpoint = cfg.sim.fault_listen if fault_session is not None else None
    try:
        print(json.dumps({"ready": True, **addresses, "fault_control": fault_endpoint}), flush=True)
        await stop.wait()
    finally:
        if fault_session is not None:
            from cellctl.api.session import close_session

            await asyncio.to_thread(close_session, fault_session)
        await cell.stop()
        log.info("sim_stopped")
    return 0


def main_sync(cfg: CellConfig) -> int:
    """Blocking entry (the precise event loop keeps the 4 ms EGM cycle on time)."""
    from drivers.runtime import precise_event_loop

    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        return runner.run(run_sim(cfg))
