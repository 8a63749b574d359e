"""Shared state of the simulated ABB controller (no I/O).

The RWS server simulator (``rws_server.py``) and the EGM simulator (``egm.py``) both act on one
``ControllerModel``: the RWS side turns motors on, starts the RAPID program, writes RAPID variables;
the EGM side asks ``egm_wanted`` every cycle and reports the end of a session. The model is used from
one asyncio loop and is not thread-safe (no locks: every method is short and never awaits).

What the EGM simulator needs from here (the contract with ``egm.py``):

- ``egm_wanted`` -> bool: True while the RAPID program would sit in ``EGMRunJoint`` (motors on,
  program running, program in its EGM phase, end variable ``egm_end`` false). Poll it every cycle.
- ``egm_params`` -> ``EgmRunParams``: the arguments the RAPID module passes to EGMSetupUC /
  EGMActJoint / EGMRunJoint, read from the RAPID variables when the program entered its EGM phase
  (communication timeout, position-correction gain, speed / position deviation limits, ...).
- ``egm_session_ended(reason, event_code)``: call it when the session ends on the EGM side
  (communication timeout -> 41822, a guidance error such as a joint-limit or speed-deviation
  violation -> its event code). The model logs the event, runs the module's error handler
  (``egm_status`` := -41822 for the timeout, -1 otherwise) and ends the program (RAPID stopped, PP
  back at main), as the RAPID module in ``drivers/abb_egm/rapid/CellEgm.mod`` does. While the
  program is merely stopped or the motors are off, ``egm_wanted`` is False and the session is
  suspended (MCI stopped), not ended: a restart continues it.
- ``set_position_source(fn)``: ``fn()`` returns ``(q_deg (6,), pos_mm (3,), quat_wxyz (4,))`` of the
  flange in the base frame; the RWS position endpoints read through it.
- ``set_external_axes_source(fn)``: ``fn()`` returns the six external axes of the motion group
  (``eax_a..eax_f``: mm for a linear track, 9E9 where unused); all unused until one is set.
- ``subscribe(cb)``: ``cb(kind, data)`` on every change; kinds are ``"ctrlstate"``, ``"opmode"``,
  ``"execution"``, ``"rapid-data"``, ``"signal"``, ``"elog"``, ``"egm"`` (``data["wanted"]``).
- ``motors_off()`` / ``emergency_stop()`` / ``guard_stop()`` are the fault knobs' entry points.

RAPID values are held as RAPID literal strings, the way RWS carries them; their codec, the names of
the RAPID module's variables and the return codes live in :mod:`drivers.abb_egm.rapid_values`, shared
with the RWS client, so the two cannot drift apart.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import structlog

from drivers.abb_egm import rws_protocol as rw
from drivers.abb_egm.rapid_values import (
    EXTAX_UNUSED,
    RAPID_MODULE,
    RAPID_TASK,
    RC_BAD_VALUE,
    RC_IO_ACCESS_DENIED,
    RC_NOT_FOUND,
    RC_READ_ONLY,
    RC_STATE_REFUSED,
    SIGNAL_END,
    STATUS_EGM_ERROR,
    STATUS_ENDED,
    STATUS_RUNNING,
    VAR_COMM_TIMEOUT,
    VAR_COND_TIME,
    VAR_END,
    VAR_LP_FILTER,
    VAR_MAX_POS_DEV,
    VAR_MAX_SPEED_DEV,
    VAR_POS_CORR_GAIN,
    VAR_RAMP_IN,
    VAR_SAMPLE_RATE,
    VAR_STATUS,
    ControllerError,
    ElogEntry,
    JointTarget,
    RapidValueError,
    format_bool,
    format_jointtarget,
    format_num,
    format_string,
    parse_bool,
    parse_jointtarget,
    parse_num,
    parse_string,
    validate_literal,
)
from drivers.abb_egm.rws_protocol import OPMODES, CtrlState, OpMode, RapidState

log = structlog.get_logger(__name__)

Listener = Callable[[str, dict], None]
PositionSource = Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]
ExternalAxesSource = Callable[[], np.ndarray]


# Event log codes. 41822 is documented (reference §2.5); 10010..10013 are the controller's
# motors-off / motors-on / guard-stop / emergency-stop state messages as commonly seen in IRC5
# event logs (from memory: UNVERIFIED, used for display only).
EVENT_EGM_COMM_TIMEOUT = 41822
EVENT_MOTORS_OFF = 10010
EVENT_MOTORS_ON = 10011
EVENT_GUARD_STOP = 10012
EVENT_EMERGENCY_STOP = 10013


class StateRefused(ControllerError):
    """The request is not allowed in the current controller / RAPID state (e.g. motors on during e-stop)."""

    http_status = 400


class SymbolNotFound(ControllerError):
    """No RAPID variable or IO signal of that name."""

    http_status = 404


class SignalNotFound(SymbolNotFound):
    """No IO signal of that name (RWS answers it with its own return code, unlike a RAPID symbol)."""


class AccessDenied(ControllerError):
    """Writing a constant or a signal whose access level forbids it."""

    http_status = 403


# --------------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------------


@dataclass
class RapidVar:
    """One RAPID data symbol: its type, storage class and current value as a literal."""

    task: str
    module: str
    name: str
    rapid_type: str
    value: str
    storage: Literal["PERS", "VAR", "CONST"] = "PERS"


@dataclass
class IoSignal:
    """One IO signal. ``lvalue`` is 0/1 for digital, a number for analog / group signals."""

    name: str
    signal_type: Literal["DI", "DO", "AI", "AO", "GI", "GO"]
    lvalue: float = 0.0
    network: str = "Local"
    device: str = "DRV_1"
    writable: bool = True


@dataclass(frozen=True)
class EgmRunParams:
    """What the RAPID module hands to EGMSetupUC / EGMActJoint / EGMRunJoint (units in the names)."""

    comm_timeout_s: float
    pos_corr_gain: float
    max_speed_deviation_deg_s: float
    max_pos_deviation_deg: float
    cond_time_s: float
    ramp_in_time_s: float
    lp_filter_hz: float
    sample_rate_ms: float

    @property
    def max_speed_deviation_dps(self) -> float:
        """Alias of ``max_speed_deviation_deg_s`` (the name of the first version of this contract)."""
        return self.max_speed_deviation_deg_s


_SEVERITY = {"info": 1, "warning": 2, "error": 3}
_ZERO_POSE_POS_MM = np.array([1580.0, 0.0, 1765.0])
# tool0 at all-zero joints: rotated +90 deg about base y (URDF rpy (0, pi/2, 0)).
_ZERO_POSE_QUAT_WXYZ = np.array([math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0])


def _home_pose() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(6), _ZERO_POSE_POS_MM.copy(), _ZERO_POSE_QUAT_WXYZ.copy()


class ControllerModel:
    """State of one simulated IRC5 / OmniCore controller with the CellEgm RAPID program loaded.

    State-changing methods raise ``StateRefused`` where the real controller refuses (motors on during
    an emergency stop, starting RAPID with the motors off, ...), ``SymbolNotFound`` for unknown
    variables / signals, ``RapidValueError`` for malformed literals and ``AccessDenied`` for writes to
    constants or protected signals. Every change is reported to the subscribers.

    ``end_var`` names the bool RAPID variable that ends the EGM session (default ``egm_end``).
    """

    def __init__(
        self,
        *,
        opmode: OpMode = rw.AUTO,
        ctrl_state: CtrlState = rw.MOTOROFF,
        end_var: str = VAR_END,
        task: str = RAPID_TASK,
        module: str = RAPID_MODULE,
        elog_capacity: int = 1000,
    ) -> None:
        self._ctrl_state: CtrlState = ctrl_state
        self._opmode: OpMode = opmode
        self._rapid_state: RapidState = rw.STOPPED
        self.speed_ratio_pct = 100
        self.task = task
        self.module = module
        self.end_var = end_var
        # "main": PP at main; "egm": program inside EGMRunJoint (or stopped there).
        self._phase: Literal["main", "egm"] = "main"
        self._egm_params: EgmRunParams | None = None
        self._vars: dict[tuple[str, str, str], RapidVar] = {}
        self._signals: dict[str, IoSignal] = {}
        self._events: deque[ElogEntry] = deque(maxlen=elog_capacity)
        self._event_seq = 0
        self._listeners: list[Listener] = []
        # RAPID tasks of the system: name -> active (only the motion task runs the CellEgm program)
        self.tasks_active: dict[str, bool] = {task: True}
        self._position_source: PositionSource = _home_pose
        self._external_axes_source: ExternalAxesSource = lambda: np.full(6, EXTAX_UNUSED)
        self._egm_wanted_last = False
        self._define_program_data()
        self._define_signals()

    # ---- program data -------------------------------------------------------------------------

    def _define_program_data(self) -> None:
        # Defaults equal the PERS initial values in CellEgm.mod.
        t, m = self.task, self.module
        for name, rtype, value in (
            (self.end_var, "bool", "FALSE"),
            (VAR_STATUS, "num", "0"),
            (VAR_COMM_TIMEOUT, "num", "1"),
            (VAR_POS_CORR_GAIN, "num", "1"),
            (VAR_MAX_SPEED_DEV, "num", "1000"),
            (VAR_MAX_POS_DEV, "num", "1000"),
            (VAR_COND_TIME, "num", "1000000"),
            (VAR_RAMP_IN, "num", "0.05"),
            (VAR_LP_FILTER, "num", "20"),
            (VAR_SAMPLE_RATE, "num", "4"),
        ):
            self.define_var(t, m, name, rtype, value)

    def _define_signals(self) -> None:
        # A DO the daemon may use instead of the variable, and a read-only DI (e.g. a bed sensor).
        self.define_signal(IoSignal(SIGNAL_END, "DO"))
        self.define_signal(IoSignal("DI_PLATE_PRESENT", "DI", writable=False))

    def define_var(
        self, task: str, module: str, name: str, rapid_type: str, value: str, storage: str = "PERS"
    ) -> None:
        """Declare a RAPID data symbol (as if the module declared it)."""
        literal = validate_literal(rapid_type, value)
        self._vars[(task, module, name)] = RapidVar(task, module, name, rapid_type, literal, storage)  # type: ignore[arg-type]

    def define_signal(self, signal: IoSignal) -> None:
        """Declare an IO signal (as the EIO configuration would)."""
        self._signals[signal.name] = signal

    # ---- subscription -------------------------------------------------------------------------

    def subscribe(self, callback: Listener) -> Callable[[], None]:
        """Register ``callback(kind, data)`` for every change; returns a function that unsubscribes."""
        self._listeners.append(callback)

        def unsubscribe() -> None:
            if callback in self._listeners:
                self._listeners.remove(callback)

        return unsubscribe

    def _notify(self, kind: str, data: dict) -> None:
        for cb in list(self._listeners):
            try:
                cb(kind, data)
            except Exception:  # a broken listener must not break the controller
                log.exception("listener_failed", kind=kind)
        wanted = self.egm_wanted
        if wanted != self._egm_wanted_last:
            self._egm_wanted_last = wanted
            for cb in list(self._listeners):
                try:
                    cb("egm", {"wanted": wanted})
                except Exception:
                    log.exception("listener_failed", kind="egm")

    # ---- panel --------------------------------------------------------------------------------

    @property
    def ctrl_state(self) -> CtrlState:
        """Controller state as RWS reports it (``motoron``, ``motoroff``, ``guardstop``, ...)."""
        return self._ctrl_state

    @property
    def opmode(self) -> OpMode:
        """Operating mode: ``AUTO``, ``MANR`` (manual reduced speed) or ``MANF`` (manual full speed)."""
        return self._opmode

    @property
    def rapid_state(self) -> RapidState:
        """RAPID execution state: ``running`` or ``stopped``."""
        return self._rapid_state

    def _set_ctrl_state(self, state: CtrlState) -> None:
        if state != self._ctrl_state:
            self._ctrl_state = state
            self._notify("ctrlstate", {"ctrlstate": state})

    def set_opmode(self, mode: OpMode) -> None:
        """Turn the mode key (cabinet, not RWS). Stops RAPID and the motors, as the real controller does."""
        if mode not in OPMODES:
            raise RapidValueError(f"unknown opmode {mode!r}", code=RC_BAD_VALUE)
        if mode == self._opmode:
            return
        self._halt_program("opmode change")
        if self._ctrl_state == rw.MOTORON:
            self._set_ctrl_state(rw.MOTOROFF)
        self._opmode = mode
        self._notify("opmode", {"opmode": mode})

    def motors_on(self) -> None:
        """Switch the motors on (RWS ``ctrl-state=motoron``); only from motors off / e-stop reset, in AUTO."""
        if self._ctrl_state == rw.MOTORON:
            return
        if self._ctrl_state in (rw.EMERGENCYSTOP, rw.GUARDSTOP, rw.SYSFAIL, rw.INIT):
            raise StateRefused(
                f"motors on refused: controller is in {self._ctrl_state}", code=RC_STATE_REFUSED
            )
        if self._opmode != rw.AUTO:
            # In manual mode the enabling device on the pendant switches the motors on, not RWS.
            raise StateRefused(f"motors on refused: operating mode is {self._opmode}", code=RC_STATE_REFUSED)
        self._set_ctrl_state(rw.MOTORON)
        self.log_event(EVENT_MOTORS_ON, "Motors ON state", "Motors on requested through RWS.", "info")

    def motors_off(self) -> None:
        """Switch the motors off; a running program stops (as the real controller does in AUTO)."""
        if self._ctrl_state in (rw.EMERGENCYSTOP, rw.GUARDSTOP, rw.SYSFAIL):
            raise StateRefused(
                f"motors off refused: controller is in {self._ctrl_state}", code=RC_STATE_REFUSED
            )
        if self._ctrl_state == rw.MOTOROFF:
            return
        self._halt_program("motors off")
        self._set_ctrl_state(rw.MOTOROFF)
        self.log_event(EVENT_MOTORS_OFF, "Motors OFF state", "Motors switched off.", "info")

    def emergency_stop(self) -> None:
        """Press the emergency stop: motors off, RAPID stopped, EGM ends."""
        if self._ctrl_state == rw.EMERGENCYSTOP:
            return
        self._halt_program("emergency stop")
        self._set_ctrl_state(rw.EMERGENCYSTOP)
        self.log_event(
            EVENT_EMERGENCY_STOP, "Emergency stop state", "The emergency stop circuit opened.", "error"
        )

    def reset_emergency_stop(self) -> None:
        """Release and reset the emergency stop: the controller goes to ``emergencystopreset``."""
        if self._ctrl_state != rw.EMERGENCYSTOP:
            raise StateRefused(
                f"no emergency stop to reset: controller is in {self._ctrl_state}", code=RC_STATE_REFUSED
            )
        self._set_ctrl_state(rw.EMERGENCYSTOPRESET)

    def guard_stop(self) -> None:
        """Open the safety guard (auto stop): motors off, RAPID stopped."""
        if self._ctrl_state in (rw.EMERGENCYSTOP, rw.GUARDSTOP):
            return
        self._halt_program("guard stop")
        self._set_ctrl_state(rw.GUARDSTOP)
        self.log_event(
            EVENT_GUARD_STOP, "Safety guard stop state", "The safety guard circuit opened.", "warning"
        )

    def reset_guard_stop(self) -> None:
        """Close the safety guard again: the controller goes to ``motoroff``."""
        if self._ctrl_state != rw.GUARDSTOP:
            raise StateRefused(
                f"no guard stop to reset: controller is in {self._ctrl_state}", code=RC_STATE_REFUSED
            )
        self._set_ctrl_state(rw.MOTOROFF)

    # ---- RAPID execution ----------------------------------------------------------------------

    def start_rapid(self) -> None:
        """Start (or continue) the program. From PP at main this enters the EGM phase of CellEgm.mod."""
        if self._rapid_state == rw.RUNNING:
            return
        if self._ctrl_state != rw.MOTORON:
            raise StateRefused(
                f"start refused: motors are not on (controller is {self._ctrl_state})", code=RC_STATE_REFUSED
            )
        if self._opmode != rw.AUTO:
            raise StateRefused(
                f"start refused: operating mode {self._opmode} needs the pendant (RMMP)",
                code=RC_STATE_REFUSED,
            )
        if not self.tasks_active.get(self.task, False):
            raise StateRefused(f"start refused: task {self.task} is not active", code=RC_STATE_REFUSED)
        self._rapid_state = rw.RUNNING
        if self._phase == "main":
            self._enter_egm_phase()
        self._notify("execution", {"ctrlexecstate": rw.RUNNING})
        # A session that was told to end while the program was stopped ends as soon as it runs.
        if self._phase == "egm" and self._var_bool(self.end_var):
            self._finish_program(STATUS_ENDED, "end variable set")

    def stop_rapid(self) -> None:
        """Stop the program. Inside EGMRunJoint the EGM state goes back to CONNECTED; a start resumes it."""
        if self._rapid_state == rw.STOPPED:
            return
        self._rapid_state = rw.STOPPED
        self._notify("execution", {"ctrlexecstate": rw.STOPPED})

    def reset_pp(self) -> None:
        """Set the program pointer to main (only with the program stopped); the EGM identity is released."""
        if self._rapid_state == rw.RUNNING:
            raise StateRefused("reset PP refused: the program is running", code=RC_STATE_REFUSED)
        self._phase = "main"
        self._egm_params = None
        self._notify("execution", {"ctrlexecstate": rw.STOPPED, "pp": "main"})

    def _enter_egm_phase(self) -> None:
        # main(): egm_end := FALSE; read the settings; EGMGetId; EGMSetupUC; EGMActJoint; EGMRunJoint.
        self._write_var_internal(self.end_var, "FALSE")
        self._egm_params = EgmRunParams(
            comm_timeout_s=self._var_num(VAR_COMM_TIMEOUT),
            pos_corr_gain=self._var_num(VAR_POS_CORR_GAIN),
            max_speed_deviation_deg_s=self._var_num(VAR_MAX_SPEED_DEV),
            max_pos_deviation_deg=self._var_num(VAR_MAX_POS_DEV),
            cond_time_s=self._var_num(VAR_COND_TIME),
            ramp_in_time_s=self._var_num(VAR_RAMP_IN),
            lp_filter_hz=self._var_num(VAR_LP_FILTER),
            sample_rate_ms=self._var_num(VAR_SAMPLE_RATE),
        )
        self._phase = "egm"
        self._write_var_internal(VAR_STATUS, str(STATUS_RUNNING))
        log.info("rapid_egm_phase_entered", params=self._egm_params)

    def _finish_program(self, status: int, reason: str) -> None:
        # EGMStop / EGMReset, egm_status := status, main ends (run mode "once"): program stops, PP at main.
        self._phase = "main"
        self._egm_params = None
        self._write_var_internal(VAR_STATUS, format_num(status))
        # CleanUp in CellEgm.mod clears the end signal.
        end_sig = self._signals.get(SIGNAL_END)
        if end_sig is not None and end_sig.lvalue != 0:
            end_sig.lvalue = 0.0
            self._notify("signal", {"name": SIGNAL_END, "lvalue": 0.0})
        was_running = self._rapid_state == rw.RUNNING
        self._rapid_state = rw.STOPPED
        log.info("rapid_program_finished", status=status, reason=reason)
        if was_running:
            self._notify("execution", {"ctrlexecstate": rw.STOPPED, "pp": "main"})

    def _halt_program(self, reason: str) -> None:
        if self._rapid_state == rw.RUNNING:
            log.info("rapid_halted", reason=reason)
            self.stop_rapid()

    def set_task_active(self, task: str, active: bool) -> None:
        """Activate / deactivate a task (RWS ``activate`` / ``deactivate``); only with RAPID stopped."""
        if task not in self.tasks_active:
            raise SymbolNotFound(f"task not found: {task}", code=RC_NOT_FOUND)
        if self._rapid_state == rw.RUNNING:
            raise StateRefused("task (de)activation refused: the program is running", code=RC_STATE_REFUSED)
        self.tasks_active[task] = active

    def modules(self, task: str) -> list[tuple[str, str]]:
        """``(name, type)`` of the modules loaded in ``task``: the system modules and the program's."""
        if task not in self.tasks_active:
            raise SymbolNotFound(f"task not found: {task}", code=RC_NOT_FOUND)
        prog = sorted({m for (t, m, _n) in self._vars if t == task})
        return [("BASE", "SysMod"), ("user", "SysMod"), *((m, "ProgMod") for m in prog)]

    # ---- EGM program model --------------------------------------------------------------------

    @property
    def egm_wanted(self) -> bool:
        """True while the program sits in EGMRunJoint: motors on, running, EGM phase, end variable false."""
        return (
            self._ctrl_state == rw.MOTORON
            and self._rapid_state == rw.RUNNING
            and self._phase == "egm"
            and not self._var_bool(self.end_var)
        )

    @property
    def egm_params(self) -> EgmRunParams | None:
        """The EGM arguments of the current session (None outside the EGM phase)."""
        return self._egm_params

    def egm_session_ended(self, reason: str, event_code: int | None) -> None:
        """The EGM side ended the session (41822 comm timeout, or a guidance error with its event code).

        Logs the event, then does what CellEgm.mod's error handler does: ``egm_status := -41822`` for a
        communication timeout, ``-1`` for any other EGM error; EGMReset; the program stops with PP at
        main. (While ``egm_wanted`` is False because the program was stopped or the motors went off,
        the session is only suspended, as on the controller: do not call this then.)
        """
        if event_code is not None:
            title = "No data from the UdpUc device" if event_code == EVENT_EGM_COMM_TIMEOUT else "EGM error"
            self.log_event(event_code, title, reason, "error")
        if self._phase != "egm":
            return
        status = -EVENT_EGM_COMM_TIMEOUT if event_code == EVENT_EGM_COMM_TIMEOUT else STATUS_EGM_ERROR
        self._finish_program(status, reason)

    # ---- RAPID variables ----------------------------------------------------------------------

    def _find(self, task: str, module: str | None, name: str) -> RapidVar:
        if module:
            var = self._vars.get((task, module, name))
        else:
            var = next((v for (t, _m, n), v in self._vars.items() if t == task and n == name), None)
        if var is None:
            where = f"{task}/{module}/{name}" if module else f"{task}/{name}"
            raise SymbolNotFound(f"RAPID symbol not found: {where}", code=RC_NOT_FOUND)
        return var

    def var_info(self, task: str, module: str | None, name: str) -> RapidVar:
        """Return the symbol record (type, storage, value literal)."""
        return self._find(task, module, name)

    def get_var(self, task: str, module: str | None, name: str) -> str:
        """Read a RAPID variable as its literal string; ``module`` None searches all modules of the task."""
        return self._find(task, module, name).value

    def set_var(self, task: str, module: str | None, name: str, value: str) -> None:
        """Write a RAPID variable from a literal string (validated against the variable's type)."""
        var = self._find(task, module, name)
        if var.storage == "CONST":
            raise AccessDenied(f"RAPID symbol {name} is a CONST", code=RC_READ_ONLY)
        var.value = validate_literal(var.rapid_type, value)
        self._notify("rapid-data", {"task": var.task, "module": var.module, "name": name, "value": var.value})
        if name == self.end_var and var.task == self.task:
            self._on_end_var_written()

    def _on_end_var_written(self) -> None:
        # The module's IPers trap: egm_end TRUE -> EGMStop. Only takes effect while the program runs.
        if self._phase == "egm" and self._rapid_state == rw.RUNNING and self._var_bool(self.end_var):
            self._finish_program(STATUS_ENDED, "end variable set")

    def _write_var_internal(self, name: str, literal: str) -> None:
        var = self._find(self.task, self.module, name)
        var.value = validate_literal(var.rapid_type, literal)
        self._notify("rapid-data", {"task": var.task, "module": var.module, "name": name, "value": var.value})

    def _var_num(self, name: str) -> float:
        return parse_num(self._find(self.task, self.module, name).value)

    def _var_bool(self, name: str) -> bool:
        return parse_bool(self._find(self.task, self.module, name).value)

    def get_num(self, task: str, module: str | None, name: str) -> float:
        """Typed read of a ``num``."""
        return parse_num(self.get_var(task, module, name))

    def set_num(self, task: str, module: str | None, name: str, value: float) -> None:
        """Typed write of a ``num``."""
        self.set_var(task, module, name, format_num(value))

    def get_bool(self, task: str, module: str | None, name: str) -> bool:
        """Typed read of a ``bool``."""
        return parse_bool(self.get_var(task, module, name))

    def set_bool(self, task: str, module: str | None, name: str, value: bool) -> None:
        """Typed write of a ``bool``."""
        self.set_var(task, module, name, format_bool(value))

    def get_string(self, task: str, module: str | None, name: str) -> str:
        """Typed read of a ``string``."""
        return parse_string(self.get_var(task, module, name))

    def set_string(self, task: str, module: str | None, name: str, value: str) -> None:
        """Typed write of a ``string``."""
        self.set_var(task, module, name, format_string(value))

    def get_jointtarget(self, task: str, module: str | None, name: str) -> JointTarget:
        """Typed read of a ``jointtarget``."""
        return parse_jointtarget(self.get_var(task, module, name))

    def set_jointtarget(
        self, task: str, module: str | None, name: str, value: JointTarget | np.ndarray
    ) -> None:
        """Typed write of a ``jointtarget`` (a JointTarget or a (6,) array of degrees)."""
        self.set_var(task, module, name, format_jointtarget(value))

    # ---- IO -----------------------------------------------------------------------------------

    def signal(self, name: str) -> IoSignal:
        """The signal record; ``SymbolNotFound`` if the signal does not exist."""
        sig = self._signals.get(name)
        if sig is None:
            raise SignalNotFound(f"IO signal not found: {name}", code=RC_NOT_FOUND)
        return sig

    def get_io(self, name: str) -> float:
        """Read a signal's value (0/1 for digital signals)."""
        return self.signal(name).lvalue

    def set_io(self, name: str, value: float, *, force: bool = False) -> None:
        """Write a signal. Inputs and protected signals refuse unless ``force`` (simulator wiring)."""
        sig = self.signal(name)
        if not force and (not sig.writable or sig.signal_type in ("DI", "AI", "GI")):
            raise AccessDenied(
                f"IO signal {name} may not be written (access level)", code=RC_IO_ACCESS_DENIED
            )
        if sig.signal_type in ("DI", "DO") and value not in (0, 1):
            raise RapidValueError(f"digital signal {name} takes 0 or 1, got {value!r}", code=RC_BAD_VALUE)
        sig.lvalue = float(value)
        self._notify("signal", {"name": name, "lvalue": sig.lvalue})
        # CellEgm.mod also ends the session on a rising DO_EGM_END (a signal for cells that prefer IO).
        if (
            name == SIGNAL_END
            and sig.lvalue == 1
            and self._phase == "egm"
            and self._rapid_state == rw.RUNNING
        ):
            self._finish_program(STATUS_ENDED, "end signal set")

    @property
    def signals(self) -> list[IoSignal]:
        """All signals."""
        return list(self._signals.values())

    # ---- event log ----------------------------------------------------------------------------

    def log_event(self, code: int, title: str, desc: str, severity: str = "info") -> ElogEntry:
        """Append an entry to event-log domain 0; ``severity`` is ``info`` / ``warning`` / ``error``."""
        if severity not in _SEVERITY:
            raise RapidValueError(f"unknown severity {severity!r}", code=RC_BAD_VALUE)
        self._event_seq += 1
        tstamp = time.strftime("%Y-%m-%d T %H:%M:%S", time.gmtime())
        ev = ElogEntry(self._event_seq, _SEVERITY[severity], int(code), title, desc, tstamp)
        self._events.append(ev)
        log.info("elog_event", code=code, title=title, severity=severity)
        self._notify("elog", {"seqnum": ev.seqnum, "code": ev.code, "msgtype": ev.msgtype, "title": title})
        return ev

    @property
    def events(self) -> list[ElogEntry]:
        """Event log, newest first (as RWS lists it)."""
        return list(reversed(self._events))

    def clear_events(self) -> None:
        """Clear the event log (RWS ``clear``)."""
        self._events.clear()

    # ---- position -----------------------------------------------------------------------------

    def set_position_source(self, fn: PositionSource) -> None:
        """``fn()`` -> ``(q_deg (6,), pos_mm (3,), quat_wxyz (4,))`` of the flange in the base frame."""
        self._position_source = fn

    def position(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current ``(q_deg (6,), pos_mm (3,), quat_wxyz (4,))``; the all-zero pose until a source is set."""
        q_deg, pos_mm, quat = self._position_source()
        return np.asarray(q_deg, dtype=float), np.asarray(pos_mm, dtype=float), np.asarray(quat, dtype=float)

    def set_external_axes_source(self, fn: ExternalAxesSource) -> None:
        """``fn()`` -> the six external axes ``eax_a..eax_f`` (a track in mm, 9E9 where unused)."""
        self._external_axes_source = fn

    def external_axes(self) -> np.ndarray:
        """Current external axes (6,) (``eax_a..eax_f``; 9E9 where unused); all unused until a source is set."""
        ext = np.asarray(self._external_axes_source(), dtype=float)
        if ext.shape != (6,):
            raise ValueError(f"the external axes source must give 6 values, got {ext.shape}")
        return ext
