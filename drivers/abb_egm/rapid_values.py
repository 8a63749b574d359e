"""RAPID values and names the RWS client and the controller simulator share (no I/O).

RAPID values travel as RAPID literal strings, the way RWS carries them (``"1.5"``, ``"TRUE"``,
``"\\"text\\""``, ``"[[0,0,0,0,30,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]]"``). The literal codec
below is used by :mod:`drivers.abb_egm.rws_client` and by the simulator
(:mod:`drivers.abb_egm.sim.model`, :mod:`drivers.abb_egm.sim.rws_server`), so the two cannot drift
apart, as the EGM codec (:mod:`drivers.abb_egm.codec`) is shared by the endpoint and the EGM simulator.
Beside it: the names of the RAPID module ``rapid/CellEgm.mod`` and its variables, the values of its
status variable, and the controller return codes an error carries.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

# Names of the RAPID module and its variables. They must match drivers/abb_egm/rapid/CellEgm.mod.
RAPID_TASK = "T_ROB1"
RAPID_MODULE = "CellEgm"
VAR_END = "egm_end"
VAR_STATUS = "egm_status"
VAR_COMM_TIMEOUT = "egm_comm_timeout_s"
VAR_POS_CORR_GAIN = "egm_pos_corr_gain"
VAR_MAX_SPEED_DEV = "egm_max_speed_dev_dps"
VAR_MAX_POS_DEV = "egm_max_pos_dev_deg"
VAR_COND_TIME = "egm_cond_time_s"
VAR_RAMP_IN = "egm_ramp_in_s"
VAR_LP_FILTER = "egm_lp_filter_hz"
VAR_SAMPLE_RATE = "egm_sample_rate_ms"

# egm_status values written by the RAPID module (negative values are minus the event code).
STATUS_IDLE = 0
STATUS_RUNNING = 1
STATUS_ENDED = 2
STATUS_EGM_ERROR = -1
SIGNAL_END = "DO_EGM_END"

# The one controller return code the reference documents (IO write refused by access level). The
# other codes are the simulator's own, in a range the controller does not use, so nobody mistakes
# them for real ones.
RC_IO_ACCESS_DENIED = -1073445881
RC_STATE_REFUSED = -7001
RC_NOT_FOUND = -7002
RC_BAD_VALUE = -7003
RC_READ_ONLY = -7004


class ControllerError(Exception):
    """The controller refuses a request.

    Attributes: ``code`` (the controller's return code, negative), ``http_status`` (what RWS answers
    with), ``message``.
    """

    http_status = 400

    def __init__(self, message: str, *, code: int) -> None:
        super().__init__(message)
        self.message = message
        self.code = code


class RapidValueError(ControllerError, ValueError):
    """A RAPID literal does not parse as the variable's type."""

    http_status = 400


# --------------------------------------------------------------------------------------------------
# RAPID literal codec (shared by the RWS client and server)
# --------------------------------------------------------------------------------------------------

_NUM_RE = re.compile(r"^\s*[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?\s*$")
# RAPID uses 9E+09 for "axis not used" in the external axes of a jointtarget / robtarget. RWS prints
# it in more than one way: ``9E+09``, ``8.999999e+009`` (ABB's RWS 1.0 robtarget example), and a
# RAPID num is a 32-bit float (9E9 stored is 8999999488); anything from EXTAX_UNUSED_MIN up is unused.
EXTAX_UNUSED = 9e9
EXTAX_UNUSED_MIN = 8.99e9


def format_num(value: float) -> str:
    """Format a RAPID ``num`` literal (RAPID num is a 32-bit float; 9 significant digits keep it)."""
    if not math.isfinite(value):
        raise RapidValueError(f"num value {value!r} is not finite", code=RC_BAD_VALUE)
    if float(value).is_integer() and abs(value) < 1e9:
        return str(int(value))
    return f"{value:.9g}".replace("e", "E")


def parse_num(text: str) -> float:
    """Parse a RAPID ``num`` literal such as ``"1.5"`` or ``"9E+09"``."""
    if not _NUM_RE.match(text):
        raise RapidValueError(f"not a RAPID num literal: {text!r}", code=RC_BAD_VALUE)
    return float(text)


def format_bool(value: bool) -> str:
    """Format a RAPID ``bool`` literal (``TRUE`` / ``FALSE``)."""
    return "TRUE" if value else "FALSE"


def parse_bool(text: str) -> bool:
    """Parse a RAPID ``bool`` literal; RAPID accepts either case."""
    t = text.strip().upper()
    if t == "TRUE":
        return True
    if t == "FALSE":
        return False
    raise RapidValueError(f"not a RAPID bool literal: {text!r}", code=RC_BAD_VALUE)


def format_string(value: str) -> str:
    """Format a RAPID ``string`` literal: double quotes, ``"`` and ``\\`` doubled (RAPID's escaping)."""
    if len(value) > 80:
        raise RapidValueError(
            f"RAPID strings hold at most 80 characters, got {len(value)}", code=RC_BAD_VALUE
        )
    return '"' + value.replace("\\", "\\\\").replace('"', '""') + '"'


def parse_string(text: str) -> str:
    """Parse a RAPID ``string`` literal (quoted, with doubled quotes / backslashes)."""
    t = text.strip()
    if len(t) < 2 or t[0] != '"' or t[-1] != '"':
        raise RapidValueError(
            f"not a RAPID string literal (needs double quotes): {text!r}", code=RC_BAD_VALUE
        )
    inner = t[1:-1]
    # A lone quote inside is malformed; doubled quotes are one quote.
    if re.search(r'(?<!")"(?!")', inner.replace('""', "")):
        raise RapidValueError(f"unescaped quote in RAPID string literal: {text!r}", code=RC_BAD_VALUE)
    return inner.replace('""', '"').replace("\\\\", "\\")


def extax_or_none(value: float) -> float | None:
    """An external axis' value, or None where RAPID's 9E9 marks the axis unused."""
    return None if abs(value) >= EXTAX_UNUSED_MIN else float(value)


def format_extax(value: float) -> str:
    """Format an external axis for RWS: ``9E+09`` for an unused axis, else a num (6 decimals)."""
    if abs(value) >= EXTAX_UNUSED_MIN:
        return "9E+09"
    return format_num(round(float(value), 6))


@dataclass(frozen=True)
class JointTarget:
    """A RAPID ``jointtarget``: robot axes in degrees, external axes (deg or mm, 9E9 = unused)."""

    robax_deg: np.ndarray  # (6,) float
    extax: np.ndarray = field(default_factory=lambda: np.full(6, EXTAX_UNUSED))  # (6,) float


def format_jointtarget(jt: JointTarget | np.ndarray) -> str:
    """Format a ``jointtarget`` literal ``[[j1,..,j6],[e1,..,e6]]`` from a JointTarget or (6,) deg array."""
    if not isinstance(jt, JointTarget):
        jt = JointTarget(np.asarray(jt, dtype=float))
    rob = np.asarray(jt.robax_deg, dtype=float)
    ext = np.asarray(jt.extax, dtype=float)
    if rob.shape != (6,) or ext.shape != (6,):
        raise RapidValueError(
            f"jointtarget needs 6 robot and 6 external axes, got {rob.shape} and {ext.shape}",
            code=RC_BAD_VALUE,
        )
    return "[[" + ",".join(format_num(v) for v in rob) + "],[" + ",".join(format_num(v) for v in ext) + "]]"


_JT_RE = re.compile(r"^\s*\[\s*\[([^\[\]]*)\]\s*,\s*\[([^\[\]]*)\]\s*\]\s*$")


def parse_jointtarget(text: str) -> JointTarget:
    """Parse a ``jointtarget`` literal ``[[j1,..,j6],[e1,..,e6]]``."""
    m = _JT_RE.match(text)
    if not m:
        raise RapidValueError(f"not a RAPID jointtarget literal: {text!r}", code=RC_BAD_VALUE)
    rob = [parse_num(v) for v in m.group(1).split(",")]
    ext = [parse_num(v) for v in m.group(2).split(",")]
    if len(rob) != 6 or len(ext) != 6:
        raise RapidValueError(
            f"jointtarget needs 6+6 values, got {len(rob)}+{len(ext)}: {text!r}", code=RC_BAD_VALUE
        )
    return JointTarget(np.array(rob), np.array(ext))


_PARSERS: dict[str, Callable[[str], object]] = {
    "num": parse_num,
    "dnum": parse_num,
    "bool": parse_bool,
    "string": parse_string,
    "jointtarget": parse_jointtarget,
}


def validate_literal(rapid_type: str, text: str) -> str:
    """Check ``text`` parses as ``rapid_type``; return it normalised (types without a parser pass as is)."""
    parser = _PARSERS.get(rapid_type)
    if parser is None:
        return text
    value = parser(text)
    if rapid_type in ("num", "dnum"):
        return format_num(value)  # type: ignore[arg-type]
    if rapid_type == "bool":
        return format_bool(value)  # type: ignore[arg-type]
    if rapid_type == "jointtarget":
        return format_jointtarget(value)  # type: ignore[arg-type]
    return text.strip()


@dataclass(frozen=True)
class ElogEntry:
    """One event-log message, as the client reads it and the simulator keeps it. ``msgtype``: 1 info, 2 warning, 3 error; ``tstamp`` as the controller
    writes it (``2024-01-10 T 14:53:00``, controller clock); texts empty unless a language was asked."""

    seqnum: int
    msgtype: int
    code: int
    title: str
    desc: str
    tstamp: str
    conseqs: str = ""
    causes: str = ""
    actions: str = ""
    args: tuple[str, ...] = ()
