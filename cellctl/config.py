"""The cell's configuration: `cell.toml`, validated.

One pydantic model per section, each owned by the part of the cell that reads it. All models are
frozen and forbid unknown keys; units are in the field names. Values come from the TOML file, then
environment variables override them: ``CELL_<SECTION>__<FIELD>`` (for example
``CELL_ROBOT__EGM_PORT=6511``; lists and tables as JSON). Secrets (the RWS and Zenoh passwords) are
never read from the file: the file names an environment variable or a secrets file.

Load with :func:`load_config`; every problem is reported by :class:`ConfigError` with its TOML path,
the offending value and what was expected.
"""

from __future__ import annotations

import functools
import json
import math
import os
import re
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from analysis.contracts.placement import Placement
from analysis.forming.rules import PlanSettings
from drivers.abb_egm.limits import EGM_CYCLE_S, Q_MAX_DEG, Q_MIN_DEG, QD_MAX_DEG_S, LinearTrack, RobotLimits
from drivers.abb_egm.rws_protocol import AUTO, OpMode

if TYPE_CHECKING:  # read only for kind = "mesh" (the mesh readers load open3d)
    from analysis.design.mesh import TriMesh

ENV_PREFIX = "CELL_"
ENV_DELIMITER = "__"
DEFAULT_CONFIG_PATH = Path("cell.toml")

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Port = Annotated[int, Field(ge=1, le=65535)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Joint6 = Annotated[list[Finite], Field(min_length=6, max_length=6)]
PositiveJoint6 = Annotated[list[PositiveFloat], Field(min_length=6, max_length=6)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]

_ZENOH_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/(\[[0-9a-fA-F:]+\]|[^/:\s]+):\d{1,5}$")
_SECRET_WORDS = ("password", "passwd", "secret", "token")
#: an environment variable's name (what every ``*_env`` key holds: never the secret itself)
_ENV_NAME = re.compile(r"[A-Z_][A-Z0-9_]{0,127}")

#: ``[robot]``'s joint limits when cell.toml names none
_DEFAULT_LIMITS = RobotLimits()

# Physical and sane bounds. The joint ranges and speeds are the IRB 4600-40/2.55's
# (drivers/abb_egm/limits.py, from its product specification); the others are sanity bounds
# well beyond what the cell does, so that a typo (1e12) is refused while any real setting passes.
#: TCP speed, mm/s: beyond any industrial arm's tool speed
TCP_SPEED_BOUND_MM_S = 10_000.0
#: joint acceleration, deg/s^2, and jerk, deg/s^3
JOINT_ACCEL_BOUND_DEG_S2 = 10_000.0
JOINT_JERK_BOUND_DEG_S3 = 1_000_000.0
#: each workspace coordinate, mm: the 2.55 m reach plus tool, sensor and stand-off, with room
WORKSPACE_BOUND_MM = 4_000.0
#: a linear track: travel, speed and acceleration bounds (floor tracks run to tens of metres at ~2 m/s)
TRACK_TRAVEL_BOUND_MM = 50_000.0
TRACK_SPEED_BOUND_MM_S = 3_000.0
TRACK_ACCEL_BOUND_MM_S2 = 10_000.0
TRACK_JERK_BOUND_MM_S3 = 1_000_000.0
#: profiles per second: the HD8's top rate (the simulator's max_rate_hz)
LASER_RATE_BOUND_HZ = 1_000.0
#: TCP speed, mm/s, below which no scan ends in a working day (1 mm/s: a 1.2 m pass in 20 min)
TCP_SPEED_MIN_MM_S = 1.0
#: CPUs an affinity list may name: the kernel's CPU set (CPU_SETSIZE), each CPU once
CPU_LIST_BOUND = 1024
#: Zenoh endpoints one process may listen on or connect to
ZENOH_ENDPOINTS_BOUND = 64
#: EGMActJoint \MaxSpeedDeviation, deg/s: about three times the IRB 4600's fastest joint (360 deg/s)
EGM_SPEED_DEVIATION_BOUND_DEG_S = 1_000.0
#: EGMActJoint \MaxPosDeviation, deg: more than any joint's whole range (+-400 deg: 800); with a
#: track it also bounds the track, in mm, and may then reach the longest track's travel
EGM_POS_DEVIATION_BOUND_DEG = 1_000.0
#: the sensor's offset from the flange (hand-eye), mm: beyond the IRB 4600's 2.55 m reach and more
HAND_EYE_BOUND_MM = 3_000.0
#: profiles the sensor client buffers (about 80 min at 200 Hz; 500 points a profile: 6 GB)
BUFFER_PROFILES_BOUND = 1_000_000
#: points published to the analysis: fewer than the minimum leave a plate too sparse to judge, more
#: than the maximum (10x the 6 m plate's 33 M) no worker analyses in its measured memory
PUBLISH_POINTS_MIN = 100_000
PUBLISH_POINTS_BOUND = 400_000_000
#: directories never taken as a data or design directory: the system's own. ``SYSTEM_TREES`` and
#: everything under them; ``SYSTEM_ROOTS`` themselves (a directory inside them, such as
#: /var/lib/cellctl or /home/cell/data, is fine). Symlinks are resolved first (/lib -> /usr/lib).
SYSTEM_TREES = ("/bin", "/boot", "/dev", "/etc", "/lib", "/lib32", "/lib64", "/libx32", "/proc", "/sbin",
                "/sys", "/usr")  # fmt: skip
SYSTEM_ROOTS = ("/", "/home", "/media", "/mnt", "/opt", "/root", "/run", "/srv", "/tmp", "/var", "/var/lib")


def _seconds(hi: float, default_gt: float = 0.0) -> Any:
    return Annotated[float, Field(gt=default_gt, le=hi, allow_inf_nan=False)]


EnvName = Annotated[str, Field(min_length=1, max_length=128)]


def system_directory(path: Path) -> str:
    """The system directory ``path`` is or lies in ("" when none): see :data:`SYSTEM_TREES`."""
    try:
        p = Path(os.path.abspath(path)).resolve()
    except (OSError, RuntimeError):
        p = Path(os.path.abspath(path))
    for tree in SYSTEM_TREES:
        for root in {Path(tree), Path(tree).resolve()}:
            if p == root or p.is_relative_to(root):
                return str(root)
    return str(p) if str(p) in SYSTEM_ROOTS else ""


def _not_a_system_directory(v: Path) -> Path:
    if where := system_directory(v):
        raise ValueError(
            f"{str(v)[:120]!r} is a system directory or lies in one ({where}): give the cell its own "
            "directory (e.g. /var/lib/cellctl/data)"
        )
    return v


Endpoints = Annotated[list[str], Field(max_length=ZENOH_ENDPOINTS_BOUND)]


class Section(BaseModel):
    """Base of every section: frozen, unknown keys rejected, no boolean where a number is meant
    (``rate_hz = true`` would otherwise be 1 Hz)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_as_number(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        for name, value in data.items():
            field = cls.model_fields.get(name)
            if field is None or "bool" in str(field.annotation):
                continue
            values = value if isinstance(value, list) else [value]
            if any(isinstance(v, bool) for v in values):
                raise ValueError(f"{name}: expected a number, got a boolean")
        return data

    @field_validator("*")
    @classmethod
    def _env_keys_name_variables(cls, v: Any, info: Any) -> Any:
        # A *_env key holds the NAME of an environment variable; a password typed into it would be
        # logged as "variable ... is not set". The value is never echoed.
        if info.field_name.endswith("_env") and isinstance(v, str) and not _ENV_NAME.fullmatch(v):
            raise ValueError(
                "expected the name of an environment variable (A-Z, 0-9, _), not its value; "
                "the value given is not shown"
            )
        return v


class Pose(Section):
    """A rigid transform: translation in mm, then rotation as roll-pitch-yaw (deg, fixed axes x, y, z)."""

    pos_mm: Vec3 = [0.0, 0.0, 0.0]
    rpy_deg: Vec3 = [0.0, 0.0, 0.0]


class CellSection(Section):
    id: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")] = "cell1"
    data_dir: Path = Path("data")
    designs_dir: Path = Path("designs")

    @field_validator("data_dir", "designs_dir")
    @classmethod
    def _own_directory(cls, v: Path) -> Path:
        return _not_a_system_directory(v)


class TrackSection(Section):
    """``[robot.track]``: the linear track the robot base rides on (absent: a fixed base).

    The track is the seventh axis, first in the chain: a configuration is ``axes_mm_deg`` (track mm,
    then the six joints in deg). ``origin_mm`` is the robot base origin in the cell's world frame at
    track position 0 and ``direction`` the world direction of + travel (normalised); the base keeps
    the world's orientation. Travel, speed and acceleration are checked like the arm's joints; the
    travel is shrunk by ``margin_mm`` at both ends. On the controller the track is a mechanical unit
    in the robot's motion group (docs/robot-setup.md, "Linear track"). ``jerk_max_mm_s3`` bounds
    the track's jerk in plans and stops, as ``joint_jerk_max_deg_s3`` does the joints'.
    """

    travel_min_mm: Finite = 0.0
    travel_max_mm: Finite = 6000.0
    margin_mm: NonNegativeFloat = 10.0
    speed_max_mm_s: Annotated[float, Field(gt=0, le=TRACK_SPEED_BOUND_MM_S, allow_inf_nan=False)] = 1000.0
    accel_max_mm_s2: Annotated[float, Field(gt=0, le=TRACK_ACCEL_BOUND_MM_S2, allow_inf_nan=False)] = 2000.0
    jerk_max_mm_s3: Annotated[float, Field(gt=0, le=TRACK_JERK_BOUND_MM_S3, allow_inf_nan=False)] = 20000.0
    origin_mm: Vec3 = [0.0, 0.0, 0.0]
    direction: Vec3 = [1.0, 0.0, 0.0]
    #: hold the carriage still when the arm reaches the whole plan from one position (a plate within
    #: the fixed arm's reach then gets the rail-less plan); false: the carriage always follows the passes
    hold: bool = True

    @model_validator(mode="after")
    def _travel_usable(self) -> TrackSection:
        lo, hi = self.travel_min_mm, self.travel_max_mm
        if max(abs(lo), abs(hi)) > TRACK_TRAVEL_BOUND_MM:
            raise ValueError(f"track travel [{lo}, {hi}] mm reaches beyond +-{TRACK_TRAVEL_BOUND_MM:g} mm")
        if not lo < hi:
            raise ValueError(f"track: travel_min_mm ({lo}) must be below travel_max_mm ({hi})")
        if 2 * self.margin_mm >= hi - lo:
            raise ValueError("track: margin_mm leaves no usable travel")
        if sum(v * v for v in self.direction) < 1e-12:
            raise ValueError("track: direction must not be the zero vector")
        return self

    def linear_track(self) -> LinearTrack:
        """The kinematic track with the usable travel (the hard travel shrunk by the margin)."""
        return LinearTrack(
            origin_mm=self.origin_mm,
            direction=self.direction,
            travel_min_mm=self.travel_min_mm + self.margin_mm,
            travel_max_mm=self.travel_max_mm - self.margin_mm,
            speed_max_mm_s=self.speed_max_mm_s,
            accel_max_mm_s2=self.accel_max_mm_s2,
            jerk_max_mm_s3=self.jerk_max_mm_s3,
        )


class RobotSection(Section):
    # EGM (UDP): the controller sends to egm_host:egm_port and we answer to its source address.
    egm_host: str = "127.0.0.1"
    egm_port: Port = 6511
    egm_comm_timeout_s: _seconds(60.0) = 1.0
    egm_watchdog_s: _seconds(10.0) = 0.1
    egm_history_len: Annotated[int, Field(ge=1000, le=10_000_000)] = 30_000
    # an in-process endpoint's reply thread (tools and tests that build an endpoint from cell.toml);
    # the daemon's motion process always answers from its own real-time thread
    egm_reply_thread: bool = True
    egm_reply_priority: Annotated[int, Field(ge=0, le=99)] = 20
    egm_reply_cpus: Annotated[
        list[Annotated[int, Field(ge=0, le=CPU_LIST_BOUND - 1)]], Field(max_length=CPU_LIST_BOUND)
    ] = []
    egm_switch_interval_s: Annotated[float, Field(gt=0, le=0.005, allow_inf_nan=False)] = 2e-4
    egm_reply_spin_us: Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)] = 150.0
    # the motion process (docs/operations.md "The motion process"): its cycle thread runs under
    # SCHED_FIFO at egm_reply_priority, pinned to egm_reply_cpus; memory locked; a refusal is logged
    # and shown in status, and with motion_realtime_required the daemon refuses to start instead
    motion_lock_memory: bool = True
    motion_realtime_required: bool = False
    # RWS (HTTP/HTTPS)
    rws_url: str = "http://127.0.0.1:8080"
    rws_profile: Literal["rws1", "rws2"] = "rws1"
    rws_user: str = "Default User"
    rws_password_env: str = "CELL_RWS_PASSWORD"
    rws_password_file: Path | None = None
    rws_timeout_s: _seconds(120.0) = 5.0
    rws_ca_file: Path | None = None
    rws_poll_interval_s: _seconds(10.0) = 0.2
    rws_mechunit: str = "ROB_1"
    # The RAPID module of drivers/abb_egm/rapid (CellEgm.mod) and the EGM settings written to it.
    rapid_task: str = "T_ROB1"
    rapid_module: str = "CellEgm"
    egm_pos_corr_gain: Annotated[float, Field(ge=0, le=20)] = 1.0
    egm_max_speed_deviation_deg_s: PositiveFloat = 1000.0
    egm_max_pos_deviation_deg: PositiveFloat = 1000.0
    egm_cond_time_s: _seconds(1e7) = 1e6
    egm_ramp_in_s: _seconds(60.0) = 0.05
    egm_lp_filter_hz: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = 20.0
    egm_sample_rate_ms: Annotated[int, Field(ge=4, le=1000, multiple_of=4)] = 4
    # Limits every commanded set-point is checked against (IRB 4600-40/2.55 defaults, with margins).
    # (the defaults: drivers/abb_egm/limits.py's RobotLimits, the one home of the robot's limits)
    joint_lower_deg: Joint6 = list(_DEFAULT_LIMITS.joint_lower_deg)
    joint_upper_deg: Joint6 = list(_DEFAULT_LIMITS.joint_upper_deg)
    joint_margin_deg: NonNegativeFloat = _DEFAULT_LIMITS.joint_margin_deg
    joint_speed_max_deg_s: PositiveJoint6 = list(_DEFAULT_LIMITS.joint_speed_max_deg_s)
    joint_accel_max_deg_s2: PositiveJoint6 = list(_DEFAULT_LIMITS.joint_accel_max_deg_s2)
    joint_jerk_max_deg_s3: PositiveJoint6 = list(_DEFAULT_LIMITS.joint_jerk_max_deg_s3)
    tcp_speed_max_mm_s: Annotated[float, Field(gt=0, le=TCP_SPEED_BOUND_MM_S, allow_inf_nan=False)] = 250.0
    workspace_min_mm: Vec3 = [-500.0, -2000.0, 100.0]
    workspace_max_mm: Vec3 = [2600.0, 2000.0, 2400.0]
    tracking_error_max_mm: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 5.0
    # Planning: smallest |joint 5| along a plan (distance from the wrist singularity).
    wrist_margin_deg: Annotated[float, Field(ge=0, lt=90, allow_inf_nan=False)] = 5.0
    # Mounting: flange -> sensor (laser) frame, from the hand-eye calibration.
    sensor_in_flange: Pose = Pose(pos_mm=[0.0, 0.0, 150.0])
    # The linear track (seventh axis), or None for a fixed base.
    track: TrackSection | None = None

    @field_validator("tcp_speed_max_mm_s")
    @classmethod
    def _tcp_speed_usable(cls, v: float) -> float:
        if v < TCP_SPEED_MIN_MM_S:
            raise ValueError(
                f"{v:g} mm/s is below {TCP_SPEED_MIN_MM_S:g} mm/s: no scan would end (a 1.2 m pass takes 20 min "
                "at 1 mm/s)"
            )
        return v

    @field_validator("egm_max_speed_deviation_deg_s")
    @classmethod
    def _speed_deviation_meaningful(cls, v: float) -> float:
        if v > EGM_SPEED_DEVIATION_BOUND_DEG_S:
            raise ValueError(
                f"{v:g} deg/s is beyond {EGM_SPEED_DEVIATION_BOUND_DEG_S:g} deg/s, about three times the "
                "IRB 4600's fastest joint (360 deg/s): a deviation that large never binds"
            )
        return v

    @field_validator("rws_url")
    @classmethod
    def _url_parses(cls, v: str) -> str:
        parts = urlsplit(v)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"expected an http:// or https:// URL with a host, got {v!r}")
        if parts.port is not None and not 1 <= parts.port <= 65535:
            raise ValueError(f"port out of range in {v!r}")
        return v

    @model_validator(mode="after")
    def _limits_ordered(self) -> RobotSection:
        for i, (lo, hi) in enumerate(zip(self.joint_lower_deg, self.joint_upper_deg, strict=True)):
            if lo < Q_MIN_DEG[i] or hi > Q_MAX_DEG[i]:
                raise ValueError(
                    f"joint {i + 1}: limits [{lo}, {hi}] deg leave the IRB 4600's range "
                    f"[{Q_MIN_DEG[i]:g}, {Q_MAX_DEG[i]:g}] deg"
                )
            if not lo < hi:
                raise ValueError(
                    f"joint {i + 1}: joint_lower_deg ({lo}) must be below joint_upper_deg ({hi})"
                )
            if 2 * self.joint_margin_deg >= hi - lo:
                raise ValueError(f"joint {i + 1}: joint_margin_deg leaves no usable range")
        for i, (v, a, j) in enumerate(
            zip(
                self.joint_speed_max_deg_s,
                self.joint_accel_max_deg_s2,
                self.joint_jerk_max_deg_s3,
                strict=True,
            )
        ):
            if v > QD_MAX_DEG_S[i]:
                raise ValueError(
                    f"joint {i + 1}: joint_speed_max_deg_s ({v}) exceeds the IRB 4600's {QD_MAX_DEG_S[i]:g} deg/s"
                )
            if a > JOINT_ACCEL_BOUND_DEG_S2 or j > JOINT_JERK_BOUND_DEG_S3:
                raise ValueError(
                    f"joint {i + 1}: acceleration {a} deg/s^2 / jerk {j} deg/s^3 beyond the bounds "
                    f"{JOINT_ACCEL_BOUND_DEG_S2:g} / {JOINT_JERK_BOUND_DEG_S3:g}"
                )
        for axis, lo, hi in zip("xyz", self.workspace_min_mm, self.workspace_max_mm, strict=True):
            if max(abs(lo), abs(hi)) > WORKSPACE_BOUND_MM:
                raise ValueError(
                    f"workspace {axis}: [{lo}, {hi}] mm reaches beyond +-{WORKSPACE_BOUND_MM:g} mm "
                    "(the arm's 2.55 m reach with tool and sensor)"
                )
            if not lo < hi:
                raise ValueError(
                    f"workspace {axis}: workspace_min_mm ({lo}) must be below workspace_max_mm ({hi})"
                )
        if len(set(self.egm_reply_cpus)) != len(self.egm_reply_cpus):
            raise ValueError("egm_reply_cpus: a CPU is named twice")
        pos_dev = self.egm_max_pos_deviation_deg
        if self.track is None and pos_dev > EGM_POS_DEVIATION_BOUND_DEG:
            raise ValueError(
                f"egm_max_pos_deviation_deg ({pos_dev:g}) is beyond {EGM_POS_DEVIATION_BOUND_DEG:g} deg, more "
                "than any joint's whole range (800 deg); only a track (in mm for it) needs more"
            )
        if pos_dev > TRACK_TRAVEL_BOUND_MM:
            raise ValueError(
                f"egm_max_pos_deviation_deg ({pos_dev:g}) is beyond {TRACK_TRAVEL_BOUND_MM:g}, the longest "
                "track's travel in mm (with a track it bounds the track in mm)"
            )
        offset = sum(v * v for v in self.sensor_in_flange.pos_mm) ** 0.5
        if offset > HAND_EYE_BOUND_MM:
            raise ValueError(
                f"sensor_in_flange.pos_mm is {offset:.4g} mm from the flange, beyond {HAND_EYE_BOUND_MM:g} mm "
                "(the IRB 4600 reaches 2.55 m): a hand-eye calibration in metres, or a typo?"
            )
        if self.track is not None:
            travel = self.track.travel_max_mm - self.track.travel_min_mm
            if self.egm_max_pos_deviation_deg < travel:
                raise ValueError(
                    f"egm_max_pos_deviation_deg ({self.egm_max_pos_deviation_deg:g}) is below the track's travel "
                    f"({travel:g} mm): EGMActJoint's \\MaxPosDeviation also bounds the track (in mm), so a long "
                    "move would end the session (docs/robot-setup.md, 'Linear track')"
                )
        if self.rws_profile == "rws2" and not self.rws_url.startswith("https://"):
            raise ValueError(
                "rws_profile 'rws2' (RobotWare 7) speaks HTTPS: rws_url must start with https://"
            )
        return self

    def limits(self) -> RobotLimits:
        """The joint limits of this ``[robot]`` as the one value planning and motion read."""
        return RobotLimits(
            joint_lower_deg=tuple(self.joint_lower_deg),
            joint_upper_deg=tuple(self.joint_upper_deg),
            joint_margin_deg=self.joint_margin_deg,
            joint_speed_max_deg_s=tuple(self.joint_speed_max_deg_s),
            joint_accel_max_deg_s2=tuple(self.joint_accel_max_deg_s2),
            joint_jerk_max_deg_s3=tuple(self.joint_jerk_max_deg_s3),
        )


class LaserSection(Section):
    # Which profile source reads the sensor (drivers/laser/registry.py, docs/sensors.md): "hd8" (the
    # HD8 protocol over TCP: host, control_port, data_port) or "gige" (a GigE Vision / GenICam 3D
    # profiler through Aravis: gige_device, or host when that is unset).
    protocol: Literal["hd8", "gige"] = "hd8"
    host: str = "127.0.0.1"
    control_port: Port = 3190
    data_port: Port = 3196
    # GigE Vision: the device's IP address or Aravis id ("Vendor-Model-Serial"); None: host
    gige_device: str | None = None
    # GigE Vision: profiles per GVSP block (the range image's Height; its duration at rate_hz is the
    # latency it adds: 10 at 200 Hz is 50 ms), first sensor column (OffsetX)
    gige_rows_per_buffer: Annotated[int, Field(ge=1, le=65_535)] = 10
    gige_x_offset_px: Annotated[int, Field(ge=0)] = 0
    # GigE Vision: GVSP packet size in bytes; None negotiates the largest the network takes
    gige_packet_size: Annotated[int, Field(ge=576, le=65_000)] | None = None
    line_width_mm: PositiveFloat = 50.0
    points_per_profile: Annotated[int, Field(ge=2, le=4096)] = 500
    rate_hz: Annotated[float, Field(gt=0, le=LASER_RATE_BOUND_HZ, allow_inf_nan=False)] = 200.0
    exposure_us: Annotated[float, Field(ge=10, le=100_000)] = 500.0
    depth_min_mm: PositiveFloat = 70.0
    depth_max_mm: PositiveFloat = 130.0
    latency_ms: Finite = 0.0
    # which sensor stamp the acquisition uses: "us" (protocol's mid-exposure us) or "ms" (HD8 counter)
    sensor_clock: Literal["us", "ms"] = "us"
    watchdog_s: _seconds(60.0) = 0.5
    buffer_profiles: Annotated[int, Field(ge=100)] = 20_000

    @field_validator("buffer_profiles")
    @classmethod
    def _buffer_fits_in_memory(cls, v: int) -> int:
        if v > BUFFER_PROFILES_BOUND:
            raise ValueError(
                f"{v} profiles is beyond {BUFFER_PROFILES_BOUND}: about 80 min of profiles at 200 Hz, 6 GB at "
                "500 points a profile"
            )
        return v

    @model_validator(mode="after")
    def _range_ordered(self) -> LaserSection:
        if not self.depth_min_mm < self.depth_max_mm:
            raise ValueError(
                f"depth_min_mm ({self.depth_min_mm}) must be below depth_max_mm ({self.depth_max_mm})"
            )
        if self.exposure_us * 1e-6 * self.rate_hz > 1.0:
            raise ValueError(
                f"exposure_us ({self.exposure_us}) does not fit in one profile period at rate_hz ({self.rate_hz})"
            )
        return self


class ScanSection(Section):
    standoff_mm: PositiveFloat = 100.0
    overlap_fraction: Annotated[float, Field(ge=0, lt=0.9)] = 0.2
    speed_mm_s: PositiveFloat | Literal["auto"] = "auto"
    profile_spacing_mm: PositiveFloat = 0.5
    transit_speed_mm_s: PositiveFloat = 250.0
    edge_passes: bool = True
    # The raster passes run along the plate's "longer" or "shorter" footprint axis, or "fastest":
    # whichever gives the shorter timed scan within the limits (the other where one is refused).
    pass_axis: Literal["fastest", "longer", "shorter"] = "fastest"
    placement_uncertainty_mm: NonNegativeFloat = 30.0
    placement_uncertainty_deg: NonNegativeFloat = 2.0
    placement_z_mm: Finite = 300.0
    edge_tilt_deg: Annotated[float, Field(ge=0, lt=80, allow_inf_nan=False)] = 30.0
    # The sensor leans this much along the passes (about its laser line), so that the arm's forearm
    # never lines up with the sensor axis (the wrist singularity, |joint 5| -> 0) where a sensor
    # looking straight down would need it: a plate low under the base (a riser) reached near and far.
    sweep_pitch_deg: Annotated[float, Field(ge=0, lt=45, allow_inf_nan=False)] = 0.0
    link_clearance_mm: NonNegativeFloat = 30.0
    approach_mm: PositiveFloat = 100.0
    # Column pitch of the cloud published to the analysis (every k-th point of each profile; the raw
    # files keep every point). 0 publishes every point. Edge passes (boundary, thickness faces) have
    # their own, usually finer, pitch.
    publish_pitch_mm: NonNegativeFloat = 0.5
    edge_publish_pitch_mm: NonNegativeFloat = 0.5
    # At most this many points published: a larger scan is thinned further by a whole factor
    # (cellctl.acquisition.publish.budget_steps) so the worker's memory and time stay as measured for
    # that many points (docs/operations.md: a 6 m plate). The raw files keep every point.
    publish_max_points: int = 40_000_000

    @field_validator("publish_max_points")
    @classmethod
    def _publication_bounded(cls, v: int) -> int:
        if v < PUBLISH_POINTS_MIN:
            raise ValueError(
                f"{v} points is below {PUBLISH_POINTS_MIN}, too few to judge a plate (0 no longer turns the bound "
                "off: an unbounded publication can exhaust a worker's memory)"
            )
        if v > PUBLISH_POINTS_BOUND:
            raise ValueError(
                f"{v} points is beyond {PUBLISH_POINTS_BOUND}, ten times the 6 m plate's 33 M: no worker analyses "
                "that in its measured memory"
            )
        return v


ZenohRole = Literal["operator", "worker", "viewer", "daemon"]
_ZENOH_USER = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@\-]{0,63}$")


class ZenohAccess(Section):
    """Zenoh user/password authentication and role-based access control (see docs/api.md).

    ``user`` and its password (``password_env`` / ``password_file``, never the file) are what this
    process presents. On the serving side (daemon or router) ``dictionary_file`` holds every
    ``user:password`` line and ``roles`` maps a role to its users: ``operator`` triggers and
    controls scans and reads state, ``worker`` receives clouds and publishes events and reports,
    ``viewer`` only reads state, reports and liveliness, ``daemon`` uses the whole key space (a
    daemon behind a router). With ``roles`` empty every dictionary user has the whole key space.
    """

    enabled: bool = False
    user: str = "cellctl"
    password_env: str = "CELL_ZENOH_PASSWORD"
    password_file: Path | None = None
    dictionary_file: Path | None = None
    roles: dict[ZenohRole, list[str]] = {}
    # "password": user/password; "tls": mutual TLS, roles name certificate common names; "both".
    auth: Literal["password", "tls", "both"] = "password"
    tls_ca_file: Path | None = None  # the cell's CA (PEM): peers must present a certificate it signed
    tls_cert_file: Path | None = None  # this process's certificate (PEM)
    tls_key_file: Path | None = None  # its private key (PEM, a secrets file: chmod 600)

    @model_validator(mode="after")
    def _tls_files_given(self) -> ZenohAccess:
        if self.auth != "password":
            missing = [
                n for n in ("tls_ca_file", "tls_cert_file", "tls_key_file") if getattr(self, n) is None
            ]
            if missing:
                raise ValueError(f"auth {self.auth!r} needs {', '.join(missing)}")
        return self

    @field_validator("roles")
    @classmethod
    def _role_users_are_names(cls, v: dict[str, list[str]]) -> dict[str, list[str]]:
        for role, users in v.items():
            for user in users:
                if not _ZENOH_USER.fullmatch(user):
                    raise ValueError(f"roles.{role}: {user!r} is not a user name (letters, digits, _ . @ -)")
        return v


class ZenohSection(Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: Endpoints = ["tcp/127.0.0.1:7447"]
    connect: Endpoints = []
    multicast_scouting: bool = False
    key_prefix: Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-{}]+(/[A-Za-z0-9_\-{}]+)*$")] = "cell/{cell_id}"
    trigger_timeout_s: _seconds(600.0) = 10.0
    shm_pool_mb: Annotated[int, Field(ge=0, le=65536)] = 0
    access: ZenohAccess = ZenohAccess()

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints_parse(cls, v: list[str]) -> list[str]:
        for ep in v:
            m = _ZENOH_ENDPOINT.match(ep)
            if not m or not 0 <= int(ep.rsplit(":", 1)[1]) <= 65535:
                raise ValueError(f"{ep!r} is not a Zenoh endpoint like 'tcp/127.0.0.1:7447'")
        return v

    @model_validator(mode="after")
    def _client_connects(self) -> ZenohSection:
        if self.mode == "client" and not self.connect:
            raise ValueError("mode 'client' needs at least one 'connect' endpoint")
        return self


class TolerancesSection(Section):
    """Template-to-plate tolerances: 'standard' range and absolute 'limit' (CSQS 2016 defaults)."""

    standard: str = "CSQS 2016 (doubly curved plate)"
    deviation_standard_mm: PositiveFloat = 2.0
    deviation_limit_mm: PositiveFloat = 3.0
    frame_gap_standard_mm: PositiveFloat = 4.0
    frame_gap_limit_mm: PositiveFloat = 5.0
    length_gap_standard_mm: PositiveFloat = 3.0
    length_gap_limit_mm: PositiveFloat = 5.0

    @model_validator(mode="after")
    def _standard_within_limit(self) -> TolerancesSection:
        for name in ("deviation", "frame_gap", "length_gap"):
            std, lim = getattr(self, f"{name}_standard_mm"), getattr(self, f"{name}_limit_mm")
            if std > lim:
                raise ValueError(f"{name}_standard_mm ({std}) must not exceed {name}_limit_mm ({lim})")
        return self


class AnalysisSection(Section):
    # "auto": the paper's spacing rule over the whole plate (analysis.templates.paper_line_count: 14 and 7
    # on the paper's 1200 x 800 mm plate, 74 and 19 on a 6000 x 2000 mm one); with a template table
    # given, "auto" leaves the lines to the table
    transverse_count: Annotated[int, Field(ge=0, le=500)] | Literal["auto"] = "auto"
    transverse_spacing_mm: PositiveFloat = 80.0
    longitudinal_count: Annotated[int, Field(ge=0, le=500)] | Literal["auto"] = "auto"
    longitudinal_spacing_mm: PositiveFloat = 100.0
    diagonals: bool = True
    sample_step_mm: PositiveFloat = 1.0
    # "rigid": one template rests on the whole plate (the paper's 3D fit); "per_line": a template per
    # detection line, on its own section (the paper's 2D case). compare: the report carries both
    template_fit: Literal["rigid", "per_line"] = "rigid"
    template_fit_compare: bool = False
    icp_stop_mm: PositiveFloat = 0.1
    workers: Annotated[int, Field(ge=1, le=64)] = 1
    tolerances: TolerancesSection = TolerancesSection()
    # Workers and the job dispatcher (docs/api.md, "Jobs and workers").
    callable: Annotated[str, Field(pattern=r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")] = (
        "analysis.pipeline:analyse_job"
    )
    heartbeat_s: _seconds(60.0) = 1.0
    ack_timeout_s: _seconds(3600.0) = 10.0
    heartbeat_timeout_s: _seconds(3600.0) = 10.0
    job_timeout_s: _seconds(86_400.0) = 900.0
    max_attempts: Annotated[int, Field(ge=1, le=10)] = 3

    @model_validator(mode="after")
    def _heartbeat_fits(self) -> AnalysisSection:
        if self.heartbeat_timeout_s < 2 * self.heartbeat_s:
            raise ValueError(
                f"heartbeat_timeout_s ({self.heartbeat_timeout_s}) must be at least twice heartbeat_s "
                f"({self.heartbeat_s}), or one late heartbeat costs a retry"
            )
        return self


class FormingSection(Section, PlanSettings):
    """The line-heating plan made after every analysis (docs/forming.md, "The plan of a job"): the
    crew's rules (least spacing, edge margin, lines per round, faces), the heat-input range, the
    material of the coefficient table, the thickness when the report has none, the FE element."""

    # false: no plan is made; heating-plan.json then says so (status no_plan)
    enabled: bool = True


class SimPlate(Section):
    """The simulated plate: a design of ``kind`` with radii and the seeded forming error, or
    (``kind = "mesh"``) the formed plate's top surface from ``mesh_file`` (PLY / STL / OBJ, mm, in
    the frame of ``design_file``, the design the trigger names: a mesh or IGES / STEP). A relative
    path is resolved against the cell.toml's folder (:func:`load_config`). docs/simulator.md."""

    kind: Literal["sail", "saddle", "twisted", "cylinder", "flat", "mesh"] = "sail"
    length_mm: PositiveFloat = 1200.0
    width_mm: PositiveFloat = 800.0
    thickness_mm: PositiveFloat = 15.0
    radius_x_mm: PositiveFloat = 4000.0
    radius_y_mm: PositiveFloat = 3000.0
    forming_error: Literal["none", "default"] = "default"
    seed: int = 7
    mesh_file: Path | None = None
    design_file: Path | None = None

    @model_validator(mode="after")
    def _mesh_files_usable(self) -> SimPlate:
        if self.kind != "mesh":
            for key in ("mesh_file", "design_file"):
                if getattr(self, key) is not None:
                    raise ValueError(f'{key} is read only with kind = "mesh" (kind is {self.kind!r})')
            return self
        from analysis.design.cad import CAD_SUFFIXES, DESIGN_SUFFIXES, MESH_SUFFIXES
        from analysis.design.mesh import MeshError, surface_mismatch

        for key in ("mesh_file", "design_file"):
            if getattr(self, key) is None:
                raise ValueError(f'kind = "mesh" needs {key}')
        try:
            mesh = sim_plate_mesh(self.mesh_file)
        except MeshError as exc:
            raise ValueError(f"mesh_file {exc}") from None
        suffix = self.design_file.suffix.lower()
        if suffix not in DESIGN_SUFFIXES:
            raise ValueError(
                f"design_file {self.design_file}: unsupported design format (use {', '.join(DESIGN_SUFFIXES)})"
            )
        if suffix in CAD_SUFFIXES:
            try:  # read whole when the simulator starts (seconds): here only that it is there
                with self.design_file.open("rb"):
                    pass
            except OSError as exc:
                raise ValueError(
                    f"design_file {self.design_file}: cannot read: {exc.strerror or exc}"
                ) from None
        elif suffix in MESH_SUFFIXES:
            try:
                design = sim_plate_mesh(self.design_file)
            except MeshError as exc:
                raise ValueError(f"design_file {exc}") from None
            why = surface_mismatch(mesh, design)
            if why:
                raise ValueError(
                    f"mesh_file {self.mesh_file} does not match design_file {self.design_file}: {why}"
                )
        return self


def sim_plate_mesh(path: Path) -> TriMesh:
    """The triangle mesh of a ``[sim.plate]`` file (read once per file version in a process: the
    config is validated more than once). Raises ``analysis.design.mesh.MeshError`` naming the file."""
    from analysis.design.mesh import MeshError

    try:
        st = Path(path).stat()
    except OSError as exc:
        raise MeshError(
            f"{path}: {'no such file' if isinstance(exc, FileNotFoundError) else exc.strerror}"
        ) from None
    return _read_sim_plate_mesh(str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=4)
def _read_sim_plate_mesh(path: str, _mtime_ns: int, _size: int) -> TriMesh:
    from analysis.design.mesh import load_mesh

    return load_mesh(path)


class SimPlacement(Section):
    """Where the simulated plate lies: its design origin at ``pos_mm``, turned ``angle_deg`` about z."""

    pos_mm: Vec3 = [1500.0, 0.0, 300.0]
    angle_deg: Finite = 3.0

    def to_placement(self) -> Placement:
        """The same as the product's placement type (what a trigger sends for this plate)."""
        return Placement.on_bed(self.pos_mm[0], self.pos_mm[1], self.angle_deg, z_mm=self.pos_mm[2])


class SimClocks(Section):
    sensor_offset_ms: Finite = 30.0
    sensor_drift_ppm: Finite = 50.0
    sensor_counter_start_ms: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    network_jitter_ms: NonNegativeFloat = 0.3


class SimFaults(Section):
    egm_loss_fraction: Fraction = 0.0
    egm_burst_ms: NonNegativeFloat = 0.0
    egm_delay_ms: NonNegativeFloat = 0.0
    egm_jitter_ms: NonNegativeFloat = 0.0
    egm_duplicate_fraction: Fraction = 0.0
    egm_reorder_fraction: Fraction = 0.0
    egm_corrupt_fraction: Fraction = 0.0
    egm_stop_sending: bool = False
    egm_rx_loss_fraction: Fraction = 0.0
    laser_disconnect_after_frames: Annotated[int, Field(ge=0)] = 0
    laser_corrupt_fraction: Fraction = 0.0
    laser_drop_fraction: Fraction = 0.0


class SimSection(Section):
    egm_cycle_ms: Annotated[float, Field(ge=1, le=100, allow_inf_nan=False)] = EGM_CYCLE_S * 1e3
    egm_q_start_deg: Joint6 = [0.0, 0.0, 0.0, 0.0, 30.0, 0.0]
    egm_track_start_mm: Finite = 0.0  # the simulated track's position at start (with [robot.track])
    egm_stream_when_idle: bool = True
    # The simulated controller's event loop (the EGM cycle, the sensor's frames, RWS) and its helper
    # threads run under SCHED_FIFO at this priority when permitted (0: normal priority). 10 (level with
    # the daemon's loop) by default; 30 (above the motion process's 20) lets one simulated cell keep
    # its controller's clock as a real controller does, but two cells on two cores then starve both
    # motion processes. docs/simulator.md.
    loop_priority: Annotated[int, Field(ge=0, le=99)] = 10
    rws_port: Port = 8080
    rws_users: dict[str, str] = {"Default User": "CELL_RWS_PASSWORD"}
    rws_max_sessions: Annotated[int, Field(ge=1, le=1000)] = 70
    rws_session_idle_s: PositiveFloat = 300.0
    opmode: OpMode = AUTO
    # The run-time fault-control queryable of `cellctl sim` (docs/simulator.md); it lives only in
    # the simulator process, on its own Zenoh endpoint, never in the daemon of a real cell.
    fault_control: bool = True
    fault_listen: str = "tcp/127.0.0.1:7448"
    depth_noise_mm: NonNegativeFloat = 0.02
    outlier_fraction: Fraction = 0.0005
    plate: SimPlate = SimPlate()
    placement: SimPlacement = SimPlacement()
    clocks: SimClocks = SimClocks()
    faults: SimFaults = SimFaults()

    @field_validator("fault_listen")
    @classmethod
    def _fault_endpoint_parses(cls, v: str) -> str:
        m = _ZENOH_ENDPOINT.match(v)
        if not m or not 0 <= int(v.rsplit(":", 1)[1]) <= 65535:
            raise ValueError(f"{v!r} is not a Zenoh endpoint like 'tcp/127.0.0.1:7448'")
        return v

    @field_validator("rws_users")
    @classmethod
    def _users_name_env_vars(cls, v: dict[str, str]) -> dict[str, str]:
        # Values are the *names* of environment variables holding the simulator's passwords.
        for user, env in v.items():
            if not _ENV_NAME.fullmatch(env):
                # never echo the value: it may be the password itself
                raise ValueError(
                    f"user {user!r}: expected the name of an environment variable (A-Z, 0-9, _) holding "
                    "its password, not the password; the value given is not shown"
                )
        return v


class DaemonSection(Section):
    """`cellctl run`: publication and timing knobs of the daemon, and its trigger queue (docs/api.md)."""

    # the state publication is sent on every change and at least this often
    status_period_s: Annotated[float, Field(gt=0, le=60, allow_inf_nan=False)] = 1.0
    # wait for the controller's first EGM packet after the EGM program started
    feedback_timeout_s: Annotated[float, Field(gt=0, le=120, allow_inf_nan=False)] = 5.0
    # pass markers are checked against the executor's playback time this often (a pass boundary lands
    # within this of its planned time)
    marker_period_s: Annotated[float, Field(ge=0.001, le=0.1, allow_inf_nan=False)] = 0.01
    # sensor streaming before the arm moves (clock fits gather pairs, the sensor settles)
    settle_s: Annotated[float, Field(ge=0, le=30, allow_inf_nan=False)] = 1.0
    # render report.html / .pdf beside report.json when the worker's results arrive
    write_html_report: bool = True
    # run the event loop under SCHED_FIFO and hold the CPUs' wake-up latency when permitted
    realtime: bool = True
    # triggers waiting while a scan holds the robot; 0 refuses a trigger while busy
    queue_max: Annotated[int, Field(ge=0, le=100)] = 4
    # pre-flight before motion: the data directory must keep this much free beyond the planned
    # scan's raw-data estimate (cellctl/daemon/preflight.py), or the job fails before the arm moves
    min_free_mb: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] = 200.0


class WorkerSection(Section):
    """`cellctl worker`: where it keeps its own files and which cells it serves (docs/operations.md)."""

    # the worker's own directory (design cache, a job's results until they are sent); relative to
    # the worker's working directory. Nothing in it is read by the daemon: results go over Zenoh.
    data_dir: Path = Path("worker-data")

    @field_validator("data_dir")
    @classmethod
    def _own_directory(cls, v: Path) -> Path:
        return _not_a_system_directory(v)

    # the cells this worker takes jobs from: key prefixes ("cell/a", "cell/b") or one key expression
    # of them ("cell/*"); empty: the cell this file configures ([zenoh] key_prefix)
    cells: list[Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-*]+(/[A-Za-z0-9_\-*]+)*$")]] = []
    # MB of touched heap the analysis process keeps ready while a streamed scan arrives (400 B a
    # point received, at most this; cellctl.worker.heap): page faults were half the sail's analysis. 0: off
    # (below 2 GiB: glibc's trim threshold, which keeps it, is an int)
    heap_reserve_mb: int = Field(1536, ge=0, le=2047)


class RouterSection(Section):
    """`cellctl router`: Zenoh's router for a fleet of cells (docs/operations.md, "Fleet")."""

    # where the router listens (cells connect as peers, workers and operator tools as clients)
    listen: Endpoints = ["tcp/0.0.0.0:7447"]
    # the cells whose keys the access rules (when [zenoh.access] is on) cover: their key prefixes;
    # empty: this file's cell only
    cells: list[Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")]] = []

    @field_validator("listen")
    @classmethod
    def _endpoints_parse(cls, v: list[str]) -> list[str]:
        if not v:
            raise ValueError("a router listens on at least one endpoint")
        return ZenohSection._endpoints_parse(v)


class LocateSection(Section):
    """The locate run: a few fast flat passes over the bed that find the plate (docs/locate.md).

    The bed is ``bed_min_xy_mm`` .. ``bed_max_xy_mm`` in the world (robot base) frame: plates lie
    within it. The passes fly ``standoff_mm`` above the design's highest edge (the plate lying at
    ``[scan] placement_z_mm``), so that its edges are within the sensor's depth range below them, and
    never nearer than ``[laser] depth_min_mm`` to its highest point; at ``speed_mm_s``,
    ``pass_spacing_mm`` apart:
    one family along the bed's longer side over the whole bed; one across it over the middle square
    when the first leaves the fit sliding, or finds the plate's edges within ``across_within_deg`` of
    square to its passes (an edge crossed square-on is seen only to a profile's spacing). Where the
    first found the plate's yaw and place along the bed, the passes across are ``across_passes``
    passes at 20 .. 80 % of its extent along the bed, each over the bed's width at the height of the
    outline it crosses (``standoff_mm`` above it); else the square family at the locate height.
    ``bed_z_mm``: the bed's top face (points up to ``min_height_mm`` above it are no plate).
    ``plate_band_mm``: points further than this below the design's lowest point or above its highest
    (the plate at ``[scan] placement_z_mm``) are no plate (supports beside a turned plate, clamps).
    A given placement is checked (``check_given``) and refused when the plate found lies more than
    ``max_offset_mm`` / ``max_angle_deg`` from it. ``convention_yaw_deg``: a plate that looks the same
    turned by 180 deg is taken at the yaw within 90 deg of this, when no placement is given.
    ``allow_face_down``: the mirrored outline is fitted too (a plate the right way up is required
    to plan, so a face-down find is refused with that reason). ``max_rms_mm``: a worse outline fit
    is refused.
    """

    check_given: bool = True
    bed_min_xy_mm: Annotated[list[Finite], Field(min_length=2, max_length=2)] = [800.0, -700.0]
    bed_max_xy_mm: Annotated[list[Finite], Field(min_length=2, max_length=2)] = [2200.0, 700.0]
    bed_z_mm: Finite = 100.0
    min_height_mm: NonNegativeFloat = 5.0
    plate_band_mm: PositiveFloat = 8.0
    standoff_mm: PositiveFloat = 75.0
    speed_mm_s: PositiveFloat = 225.0
    pass_spacing_mm: Annotated[float, Field(ge=20.0, le=2000.0, allow_inf_nan=False)] = 350.0
    across_within_deg: Annotated[float, Field(ge=0.0, le=45.0, allow_inf_nan=False)] = 10.0
    across_passes: Annotated[int, Field(ge=1, le=6)] = 2
    max_offset_mm: PositiveFloat = 20.0
    max_angle_deg: PositiveFloat = 1.0
    convention_yaw_deg: Annotated[float, Field(ge=-180.0, le=180.0, allow_inf_nan=False)] = 0.0
    allow_face_down: bool = False
    max_rms_mm: PositiveFloat = 2.0

    @model_validator(mode="after")
    def _bed_has_extent(self) -> LocateSection:
        if not all(lo < hi for lo, hi in zip(self.bed_min_xy_mm, self.bed_max_xy_mm, strict=True)):
            raise ValueError(
                f"bed_min_xy_mm {self.bed_min_xy_mm} must be below bed_max_xy_mm {self.bed_max_xy_mm} on x and y"
            )
        return self


class OpcuaSection(Section):
    """`cellctl opcua`: the cell's OPC UA server for the plant (OPC 40210 GMS; docs/opcua.md).

    ``enabled``: the command refuses to start when false. ``bind`` / ``port``: where it listens
    (loopback by default: a plant network is a choice made here). The endpoint is Basic256Sha256
    Sign & Encrypt with ``cert_file`` / ``key_file`` (the server's certificate, issued by the
    cell's CA, and its private key, a secrets file), users and roles from the HMI's ``users_file``
    (``cellctl hmi adduser``); anonymous is refused. ``trusted_dir``: the certificates (PEM or DER)
    a client's certificate must be issued by or be (the cell's CA): any other is refused.
    ``allow_insecure``: instead, security None and anonymous clients (tests, a trusted loopback only).
    """

    enabled: bool = False
    bind: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 4840
    cert_file: Path | None = None
    key_file: Path | None = None
    users_file: Path | None = None
    trusted_dir: Path | None = None
    allow_insecure: bool = False

    @model_validator(mode="after")
    def _secured_or_insecure_said(self) -> OpcuaSection:
        if self.enabled and not self.allow_insecure:
            missing = [
                k for k in ("cert_file", "key_file", "users_file", "trusted_dir") if getattr(self, k) is None
            ]
            if missing:
                raise ValueError(
                    f"the secured endpoint needs {', '.join(missing)} (or allow_insecure = true: no security)"
                )
        return self


class CellConfig(BaseSettings):
    """The whole `cell.toml`."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_DELIMITER,
        extra="forbid",
        frozen=True,
        nested_model_default_partial_update=True,
    )

    cell: CellSection = CellSection()
    robot: RobotSection = RobotSection()
    laser: LaserSection = LaserSection()
    scan: ScanSection = ScanSection()
    zenoh: ZenohSection = ZenohSection()
    analysis: AnalysisSection = AnalysisSection()
    forming: FormingSection = FormingSection()
    sim: SimSection = SimSection()
    daemon: DaemonSection = DaemonSection()
    worker: WorkerSection = WorkerSection()
    router: RouterSection = RouterSection()
    locate: LocateSection = LocateSection()
    opcua: OpcuaSection = OpcuaSection()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The file's values arrive as init kwargs; the environment overrides them.
        return (env_settings, init_settings)

    @model_validator(mode="after")
    def _speeds_within_the_tcp_cap(self) -> CellConfig:
        cap = self.robot.tcp_speed_max_mm_s
        for name, v in (
            ("scan.speed_mm_s", self.scan.speed_mm_s),
            ("scan.transit_speed_mm_s", self.scan.transit_speed_mm_s),
            ("locate.speed_mm_s", self.locate.speed_mm_s),
        ):
            if isinstance(v, int | float) and v > cap:
                raise ValueError(
                    f"{name} ({v:g} mm/s) is beyond the robot's TCP speed cap, robot.tcp_speed_max_mm_s ({cap:g} mm/s)"
                )
        return self

    @model_validator(mode="after")
    def _sim_track_start_on_the_track(self) -> CellConfig:
        track = self.robot.track
        start = self.sim.egm_track_start_mm
        if (
            track is not None
            and not track.travel_min_mm + track.margin_mm <= start <= track.travel_max_mm - track.margin_mm
        ):
            raise ValueError(
                f"sim.egm_track_start_mm ({start:g}) is outside the track's usable travel "
                f"[{track.travel_min_mm + track.margin_mm:g}, {track.travel_max_mm - track.margin_mm:g}] mm"
            )
        return self

    @model_validator(mode="after")
    def _sim_mesh_plate_fits_the_bed(self) -> CellConfig:
        sp = self.sim.plate
        if sp.kind != "mesh":
            return self
        from analysis.design.mesh import principal_extents_mm

        length = float(principal_extents_mm(sim_plate_mesh(sp.mesh_file).vertices_mm)[0])
        (x0, y0), (x1, y1) = self.locate.bed_min_xy_mm, self.locate.bed_max_xy_mm
        bed = math.hypot(x1 - x0, y1 - y0)
        if length > 2.0 * bed:
            raise ValueError(
                f"sim.plate.mesh_file {sp.mesh_file}: the plate is {length:.0f} mm long, more than twice the "
                f"bed's diagonal ({bed:.0f} mm, locate.bed_min_xy_mm .. bed_max_xy_mm): not in mm?"
            )
        return self

    @property
    def key_prefix(self) -> str:
        """The Zenoh key prefix with the cell id filled in."""
        return self.zenoh.key_prefix.replace("{cell_id}", self.cell.id)


class ConfigError(Exception):
    """A configuration that cannot be used; ``problems`` holds one readable line per problem."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = problems
        super().__init__(f"{source}: " + "; ".join(problems))


def _format_value(value: Any) -> str:
    text = json.dumps(value, default=str) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _looks_secret(key: str) -> bool:
    k = key.lower()
    return any(w in k for w in _SECRET_WORDS) and not k.endswith(("_env", "_file"))


def _problems_from(err: ValidationError, env_keys: set[str]) -> list[str]:
    problems = []
    for e in err.errors(include_url=False):
        # a TOML key may hold a newline or escape codes: escape them, one problem stays one line
        loc = [
            str(p) if str(p).isprintable() else str(p).encode("unicode_escape").decode("ascii")
            for p in e["loc"]
            if not str(p).startswith(("function-", "literal["))
        ]
        path = ".".join(loc) or "(top level)"
        msg = e["msg"].removeprefix("Value error, ")
        origin = " (from the environment)" if path.split(".")[0] in env_keys else ""
        if e["type"] == "extra_forbidden" and _looks_secret(loc[-1]):
            # A password typed into cell.toml would end up in backups and version control.
            problems.append(
                f"{path}{origin}: secrets are never read from the configuration file; "
                f"set '{loc[-1]}_env' (an environment variable name) or '{loc[-1]}_file' (a secrets file)"
            )
        elif e["type"] == "extra_forbidden":
            problems.append(f"{path}{origin}: unknown key")
        elif e["type"] == "missing":
            problems.append(f"{path}{origin}: required key is missing")
        elif (
            isinstance(e.get("input"), dict)
            or e["type"].startswith("value_error")
            or e["type"] == "assertion_error"
        ):
            problems.append(f"{path}{origin}: {msg}")
        elif _secret_bearing(loc):
            problems.append(f"{path}{origin}: {msg} (the value given is not shown)")
        else:
            problems.append(f"{path}{origin} = {_format_value(e.get('input'))}: {msg}")
    return problems


def _secret_bearing(loc: list[str]) -> bool:
    """A key whose value may be (or name) a secret: ``*_env``, ``*_file``, ``sim.rws_users``."""
    return any(p.endswith(("_env", "_file")) or p == "rws_users" or _looks_secret(p) for p in loc)


def _env_sections() -> set[str]:
    return {
        k[len(ENV_PREFIX) :].split(ENV_DELIMITER)[0].lower()
        for k in os.environ
        if k.startswith(ENV_PREFIX) and ENV_DELIMITER in k
    }


def parse_config(data: dict[str, Any], source: str = "<config>") -> CellConfig:
    """Validate already-parsed TOML data (plus environment overrides)."""
    try:
        return CellConfig(**data)
    except ValidationError as err:
        raise ConfigError(source, _problems_from(err, _env_sections())) from None


def load_config(path: str | Path = DEFAULT_CONFIG_PATH) -> CellConfig:
    """Read and validate a `cell.toml`; raises :class:`ConfigError` with readable problems."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(str(path), ["no such file"]) from None
    except IsADirectoryError:
        raise ConfigError(str(path), ["is a directory, expected a TOML file"]) from None
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror}"]) from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), [f"not UTF-8 text (byte {exc.start})"]) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), [f"TOML syntax error: {exc}"]) from None
    except RecursionError:
        raise ConfigError(str(path), ["TOML nested too deeply"]) from None
    except ValueError as exc:  # a value tomllib cannot convert, e.g. an integer beyond 4300 digits
        raise ConfigError(str(path), [f"TOML value cannot be read: {str(exc)[:120]}"]) from None
    if not data:  # an empty file would run a cell on every default: name what is missing
        raise ConfigError(
            str(path),
            ["the file is empty: required section [cell] (the cell's id, data_dir, designs_dir) is missing"],
        )
    return parse_config(_sim_plate_files_resolved(data, path.parent), str(path))


def _sim_plate_files_resolved(data: dict[str, Any], folder: Path) -> dict[str, Any]:
    """``[sim.plate] mesh_file`` / ``design_file`` given relative: against the cell.toml's folder."""
    plate = data.get("sim", {}).get("plate") if isinstance(data.get("sim"), dict) else None
    if not isinstance(plate, dict):
        return data
    for key in ("mesh_file", "design_file"):
        if isinstance(plate.get(key), str) and not Path(plate[key]).is_absolute():
            plate[key] = str(folder / plate[key])
    return data


def check_secret_file_mode(file: str | Path, *, what: str) -> None:
    """Refuse a secrets file that its group or the world may read or write (as ssh does for keys).

    Raises ConfigError naming the file, its mode and the fix; a missing file passes (the read that
    follows reports it).
    """
    try:
        mode = os.stat(file).st_mode
    except OSError:
        return
    if mode & 0o077:
        raise ConfigError(
            str(file),
            [f"{what}: secrets file has mode {mode & 0o777:03o}, readable beyond its owner; chmod 600 it"],
        )


def secret_files(cfg: CellConfig) -> list[tuple[str, Path]]:
    """The secrets files ``cfg`` names: ``(what, path)``."""
    access = cfg.zenoh.access
    named = [
        ("robot.rws_password_file", cfg.robot.rws_password_file),
        ("zenoh.access.password_file", access.password_file),
        ("zenoh.access.dictionary_file", access.dictionary_file),
        ("zenoh.access.tls_key_file", access.tls_key_file),
        ("opcua.key_file", cfg.opcua.key_file),
    ]
    return [(what, Path(path)) for what, path in named if path is not None]


def secret_file_problems(cfg: CellConfig) -> list[str]:
    """What :func:`check_secret_file_mode` would refuse when the cell runs, found now: one line per
    secrets file its group or others may read or write (``cellctl config check``)."""
    problems = []
    for what, path in secret_files(cfg):
        try:
            check_secret_file_mode(path, what=what)
        except ConfigError as err:
            problems += [f"{err.source}: {p}" for p in err.problems]
    return problems


def resolve_secret(env_name: str, file: Path | None, *, what: str) -> SecretStr:
    """A secret from its secrets file (first) or environment variable; never from cell.toml.

    Raises ConfigError naming where the secret was looked for (never its value).
    """
    if file is not None:
        check_secret_file_mode(file, what=what)
        try:
            text = Path(file).read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise ConfigError(str(file), [f"{what}: cannot read secrets file: {exc.strerror}"]) from None
        if not text:
            raise ConfigError(str(file), [f"{what}: secrets file is empty"])
        return SecretStr(text)
    value = os.environ.get(env_name)
    if not value:
        raise ConfigError("environment", [f"{what}: environment variable {env_name} is not set"])
    return SecretStr(value)
