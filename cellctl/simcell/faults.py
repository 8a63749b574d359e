"""The simulated cell's run-time fault-control channel: payload models, the applier, the client.

``cellctl sim`` serves a Zenoh queryable ``<prefix>/sim/faults`` (``<prefix>`` is
``CellConfig.key_prefix``) on its **own** endpoint ``[sim] fault_listen``, never on the daemon's, so it
exists only where the simulator runs and survives a daemon restart. It is on when
``[sim] fault_control = true``. Payload (UTF-8 JSON object, at most 16 KiB; every section optional,
every knob optional, unknown knobs refused)::

    {
      "clear": true,                      # first switch every persistent knob off (EGM, RWS, laser)
      "egm": {                            # wire faults of the controller (EgmFaults); omitted = unchanged
        "loss_fraction": 0.05, "burst_ms": 50, "delay_ms": 0, "jitter_ms": 0,
        "duplicate_fraction": 0, "reorder_fraction": 0, "corrupt_fraction": 0,
        "stop_sending": false, "rx_loss_fraction": 0
      },
      "controller": {"action": "emergency_stop"},
          # | reset_emergency_stop | guard_stop | reset_guard_stop | motors_off | motors_on
          # | stop_rapid (the pendant's stop) | start_rapid
      "rws": {
        "error_status": 503, "error_path": "/",   # answer requests under error_path with it (0: clear)
        "delay_s": 2.0, "delay_path": "/",        # delay answers under delay_path (0: clear)
        "serving": false,                         # false: stop listening (connection refused); true: back
        "expire_sessions": true                   # forget every RWS session (clients must log in again)
      },
      "laser": {
        "disconnect_after_frames": 40,      # abort data connections after 40 more frames (0: disarm)
        "corrupt": {"groups": 3, "mode": "payload" | "framing", "probability": 0.0},
        "stall_s": 1.5, "stall_acquire": true,   # send nothing for 1.5 s (frames kept and sent late)
        "clock_jump_ms": 250.0,             # step the sensor clock (and its ms counter)
        "drop_frames": 10, "drop_probability": 0.0
      }
    }

The controller action is applied first; if the controller refuses it, nothing else is applied.
Reply (``query.reply``): :class:`FaultState` JSON, the knobs now in force and the simulators' counters::

    {"applied": ["egm", ...], "egm": {...EgmFaults...},
     "controller": {"ctrl_state": "motoron", "rapid_state": "running", "opmode": "AUTO"},
     "rws": {"errors": {"/": 503}, "delays_s": {}, "serving": true},
     "laser": {"disconnect_after_frames": null, "corrupt_groups": 0, ..., "stall_remaining_s": 0.0,
               "clock_jump_ms": 250.0},
     "stats": {"egm": {...}, "laser": {...}, "rws": {...}}}

An empty object ``{}`` changes nothing and returns the state. A refused payload gets ``reply_err``
with :class:`cellctl.api.ApiError` JSON whose ``field`` names the offending knob (``egm.bogus``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from typing import Annotated, Any, Literal

import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.api import JSON, ApiError, Model, TriggerError, parse_model
from cellctl.config import CellConfig, ZenohSection

log = structlog.get_logger(__name__)

MAX_FAULT_BYTES = 16 * 1024

Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Count = Annotated[int, Field(ge=0, le=10**9)]
PathPrefix = Annotated[str, Field(pattern=r"^/[\x21-\x7e]{0,200}$")]

ControllerAction = Literal[
    "emergency_stop",
    "reset_emergency_stop",
    "guard_stop",
    "reset_guard_stop",
    "motors_off",
    "motors_on",
    "stop_rapid",
    "start_rapid",
]


class _Knobs(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class EgmKnobs(_Knobs):
    """EGM wire faults (:class:`drivers.abb_egm.sim.egm.EgmFaults`); a knob left out stays as it is."""

    loss_fraction: Fraction | None = None
    burst_ms: NonNeg | None = None
    delay_ms: NonNeg | None = None
    jitter_ms: NonNeg | None = None
    duplicate_fraction: Fraction | None = None
    reorder_fraction: Fraction | None = None
    corrupt_fraction: Fraction | None = None
    stop_sending: bool | None = None
    rx_loss_fraction: Fraction | None = None


class ControllerKnobs(_Knobs):
    """One operator action at the cabinet or the pendant."""

    action: ControllerAction


class RwsKnobs(_Knobs):
    """RWS server faults: error answers, slow answers, not listening, sessions forgotten."""

    error_status: Annotated[int, Field(ge=0, le=599)] | None = None
    error_path: PathPrefix = "/"
    delay_s: Annotated[float, Field(ge=0, le=600, allow_inf_nan=False)] | None = None
    delay_path: PathPrefix = "/"
    serving: bool | None = None
    expire_sessions: bool = False


class CorruptKnobs(_Knobs):
    """Corrupt frame groups on the wire: the next ``groups``, and each with ``probability``."""

    groups: Count = 1
    mode: Literal["payload", "framing"] = "payload"
    probability: Fraction | None = None


class LaserKnobs(_Knobs):
    """HD8 simulator faults (:class:`drivers.laser.sim.sensor.SimFaults`)."""

    disconnect_after_frames: Count | None = None
    corrupt: CorruptKnobs | None = None
    stall_s: Annotated[float, Field(ge=0, le=600, allow_inf_nan=False)] | None = None
    stall_acquire: bool = True
    clock_jump_ms: Annotated[float, Field(ge=-1e9, le=1e9, allow_inf_nan=False)] | None = None
    drop_frames: Count | None = None
    drop_probability: Fraction | None = None


class FaultRequest(_Knobs):
    """The payload of ``<prefix>/sim/faults`` (see the module docstring)."""

    clear: bool = False
    egm: EgmKnobs | None = None
    controller: ControllerKnobs | None = None
    rws: RwsKnobs | None = None
    laser: LaserKnobs | None = None


class FaultState(Model):
    """The reply: what was applied, the knobs now in force, the simulators' counters."""

    applied: list[str] = Field(default_factory=list)
    egm: dict[str, Any] = Field(default_factory=dict)
    controller: dict[str, str] = Field(default_factory=dict)
    rws: dict[str, Any] = Field(default_factory=dict)
    laser: dict[str, Any] = Field(default_factory=dict)
    stats: dict[str, dict[str, Any]] = Field(default_factory=dict)


class FaultRequestError(TriggerError):
    """A fault payload that is refused; ``field`` names the offending knob (``egm.bogus``).

    The same shape as a refused trigger (code, field, message; ``to_api_error``).
    """


class FaultChannelError(Exception):
    """The fault channel could not be reached, or it refused the request (``error`` then holds why)."""

    def __init__(self, message: str, error: ApiError | None = None) -> None:
        self.error = error
        super().__init__(message)


def sim_faults_key(key_prefix: str) -> str:
    """The queryable's key expression for a cell's prefix (``CellConfig.key_prefix``)."""
    return f"{key_prefix}/sim/faults"


def parse_fault_request(payload: bytes | bytearray | str | None) -> FaultRequest:
    """Validate a fault payload; raises FaultRequestError naming the offending knob."""
    return parse_model(
        payload, FaultRequest, FaultRequestError, limit=MAX_FAULT_BYTES, unknown="unknown fault knob"
    )


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``["egm.loss_fraction=0.05", "controller.action=motors_off"]`` -> the nested payload dict.

    Values are read as JSON (numbers, true/false, null, objects) and otherwise taken as strings.
    Raises FaultRequestError naming the item that is not ``section.knob=value``.
    """
    out: dict[str, Any] = {}
    for item in items:
        path, sep, text = item.partition("=")
        parts = path.strip().split(".")
        if not sep or not all(parts):
            raise FaultRequestError(
                "malformed", item, "expected section.knob=value, e.g. egm.loss_fraction=0.05"
            )
        try:
            value: Any = json.loads(text)
        except json.JSONDecodeError:
            value = text
        node = out
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise FaultRequestError("malformed", item, f"{p!r} is given a value and knobs")
            node = nxt
        node[parts[-1]] = value
    return out


# ----------------------------------------------------------------------------------------- applier


class SimFaultControl:
    """Applies fault requests to a running :class:`cellctl.simcell.service.SimulatedCell`.

    Runs on the simulator's event loop (every knob is a plain attribute change, except RWS going
    down or up, which is awaited).
    """

    def __init__(self, cell: Any) -> None:
        self.cell = cell
        self.clock_jump_ms = 0.0
        self.refused = 0
        self._refused_logged = -1e9

    async def apply(self, req: FaultRequest) -> FaultState:
        """Apply ``req`` (controller action first); returns the state after it.

        Raises FaultRequestError (code ``not_allowed``) if the controller refuses the action.
        """
        from drivers.abb_egm.rapid_values import ControllerError

        ctl = self.cell.controller
        applied: list[str] = []
        if req.controller is not None:
            try:
                getattr(ctl.model, req.controller.action)()
            except ControllerError as exc:
                raise FaultRequestError("not_allowed", "controller.action", str(exc)) from None
            applied.append("controller")
        if req.clear:
            await self._clear()
            applied.append("clear")
        if req.egm is not None:
            changes = req.egm.model_dump(exclude_none=True)
            if changes:
                ctl.egm.set_faults(**changes)
            applied.append("egm")
        if req.rws is not None:
            await self._apply_rws(req.rws)
            applied.append("rws")
        if req.laser is not None:
            self._apply_laser(req.laser)
            applied.append("laser")
        state = self.state(applied)
        log.info(
            "sim_faults_applied",
            applied=",".join(applied) or "none",
            request=req.model_dump_json(exclude_none=True),
        )
        return state

    async def _clear(self) -> None:
        from drivers.abb_egm.sim.egm import EgmFaults
        from drivers.laser.sim.sensor import SimFaults

        ctl, sensor = self.cell.controller, self.cell.sensor
        ctl.egm.set_faults(**dataclasses.asdict(EgmFaults()))
        ctl.rws.clear_faults()
        if not ctl.rws.injected_faults()["serving"]:
            await ctl.rws.start()
        # replace in place: the simulator holds this object
        for f in dataclasses.fields(SimFaults):
            setattr(sensor.faults, f.name, getattr(SimFaults(), f.name))

    async def _apply_rws(self, k: RwsKnobs) -> None:
        rws = self.cell.controller.rws
        if k.error_status is not None:
            if k.error_status == 0:
                rws.clear_error(k.error_path)
            else:
                rws.inject_error(k.error_path, status=k.error_status, message="injected by sim/faults")
        if k.delay_s is not None:
            rws.set_delay(k.delay_s, k.delay_path)
        if k.expire_sessions:
            rws.expire_sessions()
        if k.serving is not None:
            serving = rws.injected_faults()["serving"]
            if k.serving and not serving:
                await rws.start()
            elif not k.serving and serving:
                await rws.stop()

    def _apply_laser(self, k: LaserKnobs) -> None:
        # the sensor's own fault channel applies them (drivers/laser/sim/sensor.py); the knobs here
        # were validated already, so it cannot refuse them
        knobs: dict[str, Any] = {
            "disconnect_after_frames": k.disconnect_after_frames,
            "drop_frames": k.drop_frames,
            "drop_probability": k.drop_probability,
            "stall_s": k.stall_s,
            "stall_acquire": k.stall_acquire,
            "clock_jump_us": None if k.clock_jump_ms is None else k.clock_jump_ms * 1e3,
        }
        if k.corrupt is not None:
            knobs.update(corrupt_groups=k.corrupt.groups, corrupt_mode=k.corrupt.mode,
                         corrupt_probability=k.corrupt.probability)  # fmt: skip
        reply = self.cell.sensor.apply_faults({"laser": {n: v for n, v in knobs.items() if v is not None}})
        if not reply["ok"]:
            raise RuntimeError(f"the sensor refused validated knobs: {reply['error']}")
        if k.clock_jump_ms is not None:
            self.clock_jump_ms += k.clock_jump_ms

    def state(self, applied: list[str] | None = None) -> FaultState:
        """The knobs in force and the counters of both simulators."""
        ctl, sensor = self.cell.controller, self.cell.sensor
        lf = sensor.faults
        return FaultState(
            applied=applied or [],
            egm=dataclasses.asdict(ctl.egm.faults),
            controller={
                "ctrl_state": str(ctl.model.ctrl_state),
                "rapid_state": str(ctl.model.rapid_state),
                "opmode": str(ctl.model.opmode),
            },
            rws=ctl.rws.injected_faults(),
            laser={
                "disconnect_after_frames": lf.disconnect_after_frames,
                "corrupt_groups": lf.corrupt_groups,
                "corrupt_probability": lf.corrupt_probability,
                "corrupt_mode": lf.corrupt_mode,
                "drop_frames": lf.drop_frames,
                "drop_probability": lf.drop_probability,
                "stall_remaining_s": max(0.0, lf.stall_until_s - sensor.clock()),
                "stall_acquire": lf.stall_acquire,
                "clock_jump_ms": self.clock_jump_ms,
            },
            stats={
                "egm": dataclasses.asdict(ctl.egm.stats),
                "laser": dataclasses.asdict(sensor.stats),
                "rws": dict(ctl.rws.stats),
            },
        )

    async def handle_query(self, query: Any) -> None:
        """Answer one query on ``<prefix>/sim/faults``: validate, apply, reply (errors as ApiError JSON)."""
        payload = query.payload
        try:
            if payload is not None and len(payload) > MAX_FAULT_BYTES:
                raise FaultRequestError(
                    "too_large", "payload", f"{len(payload)} bytes, limit {MAX_FAULT_BYTES}"
                )
            raw = payload.to_bytes() if payload is not None else b"{}"
            req = parse_fault_request(raw or b"{}")
            state = await self.apply(req)
        except FaultRequestError as err:
            self._refused_one(err)
            query.reply_err(err.to_api_error().to_json(), encoding=JSON)
            return
        query.reply(query.key_expr, state.to_json(), encoding=JSON)

    def _refused_one(self, err: FaultRequestError) -> None:
        self.refused += 1
        now = time.monotonic()
        if now - self._refused_logged >= 5.0:
            self._refused_logged = now
            log.warning(
                "sim_faults_refused", code=err.code, field=err.field, error=err.message, total=self.refused
            )


# ----------------------------------------------------------------------------------------- sessions


def fault_zenoh_section(cfg: CellConfig) -> ZenohSection:
    """The ``[zenoh]`` settings of the fault channel: a peer on ``[sim] fault_listen`` (same access)."""
    return cfg.zenoh.model_copy(
        update={"mode": "peer", "listen": [cfg.sim.fault_listen], "connect": [], "multicast_scouting": False}
    )


def open_fault_session(cfg: CellConfig, *, role: Literal["serve", "connect"]) -> Any:
    """A Zenoh session of the fault channel: the simulator serves it, clients connect to it."""
    from cellctl.api.session import build_zenoh_config, open_session

    zcfg = build_zenoh_config(fault_zenoh_section(cfg), role=role, key_prefix=cfg.key_prefix)
    return open_session(zcfg, what=f"sim fault channel ({cfg.sim.fault_listen})")


async def send_faults(
    session: Any, key_prefix: str, request: dict[str, Any] | FaultRequest, *, timeout_s: float = 10.0
) -> FaultState:
    """Send one fault request over ``session``; returns the simulator's :class:`FaultState`.

    Raises FaultChannelError when no simulator answers or it refuses (``.error`` names the knob).
    """
    from cellctl.api.session import async_get

    body = (
        request.model_dump_json(exclude_none=True)
        if isinstance(request, FaultRequest)
        else json.dumps(request)
    )
    key = sim_faults_key(key_prefix)
    replies = await async_get(session, key, payload=body, timeout_s=timeout_s)
    if not replies:
        raise FaultChannelError(
            f"{key}: no reply within {timeout_s} s (is `cellctl sim` running with fault_control?)"
        )
    reply = replies[0]
    if reply.ok is None:
        raw = reply.err.payload.to_bytes()
        try:
            err = ApiError.model_validate_json(raw)
        except ValidationError:
            raise FaultChannelError(f"{key}: error reply {raw[:200]!r}") from None
        where = f"{err.field}: " if err.field else ""
        raise FaultChannelError(f"{key}: {err.code}: {where}{err.message}", err)
    try:
        return FaultState.model_validate_json(reply.ok.payload.to_bytes())
    except ValidationError as exc:
        raise FaultChannelError(f"{key}: reply is not a FaultState: {exc}") from None


async def serve_fault_control(cfg: CellConfig, cell: Any) -> tuple[Any, SimFaultControl] | None:
    """Open the channel's session and declare the queryable; None (logged) if it cannot listen.

    The caller closes the returned session in ``finally``. A simulator whose fault endpoint is taken
    still simulates: the channel is an extra, and its absence is said in the log and the ready line.
    """
    import asyncio

    from cellctl.api.session import ZenohSetupError, close_session, declare_async_queryable

    control = SimFaultControl(cell)
    try:
        session = await asyncio.to_thread(open_fault_session, cfg, role="serve")
    except ZenohSetupError as exc:
        log.error("sim_fault_control_unavailable", endpoint=cfg.sim.fault_listen, error=str(exc))
        return None
    try:
        declare_async_queryable(session, sim_faults_key(cfg.key_prefix), control.handle_query)
    except Exception:
        with contextlib.suppress(Exception):
            close_session(session)
        raise
    log.info("sim_fault_control_ready", endpoint=cfg.sim.fault_listen, key=sim_faults_key(cfg.key_prefix))
    return session, control
