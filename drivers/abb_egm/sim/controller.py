"""The simulated ABB controller: EGM over UDP and RWS over HTTP(S) on one shared controller state.

Composes :class:`~drivers.abb_egm.sim.model.ControllerModel` (panel, RAPID program, event
log), :class:`~drivers.abb_egm.sim.rws_server.RwsServer` and :class:`~drivers.abb_egm.sim.egm.EgmControllerSim`.
Starting the RAPID program through RWS starts the EGM session; the end variable, motors off, an
emergency stop or a communication timeout end it.

Run it on its own::

    python -m drivers.abb_egm.sim --egm-port 6511 --rws-port 8080 [--motors-on --start] [faults]

It prints one JSON line with its addresses on stdout and runs until SIGINT or SIGTERM.

With ``--fault-port`` (0: any free port) it serves its **fault channel** on TCP
(:mod:`drivers.sim.fault_channel`): one JSON object a line, ``{"egm": {"stop_sending": true, "loss_fraction": 0.2, ...}}`` (the knobs of
:class:`~drivers.abb_egm.sim.egm.EgmFaults`; a knob left out stays as it is, ``{}`` only reads),
answered by one line ``{"ok": true, "egm": {...the knobs in force...}, "stats": {...counters...}}``
or ``{"ok": false, "error": "..."}``. The panel (motors, RAPID) is RWS's, as on a real controller.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import os
import signal
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import structlog

from drivers.abb_egm.limits import EGM_CYCLE_S
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmFaults, EgmSimConfig, FaultError
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer
from drivers.runtime import precise_event_loop
from drivers.sim.fault_channel import start_fault_server

__all__ = ["ControllerSim", "ControllerSimConfig", "main"]

log = structlog.get_logger(__name__)

#: ABB's factory password of "Default User"; published in every RWS manual, not a secret
ABB_DEFAULT_PASSWORD = "robotics"


@dataclass(frozen=True)
class ControllerSimConfig:
    """Everything the simulated controller needs besides the EGM settings.

    ``rws_users`` maps user name to password. ``motors_on`` / ``start_program`` put the controller
    in that state at start (as an operator at the cabinet would). ``fault_port``: serve the fault
    channel (module docstring) on this TCP port of ``rws_host`` (0: any free port; None: off).
    """

    rws_host: str = "127.0.0.1"
    rws_port: int = 0
    rws_profile: str = "rws1"
    rws_users: tuple[tuple[str, str], ...] = (("Default User", ABB_DEFAULT_PASSWORD),)
    rws_max_sessions: int = 70
    motors_on: bool = False
    start_program: bool = False
    fault_port: int | None = None


class ControllerSim:
    """One simulated controller. ``await start()``, use ``model`` / ``egm`` / ``rws``, ``await stop()``."""

    def __init__(
        self,
        config: ControllerSimConfig | None = None,
        egm_config: EgmSimConfig | None = None,
        faults: EgmFaults | None = None,
        *,
        model: ControllerModel | None = None,
        clock=None,
    ) -> None:
        self.config = config or ControllerSimConfig()
        self.model = model or ControllerModel()
        kwargs = {} if clock is None else {"clock": clock}
        self.egm = EgmControllerSim(egm_config, faults=faults, model=self.model, **kwargs)
        self.rws = RwsServer(
            self.model,
            profile=self.config.rws_profile,  # type: ignore[arg-type]
            host=self.config.rws_host,
            port=self.config.rws_port,
            users=dict(self.config.rws_users),
            max_sessions=self.config.rws_max_sessions,
        )
        self._started = False
        self._fault_server: asyncio.Server | None = None

    async def start(self) -> dict:
        """Start RWS, then EGM (and the fault channel); returns the addresses (see :meth:`addresses`)."""
        await self.rws.start()
        try:
            await self.egm.start()
            if self.config.fault_port is not None:
                self._fault_server = await start_fault_server(
                    self.config.rws_host, self.config.fault_port, self.apply_faults
                )
        except BaseException:
            await self.egm.stop()
            await self.rws.stop()
            raise
        self._started = True
        if self.config.motors_on:
            self.model.motors_on()
        if self.config.start_program:
            self.model.start_rapid()
        return self.addresses()

    async def stop(self) -> None:
        """Stop EGM first (no more packets), then RWS."""
        if not self._started:
            return
        self._started = False
        if self._fault_server is not None:
            self._fault_server.close()
            self._fault_server = None
        await self.egm.stop()
        await self.rws.stop()

    def apply_faults(self, request: object) -> dict:
        """One fault-channel request (the decoded JSON object) applied; returns the reply object."""
        try:
            if not isinstance(request, dict) or set(request) - {"egm"}:
                raise FaultError(f"want an object with an 'egm' section, got {request!r:.200}")
            knobs = request.get("egm", {})
            if not isinstance(knobs, dict):
                raise FaultError(f"egm: want an object of fault knobs, got {knobs!r:.200}")
            faults = self.egm.set_faults(**knobs) if knobs else self.egm.faults
        except FaultError as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "egm": dataclasses.asdict(faults), "stats": dataclasses.asdict(self.egm.stats)}

    def addresses(self) -> dict:
        """``{"egm_local": [host, port], "egm_sensor": [host, port], "rws_url": str, "rws_profile": str}``."""
        cfg = self.egm.config
        addresses = {
            "egm_local": list(self.egm.local_address),
            "egm_sensor": [cfg.sensor_host, cfg.sensor_port],
            "rws_url": self.rws.base_url,
            "rws_profile": self.rws.profile,
        }
        if self._fault_server is not None:
            addresses["fault"] = list(self._fault_server.sockets[0].getsockname()[:2])
        return addresses

    async def __aenter__(self) -> ControllerSim:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.stop()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m drivers.abb_egm.sim",
        description="Simulated ABB controller: EGM (UDP client) and RWS (HTTP/HTTPS server).",
    )
    p.add_argument("--egm-host", default="127.0.0.1", help="sensor host the controller sends EgmRobot to")
    p.add_argument("--egm-port", type=int, required=True, help="sensor UDP port (the EGM endpoint)")
    p.add_argument("--egm-local-port", type=int, default=0, help="controller's own UDP port (0: any)")
    p.add_argument("--rws-host", default="127.0.0.1")
    p.add_argument("--rws-port", type=int, default=0, help="RWS port (0: any free port)")
    p.add_argument("--rws-profile", choices=("rws1", "rws2"), default="rws1")
    p.add_argument("--rws-user", default="Default User")
    p.add_argument(
        "--rws-password-env",
        default="CELL_RWS_PASSWORD",
        help="environment variable holding the RWS password (ABB's factory default if unset)",
    )
    p.add_argument(
        "--cycle-ms", type=float, default=EGM_CYCLE_S * 1e3, help="EGM cycle (4.032 ms on a real robot)"
    )
    p.add_argument(
        "--comm-timeout-s", type=float, default=1.0, help="used outside the RAPID program's values"
    )
    p.add_argument("--motors-on", action="store_true", help="switch the motors on at start")
    p.add_argument("--start", action="store_true", help="start the RAPID program (EGM session) at start")
    p.add_argument("--loss", type=float, default=0.0, help="EgmRobot loss fraction")
    p.add_argument("--burst-ms", type=float, default=0.0, help="each loss lasts this long")
    p.add_argument("--delay-ms", type=float, default=0.0)
    p.add_argument("--jitter-ms", type=float, default=0.0)
    p.add_argument("--duplicate", type=float, default=0.0, help="duplicate fraction")
    p.add_argument("--reorder", type=float, default=0.0, help="reorder fraction")
    p.add_argument("--corrupt", type=float, default=0.0, help="corrupted-bytes fraction")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument(
        "--fault-port", type=int, default=None, help="serve the fault channel here (0: any free port)"
    )
    p.add_argument("--q-start-deg", type=float, nargs=6, default=None, help="the arm's joints at start, deg")
    return p


async def _serve(args: argparse.Namespace) -> int:
    password = os.environ.get(args.rws_password_env)
    if password is None:
        log.info("rws_default_password", user=args.rws_user, env=args.rws_password_env)
        password = ABB_DEFAULT_PASSWORD
    sim = ControllerSim(
        ControllerSimConfig(
            rws_host=args.rws_host,
            rws_port=args.rws_port,
            rws_profile=args.rws_profile,
            rws_users=((args.rws_user, password),),
            motors_on=args.motors_on or args.start,
            start_program=args.start,
            fault_port=args.fault_port,
        ),
        EgmSimConfig(
            sensor_host=args.egm_host,
            sensor_port=args.egm_port,
            local_port=args.egm_local_port,
            cycle_s=args.cycle_ms / 1000.0,
            comm_timeout_s=args.comm_timeout_s,
            seed=args.seed,
            **({} if args.q_start_deg is None else {"q_start_deg": tuple(args.q_start_deg)}),
        ),
        EgmFaults(
            loss_fraction=args.loss,
            burst_ms=args.burst_ms,
            delay_ms=args.delay_ms,
            jitter_ms=args.jitter_ms,
            duplicate_fraction=args.duplicate,
            reorder_fraction=args.reorder,
            corrupt_fraction=args.corrupt,
        ),
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    addresses = await sim.start()
    print(json.dumps(addresses), flush=True)
    try:
        await stop.wait()
    finally:
        await sim.stop()
        log.info("controller_sim_shutdown", **{k: v for k, v in vars(sim.egm.stats).items()})
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m drivers.abb_egm.sim``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        EgmFaults(
            loss_fraction=args.loss,
            burst_ms=args.burst_ms,
            delay_ms=args.delay_ms,
            jitter_ms=args.jitter_ms,
            duplicate_fraction=args.duplicate,
            reorder_fraction=args.reorder,
            corrupt_fraction=args.corrupt,
        )
    except ValueError as exc:  # a bad knob value: a clear message, not a traceback
        print(f"controller simulator: {exc}", file=sys.stderr)
        return 2
    try:
        with asyncio.Runner(loop_factory=precise_event_loop) as runner:
            return runner.run(_serve(args))
    except OSError as exc:  # e.g. a port in use: say so plainly instead of a traceback
        print(f"controller simulator: {exc}", file=sys.stderr)
        return 2
