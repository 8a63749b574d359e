"""Scan planning benchmark: the 1200 x 800 sail plate, and a 6000 x 2000 plate on the long-plate cell.

For the sail plate at the cell.toml default placement (1500, 0, 300 mm, 3 deg) with the cell.toml
scan settings (HD8: 50 mm line, 200 Hz, 0.5 mm profile spacing -> 100 mm/s): planning time
(surface fit, passes, joint path, timing, envelope check, ray-cast coverage), planned scan time,
the ratio of scan time to pure sweep time (sweep length / scan speed; target <= 1.2) and the
predicted coverage of the top surface (target >= 0.99), and the planned scan time in parts:
``approach_s``, ``sweep_s`` (on the passes, ramps included), ``transitions_s`` (the links and
turnarounds between passes, issue 22) and ``retract_s``, with the longest single transition
``transition_max_s``. Planning is repeated ``--repeat`` times and the median reported. These plans
start at the footprint's default corner; ``from_home_corner`` is the plan the daemon makes from the
simulated arm's start (``[sim] egm_q_start_deg``, the end-to-end benchmark's): the passes started at
the plate's corner nearest the arm (``start_corner``, ``scan_time_s``, ``sweep_s``, ``transitions_s``).

``large``: the 6000 x 2000 plate (a gentle sail, radii 20 / 10 m) on the long-plate cell
(``--large-config``, default docs/examples/cell-track.toml: the robot on a riser on a 7 m track, the
plate's long side along the rail, docs/robot-setup.md "The long-plate cell") at that cell's
``[sim.placement]``: the outcome (planned or refused, with the reason), ``scan_time_s``,
``sweep_time_s``, ``sweep_ratio`` (target <= 1.2), ``passes``, the planner's ``choices`` (track hold
or follow, edge tilts lowered, edge order), the stages' times and ``decide_s`` (how long planning
took, coverage included; ``decide_cpu_s`` its CPU time, ``time.process_time``, open3d's ray-casting
threads included), ``daemon_plan_s`` / ``daemon_plan_cpu_s`` (the plan the daemon makes: without
the coverage prediction), ``cache`` (the plan cache's entry of that plan: ``write_s``, ``read_s``
(the entry parsed and its header validated), ``hit_s`` (a hit: read and the envelope check),
``bytes``, ``loop_block_ms``: the longest an asyncio loop ticking every 1 ms was held up while the
entry was stored / read / a hit was read and checked (the envelope check of its 431 k EGM samples
included) in a worker thread, as the daemon does, and ``idle`` while that thread only slept: the
machine's own delay) and ``load_avg``
(the 1-minute load average before and after the large plan: the figures are under it).

``choices``: the planner's (for the sail: the axis its passes run along, ``pass_axis``, with each
axis' lower bound, estimate and time, or why it was not solved).

``--track``: the sail with the robot on a 6 m linear track along +y, its base at the middle of the
travel where the rail-less base is (the plate within the fixed arm's reach: the carriage holds and
the plan is the rail-less one); a ``[robot.track]`` in the ``--config`` file does the same with that
track. The output's ``track`` names the track used (null: none) and the planner's choice.

Usage: ``python benchmarks/plan.py [--repeat 3] [--config cell.toml] [--track] [--large-config F]``.
Prints one JSON object; logs go to stderr.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import structlog

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def _loop_block_ms(work) -> float:
    """The longest an asyncio loop went without running (ms, beyond its 1 ms tick) while ``work()``
    ran in a worker thread, as the daemon runs the plan cache (``asyncio.to_thread``)."""
    import asyncio

    async def run() -> float:
        worst = 0.0
        done = asyncio.Event()

        async def tick() -> None:
            nonlocal worst
            last = time.perf_counter()
            while not done.is_set():
                await asyncio.sleep(0.001)
                now = time.perf_counter()
                worst = max(worst, now - last - 0.001)
                last = now

        ticker = asyncio.create_task(tick())
        await asyncio.sleep(0.01)
        await asyncio.to_thread(work)
        done.set()
        await ticker
        return worst * 1e3

    return asyncio.run(run())


def _daemon_and_cache(design, placement, settings) -> dict:
    """The daemon's plan of ``design`` (no coverage prediction) and its plan cache entry's costs."""
    import tempfile

    from cellctl.planning import plan_scan
    from cellctl.planning.cache import EntryHeader, PlanCache, _read_entry, plan_from_arrays, plan_key

    t0, c0 = time.perf_counter(), time.process_time()
    plan = plan_scan(design, placement, settings, with_coverage=False)
    out = {
        "daemon_plan_s": round(time.perf_counter() - t0, 3),
        "daemon_plan_cpu_s": round(time.process_time() - c0, 3),
    }
    with tempfile.TemporaryDirectory() as tmp:
        cache = PlanCache(tmp)
        key = plan_key(design, placement, settings, with_coverage=False, cycle_s=0.004032)
        t0 = time.perf_counter()
        cache.store(key, plan)
        write_s = time.perf_counter() - t0
        data = cache.path(key).read_bytes()
        t0 = time.perf_counter()
        header, arrays = _read_entry(data)
        plan_from_arrays(EntryHeader.model_validate(header).plan, arrays)
        read_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        hit = cache.load(key, placement, settings)
        hit_s = time.perf_counter() - t0
        # the daemon's loop beside the cache's work in its thread: the longest it was held up
        store_block_ms = _loop_block_ms(lambda: cache.store(key, plan))
        hit_block_ms = _loop_block_ms(lambda: cache.load(key, placement, settings))
        read_block_ms = _loop_block_ms(lambda: _read_entry(cache.path(key).read_bytes()))
        idle_block_ms = _loop_block_ms(lambda: time.sleep(0.5))  # the machine's own scheduling delay
    out["cache"] = {
        "write_s": round(write_s, 3), "read_s": round(read_s, 3), "hit_s": round(hit_s, 3),
        "bytes": len(data), "hit": hit is not None,
        "loop_block_ms": {
            "store": round(store_block_ms, 1), "read": round(read_block_ms, 1), "hit": round(hit_block_ms, 1),
            "idle": round(idle_block_ms, 1),
        },
    }  # fmt: skip
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=3, help="planning runs of the sail plate (median reported)")
    p.add_argument("--config", default=str(REPO / "cell.toml"), help="cell.toml with the scan settings")
    p.add_argument("--track", action="store_true", help="plan with a 6 m track along +y (base at mid-travel)")
    p.add_argument(
        "--large-config",
        default=str(REPO / "docs" / "examples" / "cell-track.toml"),
        help="the long-plate cell the 6000 x 2000 plate is planned on",
    )
    args = p.parse_args()
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING),
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
    )

    from analysis.design.plates import design_mesh, plate_spec
    from cellctl.config import load_config
    from cellctl.planning import PlannerSettings, PlanRefused, plan_scan, start_corner_near

    cfg = load_config(args.config)
    settings = PlannerSettings.from_config(cfg)
    if args.track:
        from drivers.abb_egm.limits import LinearTrack

        settings = settings.with_(
            track=LinearTrack(
                origin_mm=[0.0, -3000.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=10.0,
                travel_max_mm=5990.0, speed_max_mm_s=1000.0, accel_max_mm_s2=2000.0, jerk_max_mm_s3=20000.0,
            )
        )  # fmt: skip
    placement = cfg.sim.placement.to_placement()
    sail = design_mesh(plate_spec("sail"), pitch_mm=10.0)

    runs = []
    plan = None
    for _ in range(max(1, args.repeat)):
        t0 = time.perf_counter()
        plan = plan_scan(sail, placement, settings)
        runs.append(time.perf_counter() - t0)
    assert plan is not None
    s = plan.summary()
    # the daemon starts the passes at the corner nearest the arm: from the simulated arm's start
    # ([sim] egm_q_start_deg, the end-to-end benchmark's), the plan it makes
    q_home = np.asarray(cfg.sim.egm_q_start_deg, dtype=np.float64)
    if settings.track is not None:
        q_home = np.concatenate([[cfg.sim.egm_track_start_mm], q_home])
    corner = start_corner_near(sail, placement, settings, q_home)
    from_home = plan_scan(sail, placement, settings.with_(start_corner=corner), with_coverage=False)

    large_cfg = load_config(args.large_config)
    large_settings = PlannerSettings.from_config(large_cfg)
    large = design_mesh(
        plate_spec("sail", length_mm=6000.0, width_mm=2000.0, radius_x_mm=20000.0, radius_y_mm=10000.0),
        pitch_mm=25.0,
    )
    # the long side (the design's x) along the rail, as the cell lays it
    large_placement = large_cfg.sim.placement.to_placement()
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        big = plan_scan(large, large_placement, large_settings)
        decide_s, decide_cpu_s = time.perf_counter() - t0, time.process_time() - c0
        large_out = {
            "outcome": "planned",
            "scan_time_s": round(big.scan_time_s, 2),
            "sweep_time_s": round(big.sweep_time_s, 2),
            "sweep_ratio": round(big.sweep_ratio, 4),
            "passes": big.summary()["passes"],
            "edge_passes": big.summary()["edge_passes"],
            "coverage": round(big.coverage.fraction, 5),
            "choices": big.choices,
            "track_range_mm": round(float(np.ptp(big.trajectory.q_deg[:, 0])), 1),
            "stages_s": {k: round(v, 3) for k, v in big.timings_s.items()},
        }
        large_out.update(_daemon_and_cache(large, large_placement, large_settings))
    except PlanRefused as exc:
        decide_s, decide_cpu_s = time.perf_counter() - t0, time.process_time() - c0
        large_out = {"outcome": "refused", **{k: v for k, v in exc.to_dict().items() if k != "message"}}
    large_out["decide_s"] = round(decide_s, 3)
    large_out["decide_cpu_s"] = round(decide_cpu_s, 3)
    large_out["load_avg"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    large_out["plate"] = "sail 6000 x 2000"
    large_out["config"] = os.path.relpath(Path(args.large_config).resolve(), REPO)
    large_out["placement"] = large_placement.model_dump()

    result = {
        "plate": "sail 1200 x 800 x 15",
        "placement": placement.__dict__,
        "plan_s": round(statistics.median(runs), 3),
        "plan_runs_s": [round(r, 3) for r in runs],
        "scan_time_s": round(plan.scan_time_s, 2),
        "sweep_time_s": round(plan.sweep_time_s, 2),
        "sweep_ratio": round(plan.sweep_ratio, 4),
        # the planned scan time in parts: approach + passes + transitions between them + retract
        **{k: s[k] for k in ("approach_s", "sweep_s", "transitions_s", "retract_s")},
        "transition_max_s": max(t["transition_s"] for t in s["pass_times"]),
        "coverage": round(plan.coverage.fraction, 5),
        "coverage_worst_over_uncertainty": round(plan.coverage.worst_fraction, 5),
        "scan_speed_mm_s": plan.scan_speed_mm_s,
        "scan_speed_deviation": round(plan.scan_speed_deviation, 5),
        "toppra_time_optimal_s": round(plan.toppra_time_s, 2),
        "passes": s["passes"],
        "edge_passes": s["edge_passes"],
        "stages_s": {k: round(v, 3) for k, v in plan.timings_s.items()},
        "choices": plan.choices,
        "from_home_corner": {
            "start_corner": list(corner),
            "scan_time_s": round(from_home.scan_time_s, 2),
            **{k: from_home.summary()[k] for k in ("sweep_s", "transitions_s")},
        },
        "large": large_out,
        "track": None
        if settings.track is None
        else {
            "origin_mm": settings.track.origin_mm.tolist(),
            "direction": settings.track.direction.tolist(),
            "travel_mm": [settings.track.travel_min_mm, settings.track.travel_max_mm],
            "range_used_mm": round(float(np.ptp(plan.trajectory.q_deg[:, 0])), 1),
            "choice": plan.choices.get("track"),
        },
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
