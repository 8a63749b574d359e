"""A simulated cell in real processes (`cellctl sim`, `cellctl run`, `cellctl worker`) for the e2e tests.

Used by the e2e, fault and security tests. Everything binds loopback ports that were
free a moment ago; every process is stopped by its own pid.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path
from typing import Any

from analysis.design.mesh import save_mesh
from analysis.design.plates import design_mesh, plate_spec
from cellctl.commands.demo_cmd import DEMO_DESIGN, Processes, demo_config, to_toml, wait_ready_line
from cellctl.config import load_config

REPO = Path(__file__).resolve().parents[2]
#: the tiny cells' simulated arm at start: its sensor 716 mm above the base, over the bed, looking down
PARKED_ABOVE_BED_Q_DEG = (0.0, 5.0, 30.0, 0.0, 55.0, 0.0)


def tiny_cell_config(
    out: Path,
    *,
    forming_error: str = "default",
    kind: str = "sail",
    angle_deg: float | None = None,
    pos_xy_mm: tuple[float, float] | None = None,
    tolerances: dict[str, float] | None = None,
    parked: bool = True,
    **plate: float,
) -> Path:
    """A cell.toml for a 300 x 200 mm sail plate scanned at 1.5 mm profile spacing (a scan of ~30 s).

    ``forming_error="none"``: the simulated plate is its design, which a half turn maps onto itself.
    ``kind``: the plate's shape (``[sim.plate] kind``; ``radius_x_mm``, ``radius_y_mm`` as keywords).
    ``angle_deg``, ``pos_xy_mm``: the simulated plate's yaw and place on the bed (default: cell.toml's).
    ``tolerances``: ``[analysis.tolerances]`` keys to override (tighter ones make a line fail).
    ``parked``: the simulated arm starts parked above the bed (see below); False: at cell.toml's home.
    """
    base = load_config(REPO / "cell.toml").model_dump(mode="json")
    cfg = demo_config(base, out)
    cfg["sim"]["plate"].update(length_mm=plate.get("length_mm", 300.0), width_mm=plate.get("width_mm", 200.0))
    cfg["sim"]["plate"]["forming_error"] = forming_error
    cfg["sim"]["plate"]["kind"] = kind
    cfg["sim"]["plate"].update({k: plate[k] for k in ("radius_x_mm", "radius_y_mm") if k in plate})
    if angle_deg is not None:
        cfg["sim"]["placement"]["angle_deg"] = angle_deg
    if pos_xy_mm is not None:
        cfg["sim"]["placement"]["pos_mm"][:2] = [float(v) for v in pos_xy_mm]
    cfg["scan"].update(profile_spacing_mm=plate.get("profile_spacing_mm", 1.5))
    # Passes along the plate's length, as on every cell before issue 20's "fastest": on this plate the
    # planner would also solve the passes across (estimated 26.0 s against 27.0 s, then refused on a
    # wrist flip), 1.3-2.6 s more for every scan of every e2e and fault test. Choosing the axis has
    # its own tests (tests/planning/test_pass_axis.py).
    cfg["scan"]["pass_axis"] = "longer"
    # The simulated arm starts parked above the bed, its sensor looking down 200-300 mm above where
    # the tiny plate's plans begin (TCP at x 1411, y 0, z 716 mm), not at cell.toml's home (z 1622 mm):
    # the move to the plan's start, capped at half the TCP speed limit, took 10.6 s of every cell's
    # first job from there, and now 2-3 s. The move itself still runs, TCP-capped (it is not within
    # the start tolerance); a pause during it: tests/motion/test_executor_sim.py; the long approach
    # from home: the measurement e2e's cell (``parked=False``).
    if parked:
        cfg["sim"]["egm_q_start_deg"] = list(PARKED_ABOVE_BED_Q_DEG)
    # The HTML/PDF render (a child process of tens of CPU-seconds) has its own tests
    # (tests/zenoh/test_daemon_html_step.py); here it would only compete with the next scan.
    cfg["daemon"]["write_html_report"] = False
    # The heating plan (a child process of seconds of FE after every job) has its own tests
    # (tests/zenoh/test_daemon_heat_plan_step.py); here the daemon only writes that it is off.
    cfg.setdefault("forming", {})["enabled"] = False
    # The locate run has its own e2e tests (tests/e2e/test_locate_e2e.py): here a given placement is
    # trusted, and every job starts its scan at once.
    cfg["locate"]["check_given"] = False
    # The daemon's own heartbeat and acknowledgement timeouts (cell.toml's): the 5 s these cells once
    # had predate the workers' liveliness tokens, by which the daemon now sees a killed or cut-off
    # worker at once; short timeouts only made a worker slowed by load look lost (a second attempt).
    cfg["analysis"].update(
        transverse_count=2, transverse_spacing_mm=80.0, longitudinal_count=1, longitudinal_spacing_mm=100.0
    )  # fmt: skip
    cfg["analysis"]["tolerances"].update(tolerances or {})
    (out / "designs").mkdir(parents=True, exist_ok=True)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    path = out / "cell.toml"
    path.write_text(to_toml(cfg), encoding="utf-8")
    c = load_config(path)
    sp = c.sim.plate
    spec = plate_spec(sp.kind, length_mm=sp.length_mm, width_mm=sp.width_mm, thickness_mm=sp.thickness_mm,
                      radius_x_mm=sp.radius_x_mm, radius_y_mm=sp.radius_y_mm)  # fmt: skip
    save_mesh(design_mesh(spec, pitch_mm=5.0), out / "designs" / DEMO_DESIGN)
    return path


class Cell:
    """The processes of one simulated cell plus a client session to it."""

    def __init__(self, out: Path, config: Path) -> None:
        self.out = out
        self.config_path = config
        self.cfg = load_config(config)
        env = dict(os.environ)
        env.setdefault("CELL_RWS_PASSWORD", "robotics")
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        self.procs = Processes(out / "logs", config, env)

    def start(self, *, sim: bool = True, run: bool = True, worker: bool = True) -> None:
        if sim:
            p = self.procs.start("sim", "sim")
            wait_ready_line(self.out / "logs" / "sim.out", p, 120.0)
        if run:
            self.procs.start("run", "run")
        if worker:
            self.procs.start("worker", "worker")

    def proc(self, name: str):
        return next(p for n, p in self.procs.procs if n == name)

    def stop(self) -> dict[str, Any]:
        return self.procs.stop_all()

    @property
    def jobs_dir(self) -> Path:
        return Path(self.cfg.cell.data_dir) / "jobs"

    def job_record(self, job_id: str) -> dict[str, Any]:
        return json.loads((self.jobs_dir / job_id / "job.json").read_text())


async def open_client(cfg) -> Any:
    """A client session to the daemon, retried until it listens (60 s)."""
    from cellctl.api.session import ZenohSetupError, build_zenoh_config, open_session

    deadline = time.monotonic() + 60.0
    while True:
        try:
            return await asyncio.to_thread(
                open_session, build_zenoh_config(cfg.zenoh, role="connect", key_prefix=cfg.key_prefix)
            )
        except ZenohSetupError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)


async def wait_status(follower, pred, timeout_s: float = 90.0):
    """Wait until ``pred(CellStatus)`` holds; returns that status."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = follower.latest
        if st is not None and pred(st):
            return st
        await follower.next(0.5)
    raise TimeoutError(f"status condition not met within {timeout_s} s; last {follower.latest}")


async def trigger_demo_plate(
    cfg, plate_id: str, timeout_s: float = 300.0, *, placement: Any = "sim", design: str = DEMO_DESIGN
) -> tuple[Any, tuple[str, str, Any]]:
    """Wait until the cell is idle with a worker, trigger the demo design (or ``design``, a file in the
    designs directory; a typed TriggerRequest) and follow the job: ``(TriggerAccepted, (state, message,
    report))``. ``placement``: ``"sim"`` the simulated plate's exact placement, a
    :class:`~analysis.contracts.placement.Placement` that one, None none (the cell locates the plate first)."""
    from analysis.contracts.placement import Placement
    from cellctl.api import Keys, TriggerAccepted, TriggerRequest, call
    from cellctl.api.session import close_session
    from cellctl.commands.scan_cmd import StatusFollower, wait_for_job

    session = await open_client(cfg)
    keys = Keys(cfg.key_prefix)
    follower = StatusFollower(session, keys)
    try:
        await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 120.0)
        if placement == "sim":
            pl = cfg.sim.placement
            placement = Placement(pos_mm=tuple(pl.pos_mm), rpy_deg=(0.0, 0.0, pl.angle_deg))
        req = TriggerRequest(plate_id=plate_id, design=design, placement=placement)
        acc = await call(session, keys.trigger, req.model_dump_json(exclude_none=True), TriggerAccepted)
        return acc, await wait_for_job(follower, acc.job_id, timeout_s)
    finally:
        follower.close()
        await asyncio.to_thread(close_session, session)


#: the ship-coordinates pose of the IGES plate's design (:func:`iges_ship_plate`): the design frame
#: turned 90 degrees about z, 40 m aft, 2.5 m to port, 3 m up
T_SHIP_DESIGN = (
    (0.0, -1.0, 0.0, 40000.0),
    (1.0, 0.0, 0.0, -2500.0),
    (0.0, 0.0, 1.0, 3000.0),
    (0.0, 0.0, 0.0, 1.0),
)
IGES_DESIGN = "plate-ship.igs"


def iges_ship_plate(path: Path) -> Path:
    """Make a tiny cell's plate (``tiny_cell_config``'s sail, its forming error) one from files, as a
    plate designed in ship coordinates arrives: the design as IGES in ship coordinates
    (``designs/plate-ship.igs``, what the trigger names) and the formed top surface as a mesh in the
    same coordinates (``plates/formed.ply``), the simulator reading them (``[sim.plate] kind =
    "mesh"``, paths relative to the cell.toml). Rewrites the cell.toml at ``path``; returns it."""
    import numpy as np

    from analysis.design.cad_write import write_design
    from analysis.design.plates import default_forming_error
    from analysis.synth import write_formed_mesh

    raw = load_config(path).model_dump(mode="json")
    sp = raw["sim"]["plate"]
    if sp["forming_error"] != "default":
        raise ValueError("iges_ship_plate: the tiny cell's plate with its default forming error only")
    spec = plate_spec(sp["kind"], length_mm=sp["length_mm"], width_mm=sp["width_mm"], thickness_mm=sp["thickness_mm"],
                      radius_x_mm=sp["radius_x_mm"], radius_y_mm=sp["radius_y_mm"])  # fmt: skip
    T = np.array(T_SHIP_DESIGN)
    out = path.parent
    write_design(spec, out / "designs" / IGES_DESIGN, T_file_design=T)
    # a 1 mm grid: on 4 mm facets the default error's bump (1.5 mm high, 20 mm wide) is a sharp peak
    # the product's resting patches read low, and the design sank 0.12 mm into it (0.03-0.05 mm on the
    # analytic plates: truth_check.CheckLimits)
    write_formed_mesh(
        spec, default_forming_error(spec), out / "plates" / "formed.ply", pitch_mm=1.0, T_file_design=T
    )
    raw["sim"]["plate"] = {"kind": "mesh", "mesh_file": "plates/formed.ply",
                           "design_file": f"designs/{IGES_DESIGN}", "thickness_mm": sp["thickness_mm"], "seed": sp["seed"]}  # fmt: skip
    path.write_text(to_toml(raw), encoding="utf-8")
    return path
