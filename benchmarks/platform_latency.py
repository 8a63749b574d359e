"""The machine's own wake-up latency: how late a SCHED_FIFO thread that does nothing else wakes.

This is the floor under every real-time figure of the cell (issue 41): the motion process cannot
answer the controller sooner than the OS and the hypervisor let it run. One probe process per CPU
(pinned, SCHED_FIFO at ``--priority``, memory locked, collector off) sleeps to an absolute deadline
every ``--period-us`` (1000) and records how late it woke, in the way ``cyclictest`` does. A wake-up
later than one EGM cycle (``--cycle-ms``, 4.032) is a **stall**: a thread of the highest priority
could not have answered the controller in time then, whatever it was.

Prints one JSON object: per CPU and together, ``wakeups``, ``late_p50_us``, ``late_p99_us``,
``late_max_us`` and ``over_cycle`` (stalls), with ``sched_fifo`` (False: the OS refused the priority
and the figures are those of a normal thread).

    python benchmarks/platform_latency.py [--seconds 60] [--cpus 0 1] [--priority 90]

``egm_latency.py --motion-process`` and ``end_to_end.py`` run these probes beside their
measurement (:func:`start_probes` / :func:`stop_probes`) and set each stale cycle against the
stalls the probes saw at the same moment (:func:`in_stalls`).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_BIN_US = 10  # histogram bins of 10 us up to 20 ms, then one overflow bin
_NBINS = 2000


def _probe(cpu: int | None, priority: int, period_ns: int, cycle_ns: int, seconds: float | None) -> dict:
    """The probe loop (one process, one CPU). Returns its figures and the stalls' windows."""
    fifo = False
    refused = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, [cpu])
        except OSError as exc:
            refused.append(f"affinity: {exc}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        fifo = True
    except (OSError, AttributeError) as exc:
        refused.append(f"SCHED_FIFO: {exc}")
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
            refused.append(f"mlockall: errno {ctypes.get_errno()}")
    except OSError as exc:
        refused.append(f"mlockall: {exc}")
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    counts = [0] * (_NBINS + 1)
    stalls: list[tuple[int, int]] = []  # (deadline, woke) monotonic ns
    max_late = 0
    gc.collect()
    gc.disable()
    mono = time.monotonic_ns
    t_end = None if seconds is None else mono() + int(seconds * 1e9)
    t_start = mono()
    deadline = t_start + period_ns
    n = 0
    while not stop:
        d = deadline - mono()
        if d > 0:
            time.sleep(d / 1e9)
        now = mono()
        late = now - deadline
        if late > max_late:
            max_late = late
        b = late // (_BIN_US * 1000)
        counts[b if b < _NBINS else _NBINS] += 1
        if late > cycle_ns:
            stalls.append((deadline, now))
        n += 1
        deadline += period_ns
        if deadline <= now:  # a stall: the next deadline is the first one still ahead
            deadline += ((now - deadline) // period_ns + 1) * period_ns
        if t_end is not None and now >= t_end:
            break
    gc.enable()
    return {
        "cpu": cpu,
        "sched_fifo": fifo,
        "refused": "; ".join(refused),
        "wakeups": n,
        "seconds": (mono() - t_start) / 1e9,
        "counts": counts,
        "max_late_us": max_late / 1000.0,
        "stalls_ns": stalls,
    }


def _figures(counts: np.ndarray, max_late_us: float, over_cycle: int) -> dict:
    n = int(counts.sum())
    edges = np.arange(counts.shape[0]) * _BIN_US

    def pct(p: float) -> float | None:
        if n == 0:
            return None
        i = int(np.searchsorted(np.cumsum(counts), p / 100.0 * n))
        return float(edges[min(i, len(edges) - 1)] + _BIN_US)  # the bin's upper edge

    return {
        "wakeups": n,
        "late_p50_us": pct(50),
        "late_p99_us": pct(99),
        "late_p999_us": pct(99.9),
        "late_max_us": round(max_late_us, 1),
        "over_cycle": over_cycle,
    }


def start_probes(
    cpus: list[int] | None = None, *, priority: int = 90, period_us: int = 1000, cycle_ms: float = 4.032
) -> list[subprocess.Popen]:
    """One probe process per CPU (default: every CPU this process may run on), running until
    :func:`stop_probes`."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    argv = [sys.executable, str(Path(__file__).resolve()), "--raw", "--priority", str(priority)]
    argv += ["--period-us", str(period_us), "--cycle-ms", str(cycle_ms)]
    return [
        subprocess.Popen(
            [*argv, "--cpus", str(c)], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True
        )
        for c in cpus
    ]


def stop_probes(procs: list[subprocess.Popen], timeout_s: float = 10.0) -> dict:
    """Stop the probes and gather their figures: ``{"per_cpu": [...], **together}`` plus
    ``stalls`` (sorted [deadline_ns, woke_ns] windows on the monotonic clock, every CPU)."""
    raws = []
    for p in procs:
        p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            out, _ = p.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            out, _ = p.communicate()
        if out.strip():
            raws.append(json.loads(out.strip().splitlines()[-1]))
    return summarise(raws)


def summarise(raws: list[dict]) -> dict:
    per_cpu, stalls = [], []
    total = np.zeros(_NBINS + 1, dtype=np.int64)
    for r in raws:
        c = np.asarray(r["counts"], dtype=np.int64)
        total += c
        stalls += r["stalls_ns"]
        per_cpu.append(
            {
                "cpu": r["cpu"],
                "sched_fifo": r["sched_fifo"],
                "refused": r["refused"],
                "seconds": round(r["seconds"], 3),
            }
            | _figures(c, r["max_late_us"], len(r["stalls_ns"]))
        )
    together = _figures(
        total, max((r["max_late_us"] for r in raws), default=0.0), sum(p["over_cycle"] for p in per_cpu)
    )
    return {**together, "per_cpu": per_cpu, "stalls": sorted(stalls)}


def in_stalls(windows_ns: np.ndarray, stalls_ns: list) -> np.ndarray:
    """For each (start, end) window (monotonic ns), whether a probe's stall overlaps it: the machine
    held a thread of the highest priority back at that moment."""
    windows_ns = np.asarray(windows_ns, dtype=np.int64).reshape(-1, 2)
    if not stalls_ns or windows_ns.shape[0] == 0:
        return np.zeros(windows_ns.shape[0], dtype=bool)
    s = np.asarray(stalls_ns, dtype=np.int64).reshape(-1, 2)
    s = s[np.argsort(s[:, 0])]
    # a stall [a, b] overlaps [w0, w1] when a <= w1 and b >= w0: among the stalls starting at or
    # before w1, does the longest-reaching end reach w0?
    reach = np.maximum.accumulate(s[:, 1])
    i = np.searchsorted(s[:, 0], windows_ns[:, 1], side="right") - 1
    return (i >= 0) & (reach[np.maximum(i, 0)] >= windows_ns[:, 0])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--cpus", type=int, nargs="*", default=None, help="default: every CPU allowed")
    p.add_argument("--priority", type=int, default=90)
    p.add_argument("--period-us", type=int, default=1000)
    p.add_argument("--cycle-ms", type=float, default=4.032)
    p.add_argument("--raw", action="store_true", help=argparse.SUPPRESS)  # one probe until SIGTERM
    args = p.parse_args()
    period_ns, cycle_ns = args.period_us * 1000, int(args.cycle_ms * 1e6)
    if args.raw:
        cpu = args.cpus[0] if args.cpus else None
        print(json.dumps(_probe(cpu, args.priority, period_ns, cycle_ns, None)), flush=True)
        return 0
    procs = start_probes(args.cpus, priority=args.priority, period_us=args.period_us, cycle_ms=args.cycle_ms)
    try:
        time.sleep(args.seconds)
    finally:
        result = stop_probes(procs)
    result.pop("stalls")
    result.update(
        seconds=args.seconds, period_us=args.period_us, cycle_ms=args.cycle_ms, load_1min=os.getloadavg()[0]
    )
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
