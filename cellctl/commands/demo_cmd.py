"""`cellctl demo --out DIR`: the whole cell on this machine in one command.

Starts `cellctl sim`, `cellctl run` and `cellctl worker` as separate processes with a configuration
derived from cell.toml (free loopback ports, data under DIR, the demo plate), triggers the scan of
the simulated formed plate over Zenoh, waits for the report, prints the per-line table and the
report's path, stops every process and exits 0 (1 on a fail verdict is still a working demo: it
exits 0 too; 2 when something did not work). No process is left behind, also on Ctrl-C or failure.

The default demo plate is a 600 x 400 mm sail scanned at 1 mm profile spacing, so the demo fits in
about two minutes on two cores; ``--full`` scans the paper's 1200 x 800 mm plate at cell.toml's
settings. The job is done when report.json is stored; the HTML / PDF render follows, and the demo
waits for it before it stops the processes.

``--hmi`` also starts `cellctl hmi` on http://127.0.0.1:8088 (one user per role, passwords printed)
before the scan, and keeps the whole cell running after it until Ctrl-C: start more scans from the
browser.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config
from cellctl.jobstore.jobs import JobStoreError, read_job_record

if TYPE_CHECKING:
    from analysis.contracts.job import Report

EXIT_OK, EXIT_ERROR = 0, 2
DEMO_DESIGN = "demo-plate.ply"
HMI_ADDRESS = "127.0.0.1:8088"


class DemoError(Exception):
    """A demo step that failed (names the step and where its log is)."""


#: the lowest port :func:`free_port` hands out
_PORT_FLOOR = 20000
#: ports this process has handed out (a port picked is free but not held: never give it twice)
_PORTS_GIVEN: set[int] = set()


def _ephemeral_floor() -> int:
    """The lowest port of the kernel's ephemeral range (the local ports of outgoing connections)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A free loopback port of the given socket kind (TCP or UDP), below the kernel's ephemeral
    range and not handed out before by this process.

    The port is free when picked, not held: the process it is meant for binds it later. A port from
    the ephemeral range (what binding port 0 gives) can meanwhile become the local port of any
    outgoing connection on the machine, and the server then fails with "address already in use"
    (seen in CI: a daemon's Zenoh listener). Below that range only a listener takes a port.
    """
    ceiling = _ephemeral_floor()
    rng = random.SystemRandom()
    for _ in range(200):
        port = rng.randrange(_PORT_FLOOR, max(ceiling, _PORT_FLOOR + 1000))
        if port in _PORTS_GIVEN:
            continue
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _PORTS_GIVEN.add(port)
        return port
    with socket.socket(socket.AF_INET, kind) as s:  # a crowded range: whatever the kernel gives
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def demo_config(base: dict[str, Any], out_dir: Path, *, full: bool = False) -> dict[str, Any]:
    """The demo's configuration: ``base`` (a CellConfig dump) with loopback ports, data under ``out_dir``
    and, unless ``full``, the small demo plate with a coarser profile spacing."""
    cfg = json.loads(json.dumps(base))
    rws_port = free_port()
    cfg["cell"].update(id="demo", data_dir=str(out_dir / "data"), designs_dir=str(out_dir / "designs"))
    cfg["worker"]["data_dir"] = str(out_dir / "worker-data")  # its own: results come back over Zenoh
    cfg["robot"].update(
        egm_host="127.0.0.1", egm_port=free_port(socket.SOCK_DGRAM), rws_url=f"http://127.0.0.1:{rws_port}"
    )
    cfg["laser"].update(host="127.0.0.1", control_port=free_port(), data_port=free_port())
    cfg["zenoh"].update(
        mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[], multicast_scouting=False
    )
    cfg["zenoh"]["access"]["enabled"] = False
    cfg["sim"]["rws_port"] = rws_port
    cfg["sim"]["fault_listen"] = f"tcp/127.0.0.1:{free_port()}"  # several sims may run at once
    cfg["sim"]["faults"] = {}
    # The simulated arm shares two loaded cores with everything else; a descheduled simulator makes
    # it lag its reference by a few cycles: allow 0.1 s of lag at the scan speed (10 mm at 100 mm/s,
    # 20 mm at cell.toml's 200 mm/s; seen: 113 ms at load 6). A real cell keeps its own limit.
    speed = cfg["scan"]["speed_mm_s"]
    speed_mm_s = cfg["laser"]["rate_hz"] * cfg["scan"]["profile_spacing_mm"] if speed == "auto" else speed
    cfg["robot"]["tracking_error_max_mm"] = max(
        cfg["robot"]["tracking_error_max_mm"], 10.0, 0.1 * float(speed_mm_s)
    )
    # Likewise a simulator descheduled for 100 ms is not a stalled controller (observed at load 6).
    cfg["robot"]["egm_watchdog_s"] = max(cfg["robot"]["egm_watchdog_s"], 0.5)
    # The demo triggers with the simulated plate's true placement: checking it with a locate run would
    # only add its minute to the demo's (and benchmarks/end_to_end.py's) figures. Trigger without a
    # placement to see the cell find the plate (docs/locate.md).
    cfg["locate"]["check_given"] = False
    if not full:
        cfg["sim"]["plate"].update(kind="sail", length_mm=600.0, width_mm=400.0)
        cfg["scan"].update(
            profile_spacing_mm=1.0, placement_uncertainty_mm=10.0, placement_uncertainty_deg=1.0
        )
        cfg["analysis"].update(
            transverse_count=6,
            transverse_spacing_mm=80.0,
            longitudinal_count=3,
            longitudinal_spacing_mm=100.0,
        )
    return cfg


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(data: dict[str, Any]) -> str:
    """A small TOML writer for configuration dicts (tables of scalars, lists and nested tables)."""
    out: list[str] = []

    def table(name: str, d: dict[str, Any]) -> None:
        scalars = {
            k: v for k, v in d.items() if v is not None and not (isinstance(v, dict) and _is_table(k, v))
        }
        out.append(f"[{name}]")
        out.extend(f"{k} = {_toml_value(v)}" for k, v in scalars.items())
        out.append("")
        for k, v in d.items():
            if isinstance(v, dict) and _is_table(k, v):
                table(f"{name}.{k}", v)

    for name, section in data.items():
        table(name, section)
    return "\n".join(out)


def _is_table(key: str, value: dict) -> bool:
    # user -> secret-env maps stay inline tables; everything else nested is a sub-table
    return key != "rws_users"


class Processes:
    """Child processes of the demo, stopped in reverse order with SIGTERM, SIGKILL after a grace time."""

    def __init__(self, log_dir: Path, config: Path, env: dict[str, str]) -> None:
        self.log_dir = log_dir
        self.config = config
        self.env = env
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, *args: str) -> subprocess.Popen:
        cmd = [sys.executable, "-m", "cellctl", "--log-format", "json", *args, "--config", str(self.config)]
        out = open(self.log_dir / f"{name}.out", "wb")  # noqa: SIM115 - closed with the process
        err = open(self.log_dir / f"{name}.log", "wb")  # noqa: SIM115
        p = subprocess.Popen(cmd, stdout=out, stderr=err, env=self.env, stdin=subprocess.DEVNULL)
        out.close()
        err.close()
        self.procs.append((name, p))
        return p

    def check_alive(self) -> None:
        for name, p in self.procs:
            if p.poll() is not None:
                raise DemoError(
                    f"`cellctl {name}` exited with {p.returncode}; see {self.log_dir / (name + '.log')}"
                )

    def stop_all(self, grace_s: float = 30.0) -> dict[str, int | None]:
        codes: dict[str, int | None] = {}
        for name, p in reversed(self.procs):
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGTERM)
            try:
                codes[name] = p.wait(grace_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    p.kill()
                codes[name] = p.wait()
        self.procs.clear()
        return codes


def wait_ready_line(path: Path, proc: subprocess.Popen, timeout_s: float) -> dict:
    """Wait for `cellctl sim`'s ready line (JSON with its addresses) in its stdout file."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise DemoError(
                f"the simulated cell exited with {proc.returncode}; see {path.with_suffix('.log')}"
            )
        with contextlib.suppress(OSError, ValueError):
            for line in path.read_text().splitlines():
                if line.startswith("{") and json.loads(line).get("ready"):
                    return json.loads(line)
        time.sleep(0.2)
    raise DemoError(f"the simulated cell was not ready within {timeout_s} s; see {path.with_suffix('.log')}")


def wait_html_report(data_dir: Path, job_id: str, timeout_s: float = 120.0) -> str | None:
    """Wait until the daemon has recorded the HTML render that follows a done job (it renders after
    storing report.json); returns report.html's path, or None if there is none within ``timeout_s``."""
    job_dir = Path(data_dir) / "jobs" / job_id
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(JobStoreError):
            info = read_job_record(job_dir).info
            if info.html_s is not None:
                return info.report_html
        time.sleep(0.2)
    return None


def wait_heating_plan(data_dir: Path, job_id: str, timeout_s: float = 120.0) -> list[str]:
    """Wait until the daemon has recorded the heating plan that follows a done job's report (and, for
    a plan, report.html rendered again with it); returns what the crew reads of it (one sentence a
    line, or why there is none), or one line saying it did not come within ``timeout_s``."""
    from analysis.forming.plan_file import read_heating_plan
    from cellctl.commands.heat_plan_cmd import plan_text

    job_dir = Path(data_dir) / "jobs" / job_id
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(JobStoreError):
            info = read_job_record(job_dir).info
            rendered = info.html_s is None or info.html_with_plan_s is not None
            if info.heating_plan_status == "no_plan" or (info.heating_plan_status == "plan" and rendered):
                try:
                    plan = read_heating_plan(info.heating_plan or job_dir)
                except ValueError as exc:
                    return [f"heating plan: {exc}"]
                return [*plan_text(plan), f"heating plan: {info.heating_plan}"]
        time.sleep(0.2)
    return [f"heating plan: none recorded within {timeout_s:.0f} s (`cellctl heat-plan {job_id}` makes it)"]


async def drive_scan(
    cfg_dict: dict[str, Any], cfg: Any, procs: Processes, timeout_s: float, *, placement: bool = True
) -> tuple[str, Report | None, str]:
    """Wait for the daemon and a worker, trigger the scan of the simulated plate, wait for its report.

    placement: send the simulated plate's true placement (False: none, the cell locates the plate).
    Returns ``(job_id, report or None, the report's path)``; raises DemoError on any failure.
    """
    from analysis.contracts.results import read_report
    from cellctl.api import ApiCallError, Keys, TriggerAccepted, call
    from cellctl.api.session import ZenohSetupError, build_zenoh_config, close_session, open_session
    from cellctl.commands.scan_cmd import StatusFollower, wait_for_job

    keys = Keys(cfg.key_prefix)
    zcfg = lambda: build_zenoh_config(cfg.zenoh, role="connect", key_prefix=cfg.key_prefix)  # noqa: E731
    session = None
    deadline = time.monotonic() + 120.0
    while session is None:  # the daemon listens once it has started; until then connecting fails
        procs.check_alive()
        try:
            session = await asyncio.to_thread(open_session, zcfg(), what="demo session")
        except ZenohSetupError as exc:
            if time.monotonic() > deadline:
                raise DemoError(f"cannot reach the daemon: {exc}") from None
            await asyncio.sleep(0.5)
    follower = StatusFollower(session, keys)
    try:
        deadline = time.monotonic() + 120.0
        while True:
            procs.check_alive()
            st = follower.latest
            if st is not None and st.state.value == "idle" and st.workers:
                break
            if time.monotonic() > deadline:
                raise DemoError("the daemon and a worker did not come up within 120 s; see the logs")
            await follower.next(0.5)
        pl = cfg.sim.placement
        req = {
            "plate_id": "demo-sail" if cfg.sim.plate.length_mm < 1200 else "sail-1200x800",
            "design": DEMO_DESIGN,
            "placement": pl.to_placement().model_dump() if placement else None,
            "note": "cellctl demo",
        }
        try:
            acc = await call(session, keys.trigger, json.dumps(req), TriggerAccepted, timeout_s=30.0)
        except ApiCallError as exc:
            raise DemoError(f"the trigger was refused: {exc}") from None
        print(f"scan triggered: job {acc.job_id}", flush=True)
        state, message, report = await wait_for_job(follower, acc.job_id, timeout_s, out=sys.stdout)
        if state != "done":
            raise DemoError(f"job {acc.job_id} ended {state}: {message}")
        if report is None:  # the publication was missed: read the stored one
            rp = Path(cfg.cell.data_dir) / "jobs" / acc.job_id / "report.json"
            report = read_report(rp) if rp.exists() else None
        return acc.job_id, report, message
    finally:
        follower.close()
        await asyncio.to_thread(close_session, session)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the whole simulated cell in one command: sim, daemon, worker, one scan, the report",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--out", required=True, help="directory for the configuration, data, logs and the report")
    p.add_argument(
        "--full", action="store_true", help="the paper's 1200 x 800 mm plate at cell.toml's settings"
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="base cell.toml (default: ./cell.toml)")
    p.add_argument("--timeout-s", type=float, default=900.0, help="give up on the scan after this")
    p.add_argument(
        "--hmi",
        action="store_true",
        help=f"also serve the HMI on http://{HMI_ADDRESS} and keep the cell running until Ctrl-C",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.design.cad import design_mesh_from_file
    from analysis.design.mesh import save_mesh
    from analysis.design.plates import design_mesh, plate_spec
    from cellctl.commands.tables import line_table

    t0 = time.monotonic()
    try:
        base = load_config(args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return EXIT_ERROR
    out = Path(args.out).resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "designs").mkdir(parents=True, exist_ok=True)
    cfg_dict = demo_config(base.model_dump(mode="json"), out, full=args.full)
    cfg_path = out / "cell.toml"
    cfg_path.write_text("# written by `cellctl demo`\n" + to_toml(cfg_dict), encoding="utf-8")
    try:
        cfg = load_config(cfg_path)
    except ConfigError as err:
        print(f"cellctl demo: error: derived configuration invalid: {err.problems}", file=sys.stderr)
        return EXIT_ERROR
    sp = cfg.sim.plate
    if sp.kind == "mesh":  # the design of the plate from a file: its mesh (a CAD design's tessellation)
        design = design_mesh_from_file(sp.design_file)
    else:
        spec = plate_spec(sp.kind, length_mm=sp.length_mm, width_mm=sp.width_mm, thickness_mm=sp.thickness_mm,
                          radius_x_mm=sp.radius_x_mm, radius_y_mm=sp.radius_y_mm)  # fmt: skip
        design = design_mesh(spec, pitch_mm=5.0)
    save_mesh(design, out / "designs" / DEMO_DESIGN)
    env = dict(os.environ)
    for env_name in {cfg.robot.rws_password_env, *cfg.sim.rws_users.values()}:
        env.setdefault(env_name, "robotics")  # ABB's published factory password of the simulated controller
    env.setdefault("PYTHONUNBUFFERED", "1")
    procs = Processes(out / "logs", cfg_path, env)
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    print(
        f"demo: {sp.length_mm:.0f} x {sp.width_mm:.0f} mm {sp.kind} plate; logs in {out / 'logs'}", flush=True
    )
    try:
        sim = procs.start("sim", "sim")
        wait_ready_line(out / "logs" / "sim.out", sim, 120.0)
        procs.start("run", "run")
        procs.start("worker", "worker")
        if args.hmi:
            start_hmi(procs, out, cfg)
        job_id, report, message = asyncio.run(drive_scan(cfg_dict, cfg, procs, args.timeout_s))
        if report is not None:
            print(line_table(report))
        print(f"report: {message}")
        html = wait_html_report(cfg.cell.data_dir, job_id)
        if report is not None:  # the line-heating plan the daemon makes after the report
            for text in wait_heating_plan(cfg.cell.data_dir, job_id):
                print(text)
        if html:
            print(f"html report: {html}")
        print(f"demo finished in {time.monotonic() - t0:.0f} s (job {job_id})", flush=True)
        if args.hmi:
            print(
                f"the cell keeps running: HMI on http://{HMI_ADDRESS}/ (Ctrl-C stops everything)", flush=True
            )
            while True:
                procs.check_alive()
                time.sleep(1.0)
        return EXIT_OK
    except DemoError as exc:
        print(f"cellctl demo: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("cellctl demo: interrupted; stopping everything", file=sys.stderr)
        return 130
    finally:
        procs.stop_all()
        signal.signal(signal.SIGTERM, previous)


def start_hmi(procs: Processes, out: Path, cfg: Any) -> None:
    """Start `cellctl hmi` on HMI_ADDRESS with one user per role (passwords made up now, printed,
    and kept in ``out/hmi-passwords.txt``, mode 600; the users file holds only their hashes)."""
    import secrets

    from cellctl.hmi.auth import ROLES, add_user

    users, lines = out / "hmi-users", []
    for role in ROLES:
        password = secrets.token_urlsafe(9)
        add_user(users, role, role, password)
        lines.append(f"{role}: {password}")
    fd = os.open(out / "hmi-passwords.txt", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write("\n".join(lines) + "\n")
    pl = cfg.sim.placement.to_placement()
    procs.start(
        "hmi", "hmi", "--users", str(users), "--listen", HMI_ADDRESS,
        "--default-placement", ",".join(str(v) for v in [*pl.pos_mm, pl.rpy_deg[2]]),
    )  # fmt: skip
    print(f"HMI: http://{HMI_ADDRESS}/  users (user: password): " + ", ".join(lines), flush=True)


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt
