"""EGM reply latency: the simulated controller in this process, the EGM endpoint in a child process.

For ``--seconds`` (default 60) the controller sends one ``EgmRobot`` every 4.032 ms over loopback;
the endpoint answers each at once. Per cycle we measure the time from the controller's send to the
arrival of the matching reply (reply seqno k answers robot seqno k). A cycle is missed when its reply
arrived after the next ``EgmRobot`` went out, or never.

Prints exactly one JSON object on stdout:
``{"p50_us", "p99_us", "p999_us", "max_us", "cycles", "missed_cycles", ...}``; logs go to stderr.

    python benchmarks/egm_latency.py [--seconds 60] [--cycle-ms 4.032] [--realtime]

``--realtime`` runs both processes under SCHED_FIFO (needs the privilege), as a cell PC would run
its EGM process; without it the figures include whatever else the machine is doing.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import structlog

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig  # noqa: E402
from drivers.abb_egm.sim_egm import EgmControllerSim, EgmSimConfig, precise_event_loop  # noqa: E402


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


async def _endpoint_child() -> None:
    """Child process: serve the endpoint until SIGTERM, print its port on stdout first."""
    ep = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0, watchdog_s=1.0))
    _, port = await ep.start()
    _freeze_heap()
    print(port, flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    print(json.dumps(ep.stats.snapshot()), file=sys.stderr, flush=True)
    await ep.close()


async def _measure(port: int, seconds: float, cycle_ms: float, warmup_s: float) -> dict:
    sim = EgmControllerSim(EgmSimConfig(sensor_port=port, cycle_s=cycle_ms / 1000.0, comm_timeout_s=5.0))
    await sim.start()
    try:
        await asyncio.sleep(warmup_s)  # imports, first allocations, the endpoint's first packets
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
        latency_us, missed = sim.reply_latency()
        late_us = sim.tick_lateness_us()[-min(sim._late_n - late_n0, 4096) :]
    finally:
        await sim.stop()
    unanswered = max(0, cycles - latency_us.shape[0])
    q = np.percentile(latency_us, [50, 99, 99.9]) if latency_us.size else [float("nan")] * 3
    return {
        "p50_us": round(float(q[0]), 1),
        "p99_us": round(float(q[1]), 1),
        "p999_us": round(float(q[2]), 1),
        "max_us": round(float(latency_us.max()), 1) if latency_us.size else None,
        "cycles": int(cycles),
        "missed_cycles": int(missed.sum()) + unanswered,
        "late_replies": int(missed.sum()),
        "unanswered": unanswered,
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


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--cycle-ms", type=float, default=4.032)
    p.add_argument("--warmup-s", type=float, default=1.0)
    p.add_argument("--realtime", action="store_true", help="SCHED_FIFO for simulator and endpoint")
    p.add_argument(
        "--cpu-latency-us",
        type=int,
        default=None,
        help="hold the CPUs' wake-up latency at this many us (/dev/cpu_dma_latency), as `cellctl run` does",
    )
    p.add_argument("--endpoint-child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    _quiet_logging()
    realtime = _realtime(20) if args.realtime else False
    held = False
    if args.cpu_latency_us is not None and not args.endpoint_child:
        from cellctl.daemon.service import hold_cpu_wakeup_latency

        held = hold_cpu_wakeup_latency(args.cpu_latency_us)
    if args.endpoint_child:
        asyncio.run(_endpoint_child())
        return 0
    child = subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), "--endpoint-child"]
        + (["--realtime"] if realtime else []),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        port = int(child.stdout.readline())
        with asyncio.Runner(loop_factory=precise_event_loop) as runner:
            result = runner.run(_measure(port, args.seconds, args.cycle_ms, args.warmup_s))
    finally:
        child.send_signal(signal.SIGTERM)
        try:
            child.wait(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
    result["realtime"] = realtime
    result["cpu_latency_held"] = held
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
