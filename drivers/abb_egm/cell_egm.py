"""The CellEgm RAPID program (drivers/abb_egm/rapid/CellEgm.mod) driven through RWS.

Application code on top of the RWS client: :class:`CellEgmProgram` checks the controller's mode,
switches the motors on, writes the EGM arguments (:class:`EgmProgramSettings`) into the module's
variables and starts and ends the program's EGM session; the caller streams EGM in between. The
module's variable names and status values are shared with the simulator (:mod:`drivers.abb_egm.rapid_values`),
the controller's state strings with the client (:mod:`drivers.abb_egm.rws_protocol`).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import structlog

from drivers.abb_egm import rapid_values as _prog
from drivers.abb_egm import rws_protocol as rw
from drivers.abb_egm.rws_client import RwsClient, RwsError

__all__ = ["CellEgmProgram", "EgmProgramError", "EgmProgramSettings"]

log = structlog.get_logger(__name__)


class EgmProgramError(RwsError):
    """The CellEgm program did not start or ended with an error; ``egm_status`` is its status value."""

    def __init__(self, message: str, *, egm_status: float | None = None) -> None:
        super().__init__(message)
        self.egm_status = egm_status


@dataclass(frozen=True)
class EgmProgramSettings:
    """The EGM arguments the daemon writes into CellEgm.mod before each start (units in the names)."""

    comm_timeout_s: float = 1.0
    pos_corr_gain: float = 1.0
    max_speed_deviation_deg_s: float = 1000.0
    max_pos_deviation_deg: float = 1000.0
    cond_time_s: float = 1_000_000.0
    ramp_in_time_s: float = 0.05
    lp_filter_hz: float = 20.0
    sample_rate_ms: float = 4.0
    task: str = _prog.RAPID_TASK
    module: str = _prog.RAPID_MODULE
    start_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        if self.comm_timeout_s <= 0:
            raise ValueError(f"comm_timeout_s must be > 0, got {self.comm_timeout_s}")
        if not 0.0 <= self.pos_corr_gain <= 1.0:
            raise ValueError(f"pos_corr_gain must be within [0, 1], got {self.pos_corr_gain}")
        if self.sample_rate_ms <= 0 or self.sample_rate_ms % 4:
            raise ValueError(f"sample_rate_ms must be a positive multiple of 4, got {self.sample_rate_ms}")

    def as_rapid(self) -> dict[str, float]:
        """RAPID variable name -> value."""
        return {
            _prog.VAR_COMM_TIMEOUT: self.comm_timeout_s,
            _prog.VAR_POS_CORR_GAIN: self.pos_corr_gain,
            _prog.VAR_MAX_SPEED_DEV: self.max_speed_deviation_deg_s,
            _prog.VAR_MAX_POS_DEV: self.max_pos_deviation_deg,
            _prog.VAR_COND_TIME: self.cond_time_s,
            _prog.VAR_RAMP_IN: self.ramp_in_time_s,
            _prog.VAR_LP_FILTER: self.lp_filter_hz,
            _prog.VAR_SAMPLE_RATE: self.sample_rate_ms,
        }


class CellEgmProgram:
    """Start and end EGM sessions of the CellEgm RAPID program through RWS.

    ``start()``: AUTO check, motors on, stop + PP to main, write the settings and ``egm_end := FALSE``,
    start RAPID (cycle once), wait for ``egm_status = 1``. ``end()``: ``egm_end := TRUE``, wait for
    RAPID to stop, return ``egm_status`` (2 on a clean end). The caller streams EGM in between.
    """

    def __init__(self, rws: RwsClient, settings: EgmProgramSettings | None = None) -> None:
        self.rws = rws
        self.settings = settings or EgmProgramSettings()

    async def status(self) -> float:
        """``egm_status``: 0 idle, 1 running, 2 ended on request, -41822 comm timeout, -1 other error."""
        s = self.settings
        return await self.rws.get_rapid_num(s.task, _prog.VAR_STATUS, s.module)

    async def start(self) -> None:
        """Bring the program into EGMRunJoint; raises ``EgmProgramError`` / ``RwsError`` on refusal."""
        s = self.settings
        opmode = await self.rws.get_opmode()
        if opmode != rw.AUTO:
            raise EgmProgramError(f"the controller is in {opmode}; EGM from the daemon needs AUTO")
        if await self.rws.get_ctrl_state() != rw.MOTORON:
            await self.rws.motors_on()
        if (await self.rws.get_execution_state()).ctrlexecstate == rw.RUNNING:
            await self.rws.stop_rapid()
        await self.rws.reset_pp()
        for name, value in s.as_rapid().items():
            await self.rws.set_rapid_num(s.task, name, value, s.module)
        await self.rws.set_rapid_bool(s.task, _prog.VAR_END, False, s.module)
        await self.rws.start_rapid(cycle="once")
        loop = asyncio.get_running_loop()
        deadline = loop.time() + s.start_timeout_s
        while True:
            status = await self.status()
            if status == _prog.STATUS_RUNNING:
                log.info("egm_program_started", task=s.task)
                return
            if status < 0:
                raise EgmProgramError(f"CellEgm ended at start with egm_status {status:g}", egm_status=status)
            if loop.time() > deadline:
                raise EgmProgramError(
                    f"CellEgm did not reach EGMRunJoint within {s.start_timeout_s} s (egm_status {status:g})",
                    egm_status=status,
                )
            await asyncio.sleep(0.02)

    async def end(self, timeout_s: float = 5.0) -> float:
        """End the session (hold position) and wait for the program to stop; returns ``egm_status``."""
        s = self.settings
        await self.rws.set_rapid_bool(s.task, _prog.VAR_END, True, s.module)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while (await self.rws.get_execution_state()).ctrlexecstate == rw.RUNNING:
            if loop.time() > deadline:
                raise EgmProgramError(f"CellEgm still running {timeout_s} s after egm_end := TRUE")
            await asyncio.sleep(0.02)
        status = await self.status()
        log.info("egm_program_ended", egm_status=status)
        return status
