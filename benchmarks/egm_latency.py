"""EGM reply latency: the simulated controller in this process, the EGM endpoint in a child process.

For ``--seconds`` (default 60) the controller sends one ``EgmRobot`` every 4.032 ms over loopback;
the endpoint answers each at once. Per cycle we measure from the controller's send of ``EgmRobot`` k
(stamped right at its ``sendto``) to the arrival of the reply with seqno k. A cycle is missed when
its reply arrived after ``EgmRobot`` k + 1 went out, or never.

Two arrival times, two sets of figures:

- headline keys ``p50_us p99_us p999_us max_us missed_cycles``: arrival is the **kernel's receive
  stamp** of the reply on the simulator's socket (``SIOCGSTAMPNS``, CLOCK_REALTIME; on loopback the
  moment the endpoint's ``sendto`` handed the datagram over). This is "controller send to reply
  receive" as a controller on its own machine would see it, and "packet in to reply out" for the
  PC plus one loopback send; the simulator's own wake-up is not in it.
- ``user_p50_us user_p99_us user_p999_us user_max_us user_missed_cycles``: arrival is when the
  simulator's event loop read the reply (user space), so its wake-up after the reply is included.

Other keys: ``cycles``, ``unanswered``, ``kernel_stamped`` (False: no kernel stamps on this OS, the
headline keys are then the user-space ones), ``tick_late_*`` (how late the simulator's cycles
started), ``sim_cpu_fraction`` / ``endpoint_cpu_fraction`` (share of one core, the endpoint's over
its whole run), ``endpoint_latency_max_us`` (the endpoint's own receive-to-send time, worst case),
``load_1min`` (the machine is shared: read the figures with it) and the settings used.

``--motion-process`` (issue 41) puts the cell's own motion process on the other side instead of a
bare endpoint: ``python -m cellctl.motion.process`` started by the daemon's
:class:`~cellctl.motion.link.MotionLink` with cell.toml's real-time settings (SCHED_FIFO at
``egm_reply_priority``, memory locked, spin), executing a scan plan (a 200 x 150 mm plate, again
and again) the whole time, so each reply carries a reference computed for its cycle. It adds
``stale_cycles`` (the motion process's own count) and ``motion_realtime``. ``--load N`` runs N busy
processes (a tight Python loop each, normal priority) for the whole measurement.

The machine's own floor is measured beside: one probe per CPU (benchmarks/platform_latency.py,
SCHED_FIFO 90, pinned) records every moment it woke more than one cycle late. ``platform`` holds
its figures and ``missed_in_platform_stalls`` how many of ``missed_cycles`` fell inside such a
stall, when no thread on this machine could have answered in time (``--no-platform-probe``: none).

Prints exactly one JSON object on stdout; logs go to stderr.

    python benchmarks/egm_latency.py [--seconds 60] [--realtime] [--cpu-latency-us 0] \\
        [--reply-thread] [--switch-interval-us 200] [--spin-us 150] [--loop-busy-ms 2]

``--realtime`` runs the simulator and the endpoint under SCHED_FIFO (needs the privilege), as a cell
PC runs its EGM process; with ``--reply-thread`` the endpoint answers from its reply thread
(``--endpoint-priority``, default 20) while its loop runs at ``--loop-priority`` (10), as the daemon
does. ``--cpu-latency-us 0`` holds the CPUs out of deep idle states (PM QoS), ``--sim-cpus`` /
``--endpoint-cpus`` pin the two sides, ``--spin-us`` lets the reply thread poll around each expected
arrival, ``--loop-busy-ms`` keeps the endpoint's loop busy in pure Python the way the daemon's loop
is during a scan, and ``--no-gc-freeze`` leaves the start-up heap to the collector.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import structlog

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.platform_latency import in_stalls, start_probes, stop_probes  # noqa: E402
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig  # noqa: E402
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig  # noqa: E402
from drivers.runtime import precise_event_loop  # noqa: E402


def _realtime(priority: int) -> bool:
    """Put this process under SCHED_FIFO; False (and a note on stderr) when not permitted."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError) as exc:
        print(f"egm_latency: SCHED_FIFO not available ({exc}); running at normal priority", file=sys.stderr)
        return False
    return True


def _freeze_heap() -> None:
    # Everything allocated at start-up (numpy, pinocchio, protobuf) moves out of the collector's
    # reach, so a full collection in the cycle walks only what the cycle allocates.
    gc.collect()
    gc.freeze()


def _quiet_logging() -> None:
    # stdout is reserved for the one JSON result; only warnings and errors, on stderr
    structlog.configure(
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
        wrapper_class=structlog.make_filtering_bound_logger(30),
    )


def _endpoint_config(args: argparse.Namespace) -> EgmEndpointConfig:
    return EgmEndpointConfig(
        host="127.0.0.1",
        port=0,
        watchdog_s=1.0,
        reply_thread=args.reply_thread,
        reply_thread_priority=args.endpoint_priority if args.realtime else 0,
        reply_thread_cpus=tuple(args.endpoint_cpus),
        switch_interval_s=None if args.switch_interval_us is None else args.switch_interval_us * 1e-6,
        reply_spin_us=args.spin_us,
    )


def _busy_loop_work(loop: asyncio.AbstractEventLoop, busy_s: float, every_s: float) -> None:
    """Stand-in for the daemon's own loop work (status, Zenoh hand-offs, profile assembly): pure
    Python that holds the loop (and the GIL) for ``busy_s`` every ``every_s``."""
    end = time.perf_counter() + busy_s
    n = 0
    while time.perf_counter() < end:
        n += sum(range(64))
    loop.call_later(every_s, _busy_loop_work, loop, busy_s, every_s)


async def _endpoint_child(args: argparse.Namespace) -> None:
    """Child process: serve the endpoint until SIGTERM; print its port on stdout first and, at the end,
    one JSON line with its statistics and the CPU time it used while serving."""
    ep = EgmEndpoint(_endpoint_config(args))
    _, port = await ep.start()
    if args.gc_freeze:
        _freeze_heap()
    print(port, flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    if args.loop_busy_ms > 0:
        loop.call_soon(_busy_loop_work, loop, args.loop_busy_ms / 1000.0, args.loop_busy_every_ms / 1000.0)
    cpu0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    await stop.wait()
    cpu1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    cpu_s = cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime
    print(json.dumps({"cpu_fraction": cpu_s / (t1 - t0), "stats": ep.stats.snapshot()}), flush=True)
    await ep.close()


def _figures(latency_us: np.ndarray, missed: np.ndarray, cycles: int, prefix: str = "") -> dict:
    ok = np.isfinite(latency_us)
    latency_us, missed = latency_us[ok], missed[ok]
    unanswered = max(0, cycles - latency_us.shape[0])
    q = np.percentile(latency_us, [50, 99, 99.9]) if latency_us.size else [float("nan")] * 3
    return {
        f"{prefix}p50_us": round(float(q[0]), 1),
        f"{prefix}p99_us": round(float(q[1]), 1),
        f"{prefix}p999_us": round(float(q[2]), 1),
        f"{prefix}max_us": round(float(latency_us.max()), 1) if latency_us.size else None,
        f"{prefix}missed_cycles": int(missed.sum()) + unanswered,
    }


async def _measure(port: int, args: argparse.Namespace, q_start_deg: tuple[float, ...] | None = None) -> dict:
    seconds, cycle_ms = args.seconds, args.cycle_ms
    extra = {} if q_start_deg is None else {"q_start_deg": tuple(q_start_deg)}
    sim = EgmControllerSim(
        EgmSimConfig(sensor_port=port, cycle_s=cycle_ms / 1000.0, comm_timeout_s=5.0, **extra)
    )
    await sim.start()
    try:
        await asyncio.sleep(args.warmup_s)  # imports, first allocations, the endpoint's first packets
        if args.gc_freeze:
            _freeze_heap()
        sent0 = sim.stats.sent
        sim.reset_reply_latency()
        late_n0 = sim._late_n
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        await asyncio.sleep(seconds)
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        # silence the controller so the last cycle's reply can land before we count
        sim.set_faults(stop_sending=True)
        cycles = sim.stats.sent - sent0
        await asyncio.sleep(0.05)
        user_us, user_missed = sim.reply_latency()
        kernel_us, kernel_missed = sim.reply_latency(kernel=True)
        sent_ns = sim.reply_sent_ns()
        late_us = sim.tick_lateness_us()[-min(sim._late_n - late_n0, 4096) :]
    finally:
        await sim.stop()
    if not sim.kernel_rx_stamps:
        print("egm_latency: no kernel receive stamps; headline figures are user space", file=sys.stderr)
        kernel_us, kernel_missed = user_us, user_missed
    # each missed cycle's window, from the EgmRobot's send to its reply's arrival (or one cycle on)
    missed = kernel_missed & np.isfinite(kernel_us)
    windows = np.stack(
        [sent_ns[missed], sent_ns[missed] + (kernel_us[missed] * 1000.0).astype(np.int64)], axis=1
    )
    return {
        "_missed_windows_ns": windows,
        **_figures(kernel_us, kernel_missed, cycles),
        "cycles": int(cycles),
        "unanswered": max(0, cycles - int(np.isfinite(kernel_us).sum())),
        "kernel_stamped": sim.kernel_rx_stamps,
        **_figures(user_us, user_missed, cycles, prefix="user_"),
        "cycle_ms": cycle_ms,
        "seconds": seconds,
        "tick_late_p99_us": round(float(np.percentile(late_us, 99)), 1) if late_us.size else None,
        "tick_late_max_us": round(float(late_us.max()), 1) if late_us.size else None,
        "sim_overruns": sim.stats.overruns,
        # the simulator sleeps between cycles: its CPU share must stay far below one core
        "sim_cpu_fraction": round(
            (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime) / seconds, 3
        ),
    }


async def _motion_process(args: argparse.Namespace) -> dict:
    """The measurement against the cell's motion process executing plans (``--motion-process``)."""
    from analysis.contracts.placement import Placement
    from analysis.design.plates import design_mesh, plate_spec
    from cellctl.config import load_config
    from cellctl.daemon.wiring import motion_settings
    from cellctl.motion import ExecutorConfig
    from cellctl.motion.link import MotionLink
    from cellctl.planning import PlannerSettings, plan_scan

    cfg = load_config(REPO / "cell.toml")
    settings = PlannerSettings.from_config(cfg).with_(
        placement_uncertainty_mm=5.0, placement_uncertainty_deg=0.5
    )
    mesh = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    plan = plan_scan(mesh, Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0), settings)
    ms = motion_settings(cfg)
    ms = dataclasses.replace(ms, endpoint=dataclasses.replace(ms.endpoint, port=0))
    link = MotionLink(ms)
    _host, port = await link.start()
    stale = 0
    try:
        measure = asyncio.create_task(_measure(port, args, tuple(plan.trajectory.q_deg[0])))
        await link.wait_for_feedback(30.0)
        runs = 0
        with tempfile.TemporaryDirectory() as tmp:
            while not measure.done():
                ex = link.execution(
                    plan.trajectory, ExecutorConfig.from_settings(settings),
                    segment_labels=[s.label for s in plan.segments], segment_kinds=[s.kind for s in plan.segments],
                    work_dir=Path(tmp),
                )  # fmt: skip
                run = asyncio.create_task(ex.run())
                await asyncio.wait({run, measure}, return_when=asyncio.FIRST_COMPLETED)
                if not run.done():
                    ex.abort()
                result = await run
                stale += ex.counters.egm_stale_cycles
                runs += 1
                if result.state.value == "faulted":
                    print(f"egm_latency: execution faulted: {result.fault}", file=sys.stderr)
                    break
        out = await measure
    finally:
        await link.close()
    out.update(stale_cycles=stale, executions=runs, motion_realtime=link.realtime.model_dump())
    return out


def _attribute(result: dict, platform: dict | None) -> None:
    """Set each missed cycle against the platform probes' stalls (benchmarks/platform_latency.py):
    ``missed_in_platform_stalls`` of ``missed_cycles`` fell where a SCHED_FIFO thread of the highest
    priority was itself held back more than one cycle, so no process could have answered in time."""
    windows = result.pop("_missed_windows_ns")
    if platform is None:
        return
    result["missed_in_platform_stalls"] = int(in_stalls(windows, platform.pop("stalls")).sum())
    result["platform"] = platform


def _pin(cpus: list[int], what: str) -> None:
    if not cpus:
        return
    try:
        os.sched_setaffinity(0, cpus)
    except OSError as exc:
        print(f"egm_latency: cannot pin the {what} to CPUs {cpus} ({exc})", file=sys.stderr)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--cycle-ms", type=float, default=4.032)
    p.add_argument("--warmup-s", type=float, default=1.0)
    p.add_argument("--realtime", action="store_true", help="SCHED_FIFO for simulator and endpoint")
    p.add_argument("--sim-priority", type=int, default=20, help="the simulator's SCHED_FIFO priority")
    p.add_argument(
        "--endpoint-priority",
        type=int,
        default=20,
        help="the endpoint's SCHED_FIFO priority (its reply thread's with --reply-thread; the process "
        "then runs its loop at --loop-priority, as the daemon does)",
    )
    p.add_argument("--loop-priority", type=int, default=10, help="endpoint loop thread with --reply-thread")
    p.add_argument("--reply-thread", action="store_true", help="serve EGM from the endpoint's reply thread")
    p.add_argument("--sim-cpus", type=int, nargs="*", default=[], help="pin the simulator to these CPUs")
    p.add_argument("--endpoint-cpus", type=int, nargs="*", default=[], help="pin the endpoint (reply thread)")
    p.add_argument("--switch-interval-us", type=float, default=None, help="sys.setswitchinterval, endpoint")
    p.add_argument("--spin-us", type=float, default=0.0, help="reply thread polls this long around arrivals")
    p.add_argument(
        "--loop-busy-ms",
        type=float,
        default=0.0,
        help="keep the endpoint's event loop busy this long (pure Python) every --loop-busy-every-ms, "
        "as the daemon's loop is with the sensor streaming and assembly running",
    )
    p.add_argument("--loop-busy-every-ms", type=float, default=20.0)
    p.add_argument(
        "--no-gc-freeze", dest="gc_freeze", action="store_false", help="leave the start-up heap to the GC"
    )
    p.add_argument(
        "--cpu-latency-us",
        type=int,
        default=None,
        help="hold the CPUs' wake-up latency at this many us (/dev/cpu_dma_latency), as `cellctl run` does",
    )
    p.add_argument("--endpoint-child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--motion-process", action="store_true", help="the cell's motion process, executing plans")
    p.add_argument("--load", type=int, default=0, help="N busy processes for the whole measurement")
    p.add_argument(
        "--no-platform-probe",
        dest="platform_probe",
        action="store_false",
        help="without the probes of the machine's own wake-up latency (benchmarks/platform_latency.py)",
    )
    args = p.parse_args()
    _quiet_logging()
    busy = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)
        for _ in range(0 if args.endpoint_child else args.load)
    ]
    try:
        return _main(args)
    finally:
        for b in busy:
            b.kill()
            b.wait()


def _main(args: argparse.Namespace) -> int:
    if args.endpoint_child:
        if args.realtime:
            # with a reply thread the loop runs below it (the thread asks for its own priority)
            _realtime(args.loop_priority if args.reply_thread else args.endpoint_priority)
        if not args.reply_thread:
            _pin(args.endpoint_cpus, "endpoint")
        asyncio.run(_endpoint_child(args))
        return 0
    realtime = _realtime(args.sim_priority) if args.realtime else False
    held = False
    if args.cpu_latency_us is not None:
        from drivers.runtime import hold_cpu_wakeup_latency

        held = hold_cpu_wakeup_latency(args.cpu_latency_us)
    if args.motion_process:
        probes = start_probes(cycle_ms=args.cycle_ms) if args.platform_probe else []
        try:
            with asyncio.Runner(loop_factory=precise_event_loop) as runner:
                result = runner.run(_motion_process(args))
        finally:
            platform = stop_probes(probes) if probes else None
        _attribute(result, platform)
        result.update(realtime=realtime, cpu_latency_held=held, load=args.load, load_1min=os.getloadavg()[0])
        print(json.dumps(result))
        return 0
    child_argv = [a for a in sys.argv[1:] if a != "--realtime"] + (["--realtime"] if realtime else [])
    child = subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), "--endpoint-child", *child_argv],
        stdout=subprocess.PIPE,
        text=True,
    )
    endpoint: dict = {}
    probes: list = []
    platform = None
    try:
        port = int(child.stdout.readline())
        _pin(args.sim_cpus, "simulator")
        probes = start_probes(cycle_ms=args.cycle_ms) if args.platform_probe else []
        try:
            with asyncio.Runner(loop_factory=precise_event_loop) as runner:
                result = runner.run(_measure(port, args))
        finally:
            platform = stop_probes(probes) if probes else None
    finally:
        child.send_signal(signal.SIGTERM)
        try:
            out, _ = child.communicate(timeout=10)
            endpoint = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    if "cpu_fraction" in endpoint:
        # CPU share of the whole endpoint process while it served (warm-up included): one core = 1.0
        result["endpoint_cpu_fraction"] = round(endpoint["cpu_fraction"], 3)
        result["endpoint_latency_max_us"] = round(endpoint["stats"]["latency_max_us"], 1)
    _attribute(result, platform)
    result["realtime"] = realtime
    result["reply_thread"] = args.reply_thread
    result["loop_busy_ms"] = args.loop_busy_ms
    result["spin_us"] = args.spin_us
    result["switch_interval_us"] = args.switch_interval_us
    result["cpu_latency_held"] = held
    result["load"] = args.load
    result["load_1min"] = os.getloadavg()[0]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
