"""The words of Robot Web Services that the client, the controller simulator and the daemon share:
resource paths, media types, the subscription's resources and the controller's state strings.

Like the EGM codec, this lives beside the client and outside ``sim/`` so that the simulator cannot
drift from the client (a path spelled one way in the client and another in the simulator would pass
every simulated test and fail on a controller). Only names and pure functions here: no I/O.

Paths are ABB's (RWS 1.0 for RobotWare 6, RWS 2.0 for RobotWare 7; docs/reference/abb-egm-rws.md);
where the two profiles differ, a function takes the profile. Path parts a caller supplies (task,
module, symbol, signal names) are percent-quoted by the functions that take them.
"""

from __future__ import annotations

from typing import Final, Literal
from urllib.parse import quote

__all__ = [
    "AUTO",
    "CTRL_STATES",
    "ELOG",
    "EMERGENCYSTOP",
    "EMERGENCYSTOPRESET",
    "EXECUTION_SUBSCRIPTION",
    "FORM",
    "FORM_V2",
    "GUARDSTOP",
    "HAL_JSON_V2",
    "INIT",
    "IOSYSTEM_SIGNALS",
    "JSON",
    "LOGOUT",
    "MANF",
    "MANR",
    "MASTERSHIP",
    "MECHUNITS",
    "MOTOROFF",
    "MOTORON",
    "OPMODES",
    "PANEL_CTRLSTATE",
    "PANEL_CTRL_STATE_V2",
    "PANEL_OPMODE",
    "PANEL_SPEEDRATIO",
    "POLL",
    "RAPID_EXECUTION",
    "RAPID_MODULES",
    "RAPID_STATES",
    "RAPID_SYMBOL_DATA",
    "RAPID_SYMBOL_V2",
    "RAPID_TASKS",
    "RUNNING",
    "SERVICES",
    "STOPPED",
    "SUBSCRIPTION",
    "SYSFAIL",
    "SYSTEM",
    "V2",
    "WS_PROTOCOL",
    "XHTML",
    "XHTML_V2",
    "CtrlState",
    "OpMode",
    "Profile",
    "RapidState",
    "ctrl_state_path",
    "elog_path",
    "execution_action_path",
    "mechunit_path",
    "signal_path",
    "signal_subscription",
    "symbol_path",
    "symbol_subscription",
    "task_path",
]

#: RWS 1.0 (IRC5, RobotWare 6) or RWS 2.0 (OmniCore, RobotWare 7)
Profile = Literal["rws1", "rws2"]

# ---- media types ------------------------------------------------------------------------------
#: the version parameter every RWS 2.0 media type carries
V2: Final = "v=2.0"
#: RWS 1.0 answers with ``?json=1``
JSON: Final = "application/json"
#: RWS 1.0 answers without ``json=1`` (and every subscription event)
XHTML: Final = "application/xhtml+xml"
HAL_JSON_V2: Final = "application/hal+json;v=2.0"
XHTML_V2: Final = "application/xhtml+xml;v=2.0"
#: the subscription websocket's subprotocol per profile
WS_PROTOCOL: Final = {"rws1": "robapi2_subscription", "rws2": "rws_subscription"}
#: the body of every mutating request
FORM: Final = "application/x-www-form-urlencoded"
FORM_V2: Final = "application/x-www-form-urlencoded;v=2.0"

# ---- resources ---------------------------------------------------------------------------------
#: the root of the controller's services: ``/rw/<service>/...``
SERVICES: Final = "/rw"
LOGOUT: Final = "/logout"
SUBSCRIPTION: Final = "/subscription"
#: the subscription's websocket: ``/poll/<n>``
POLL: Final = "/poll"
#: the controller state, RWS 1.0 (``?action=setctrlstate`` changes it)
PANEL_CTRLSTATE: Final = "/rw/panel/ctrlstate"
#: the controller state, RWS 2.0 (read and changed at the same path)
PANEL_CTRL_STATE_V2: Final = "/rw/panel/ctrl-state"
PANEL_OPMODE: Final = "/rw/panel/opmode"
PANEL_SPEEDRATIO: Final = "/rw/panel/speedratio"
RAPID_EXECUTION: Final = "/rw/rapid/execution"
RAPID_TASKS: Final = "/rw/rapid/tasks"
#: the modules of a task, RWS 1.0 (``?task=``); RWS 2.0: ``task_path(task) + "/modules"``
RAPID_MODULES: Final = "/rw/rapid/modules"
#: a RAPID symbol's value, RWS 1.0: ``/rw/rapid/symbol/data/RAPID/<task>[/<module>]/<name>``
RAPID_SYMBOL_DATA: Final = "/rw/rapid/symbol/data/RAPID"
#: a RAPID symbol's value, RWS 2.0: ``/rw/rapid/symbol/RAPID/<task>[/<module>]/<name>/data``
RAPID_SYMBOL_V2: Final = "/rw/rapid/symbol/RAPID"
IOSYSTEM_SIGNALS: Final = "/rw/iosystem/signals"
ELOG: Final = "/rw/elog"
MECHUNITS: Final = "/rw/motionsystem/mechunits"
MASTERSHIP: Final = "/rw/mastership"
SYSTEM: Final = "/rw/system"
#: the subscription resource of the RAPID execution state (RWS 1.0)
EXECUTION_SUBSCRIPTION: Final = RAPID_EXECUTION + ";ctrlexecstate"

# ---- the controller's state strings --------------------------------------------------------------
CtrlState = Literal[
    "init", "motoron", "motoroff", "guardstop", "emergencystop", "emergencystopreset", "sysfail"
]
INIT: Final = "init"
MOTORON: Final = "motoron"
MOTOROFF: Final = "motoroff"
GUARDSTOP: Final = "guardstop"
EMERGENCYSTOP: Final = "emergencystop"
#: the emergency stop released, the motors not yet on again
EMERGENCYSTOPRESET: Final = "emergencystopreset"
SYSFAIL: Final = "sysfail"
CTRL_STATES: tuple[CtrlState, ...] = (
    INIT,
    MOTORON,
    MOTOROFF,
    GUARDSTOP,
    EMERGENCYSTOP,
    EMERGENCYSTOPRESET,
    SYSFAIL,
)

OpMode = Literal["AUTO", "MANR", "MANF"]
AUTO: Final = "AUTO"
MANR: Final = "MANR"
MANF: Final = "MANF"
OPMODES: tuple[OpMode, ...] = (AUTO, MANR, MANF)

#: RAPID's execution state (``ctrlexecstate``)
RapidState = Literal["running", "stopped"]
RUNNING: Final = "running"
STOPPED: Final = "stopped"
RAPID_STATES: tuple[RapidState, ...] = (RUNNING, STOPPED)


def _quoted(parts: list[str]) -> str:
    return "/".join(quote(p, safe="") for p in parts)


def ctrl_state_path(profile: Profile) -> str:
    """The controller-state resource of ``profile``."""
    return PANEL_CTRLSTATE if profile == "rws1" else PANEL_CTRL_STATE_V2


def execution_action_path(action: str) -> str:
    """RWS 2.0's sub-resource of a RAPID execution action (``start``, ``stop``, ``resetpp``)."""
    return f"{RAPID_EXECUTION}/{action}"


def symbol_path(profile: Profile, task: str, name: str, module: str | None = None) -> str:
    """The resource of the RAPID symbol ``task[/module]/name``'s value, in ``profile``'s spelling."""
    sym = _quoted([task, module, name] if module else [task, name])
    return f"{RAPID_SYMBOL_DATA}/{sym}" if profile == "rws1" else f"{RAPID_SYMBOL_V2}/{sym}/data"


def symbol_subscription(task: str, name: str) -> str:
    """The subscription resource of a RAPID variable's value (RWS 1.0)."""
    return f"{RAPID_SYMBOL_DATA}/{task}/{name};value"


def signal_path(signal: str, network: str | None = None, device: str | None = None) -> str:
    """An IO signal's resource, ``[network/device/]signal``."""
    return f"{IOSYSTEM_SIGNALS}/{_quoted([p for p in (network, device, signal) if p])}"


def signal_subscription(signal: str) -> str:
    """The subscription resource of an IO signal's state (RWS 1.0)."""
    return f"{IOSYSTEM_SIGNALS}/{signal};state"


def elog_path(domain: int, seqnum: int | None = None) -> str:
    """An event-log domain, or one message of it."""
    return f"{ELOG}/{domain}" if seqnum is None else f"{ELOG}/{domain}/{seqnum}"


def task_path(task: str) -> str:
    """A RAPID task's resource."""
    return f"{RAPID_TASKS}/{quote(task, safe='')}"


def mechunit_path(mechunit: str, what: Literal["jointtarget", "robtarget"]) -> str:
    """A mechanical unit's ``jointtarget`` or ``robtarget``."""
    return f"{MECHUNITS}/{mechunit}/{what}"
