"""From `cell.toml` to the drivers' configurations: the one place a config field meets a driver field.

The daemon, the fault and security harnesses and any command that talks to the cell's robot or
sensor build their driver objects here, so a ``[robot]`` or ``[laser]`` key is read in one place and
a new driver setting is wired once. Each function is a plain, typed mapping; :class:`CellDrivers`
holds the daemon's long-lived driver objects, named.
"""

from __future__ import annotations

from dataclasses import dataclass

from cellctl.config import CellConfig, LaserSection, RobotSection, resolve_secret
from cellctl.logging import current_logging
from cellctl.motion import EnvelopeLimits
from cellctl.motion.channel import RealtimeSpec
from cellctl.motion.link import MotionLink, MotionSettings, envelope_spec
from cellctl.planning import PlannerSettings
from drivers.abb_egm.cell_egm import CellEgmProgram, EgmProgramSettings
from drivers.abb_egm.endpoint import EgmEndpointConfig
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig
from drivers.laser.client import HD8Client, HD8ClientConfig
from drivers.laser.gige.source import GigeSourceConfig
from drivers.laser.registry import open_source
from drivers.laser.source import ProfileSource

__all__ = [
    "CellDrivers",
    "build_drivers",
    "egm_endpoint_config",
    "egm_program_settings",
    "gige_source_config",
    "hd8_client",
    "hd8_client_config",
    "laser_exposure_ns",
    "laser_source",
    "motion_settings",
    "rws_client_config",
    "rws_password",
]


def egm_endpoint_config(robot: RobotSection) -> EgmEndpointConfig:
    """``[robot] egm_*`` -> the EGM endpoint's settings."""
    return EgmEndpointConfig(
        host=robot.egm_host,
        port=robot.egm_port,
        watchdog_s=robot.egm_watchdog_s,
        history_len=robot.egm_history_len,
        # the motion process serves EGM from its own SCHED_FIFO thread (cellctl/motion/process.py);
        # these are the endpoint's settings for an in-process reply thread (tests, tools)
        reply_thread=robot.egm_reply_thread,
        reply_thread_priority=robot.egm_reply_priority,
        reply_thread_cpus=tuple(robot.egm_reply_cpus),
        switch_interval_s=robot.egm_switch_interval_s,
        reply_spin_us=robot.egm_reply_spin_us,
        # the track's position travels in externalJoints beside the joints (docs/robot-setup.md)
        n_external=0 if robot.track is None else 1,
    )


def motion_settings(cfg: CellConfig) -> MotionSettings:
    """``[robot]`` -> the motion process's settings: its EGM endpoint, the envelope every reference
    passes (cell.toml's joint, track, workspace and speed limits) and its real-time settings."""
    endpoint = egm_endpoint_config(cfg.robot)
    limits = EnvelopeLimits.from_settings(PlannerSettings.from_config(cfg), cycle_s=endpoint.cycle_s)
    fmt, level = current_logging()
    return MotionSettings(
        endpoint=endpoint,
        envelope=envelope_spec(limits),
        realtime=RealtimeSpec(
            priority=cfg.robot.egm_reply_priority if cfg.daemon.realtime else 0,
            cpus=list(cfg.robot.egm_reply_cpus),
            lock_memory=cfg.robot.motion_lock_memory,
            required=cfg.robot.motion_realtime_required,
        ),
        log_format=fmt,
        log_level=level,
        cell_id=cfg.cell.id,
    )


def rws_password(robot: RobotSection) -> str:
    """The RWS password from ``rws_password_file`` or ``rws_password_env`` (ConfigError if neither)."""
    return resolve_secret(
        robot.rws_password_env, robot.rws_password_file, what="robot.rws password"
    ).get_secret_value()


def rws_client_config(
    robot: RobotSection, password: str, *, timeout_s: float | None = None
) -> RwsClientConfig:
    """``[robot] rws_*`` -> the RWS client's settings (``timeout_s`` overrides ``rws_timeout_s``)."""
    return RwsClientConfig(
        base_url=robot.rws_url,
        profile=robot.rws_profile,
        username=robot.rws_user,
        password=password,
        timeout_s=robot.rws_timeout_s if timeout_s is None else timeout_s,
        tls_ca_file=None if robot.rws_ca_file is None else str(robot.rws_ca_file),
        poll_interval_s=robot.rws_poll_interval_s,
        mechunit=robot.rws_mechunit,
    )


def egm_program_settings(robot: RobotSection) -> EgmProgramSettings:
    """``[robot] egm_*`` / ``rapid_*`` -> the EGM arguments written into CellEgm.mod before each start."""
    return EgmProgramSettings(
        comm_timeout_s=robot.egm_comm_timeout_s,
        pos_corr_gain=min(robot.egm_pos_corr_gain, 1.0),
        max_speed_deviation_deg_s=robot.egm_max_speed_deviation_deg_s,
        max_pos_deviation_deg=robot.egm_max_pos_deviation_deg,
        cond_time_s=robot.egm_cond_time_s,
        ramp_in_time_s=robot.egm_ramp_in_s,
        lp_filter_hz=robot.egm_lp_filter_hz,
        sample_rate_ms=float(robot.egm_sample_rate_ms),
        task=robot.rapid_task,
        module=robot.rapid_module,
    )


def hd8_client_config(laser: LaserSection) -> HD8ClientConfig:
    """``[laser]`` -> the HD8 client's tuning (its stall watchdog and profile buffer)."""
    return HD8ClientConfig(watchdog_timeout_s=laser.watchdog_s, buffer_profiles=laser.buffer_profiles)


def hd8_client(laser: LaserSection) -> HD8Client:
    """A (not yet connected) client of the ``[laser]`` sensor."""
    return HD8Client(laser.host, laser.control_port, laser.data_port, config=hd8_client_config(laser))


def gige_source_config(laser: LaserSection) -> GigeSourceConfig:
    """``[laser]`` -> the GigE Vision source's tuning: region, block height, packets, watchdog, buffer."""
    return GigeSourceConfig(
        width=laser.points_per_profile,
        x_offset=laser.gige_x_offset_px,
        rows_per_buffer=laser.gige_rows_per_buffer,
        packet_size=laser.gige_packet_size,
        watchdog_timeout_s=laser.watchdog_s,
        buffer_profiles=laser.buffer_profiles,
    )


def laser_source(laser: LaserSection) -> ProfileSource:
    """A (not yet connected) source of the ``[laser]`` sensor, of the kind ``[laser] protocol`` names
    (drivers/laser/registry.py); configure it with ``rate_hz`` and ``exposure_ns`` as the HD8."""
    if laser.protocol == "gige":
        return open_source("gige", laser.gige_device or laser.host, config=gige_source_config(laser))
    return open_source(
        "hd8", laser.host, laser.control_port, laser.data_port, config=hd8_client_config(laser)
    )


def laser_exposure_ns(laser: LaserSection) -> int:
    """``[laser] exposure_us`` in the protocol's unit."""
    return round(laser.exposure_us * 1000)


@dataclass(frozen=True)
class CellDrivers:
    """The daemon's long-lived driver objects (the sensor client is made per scan: :func:`hd8_client`)."""

    motion: MotionLink
    rws: RwsClient
    program: CellEgmProgram


def build_drivers(cfg: CellConfig, password: str) -> CellDrivers:
    """The motion process's link (not started), the RWS client and the EGM program of ``cfg``."""
    rws = RwsClient(rws_client_config(cfg.robot, password))
    return CellDrivers(
        motion=MotionLink(motion_settings(cfg)),
        rws=rws,
        program=CellEgmProgram(rws, egm_program_settings(cfg.robot)),
    )
