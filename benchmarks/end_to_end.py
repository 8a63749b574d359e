"""End-to-end benchmark: the simulated 1200 x 800 mm sail plate with the HD8 settings of cell.toml.

Starts `cellctl sim`, `cellctl run` and `cellctl worker` as separate processes (loopback ports, data
in a temporary directory), triggers one scan over Zenoh and waits for the report. Reports:

* ``scan_s``: the daemon's execution of the plan (first to last reference, approach to retract);
* ``report_after_last_profile_s``: from the last profile of the scan to the report stored with the job;
* ``total_s``: from the trigger to the report stored;
* ``html_after_last_profile_s``: from the last profile to report.html / .pdf written (the render
  follows the stored JSON report and does not delay it);
* ``daemon_peak_mb`` / ``worker_peak_mb``: peak resident memory (VmHWM) of the daemon and of the
  worker with its analysis child process;
* ``overhead_ratio``: ``total_s`` / the pure sweep time (the plan's sweep length at the scan speed,
  ``sweep_time_s``): 1.0 would be a cell that only sweeps;
* ``transitions_s``: the plan's time on the links and turnarounds between passes;
* ``startup_s``: from the trigger (the job accepted) to the scan's start (design, plan, sensor and
  EGM bring-up); ``execution_beyond_plan_s``: ``scan_s`` minus the planned scan time, of which
  ``move_to_start_s`` is the move to the plan's start; ``processes_up_s``: the processes' start-up
  before the trigger (the service runs for months: not part of a job, so not in ``total_s``;
  ``total_with_processes_s`` adds it, the figure the runs before the seventh issue-22 session
  quoted as ``total_s``); ``trigger_to_report_s``: the same as ``total_s`` (kept for old scripts);
* plus the plan's figures, profile and point counts and the analysis timings;
* issue 41, how the motion process served the controller during the scan (job.json ``info.motion``):
  ``egm_stale_cycles`` (replies computed for another cycle than the one they answer, or sent more
  than a cycle after the packet arrived), ``egm_lost_cycles`` (controller cycles with no packet),
  ``egm_reply_p50_us`` / ``egm_reply_p99_us`` / ``egm_reply_max_us`` (packet arrival to reply, 10 us
  bins), ``max_tracking_error_mm``, and ``motion_realtime`` (what the OS granted the motion process);
  ``accuracy_rms_mm``: the cloud's RMS distance to the simulator's true plate surface (points at
  least 10 mm inside its edges), the figure a late reference would spoil; ``platform_over_cycle``
  and ``platform``: the machine's own floor over the same run, how often a pinned SCHED_FIFO probe
  of the highest priority woke more than one EGM cycle late (benchmarks/platform_latency.py): on a
  shared VM the hypervisor's stalls, when no process could have answered in time;
  ``egm_stale_in_platform_stalls``: how many of ``egm_stale_cycles`` fell inside such a stall (the
  scan's record, raw/motion-record.npz ``stale_ns``, against the probes' stalls).

``--load N`` runs N busy processes (a tight Python loop each, normal priority) beside the cell from
before the trigger to the report; ``--worker-busy`` runs, beside the cell's own worker, an analysis
as large as the worker's (``cellctl inspect`` of a synthetic 1200 x 800 mm scan at 0.5 mm, 1.4 M
points, again and again): the load of a worker still analysing the previous plate on the cell PC.

Targets (issue 8): report <= 15 s after the last profile, total <= 4.5 min. Issue 22's: total <=
1.1 x sweep + 5 s, report <= 3 s after the last profile.

``--plate long`` (issue 20): the 6000 x 2000 mm plate on the long cell (``--config``, default
``docs/examples/cell-track.toml``: the robot on a riser on its 7 m track), triggered WITHOUT a placement: the cell locates
the plate first (docs/locate.md). Adds ``locate_s``, ``placement_found`` and its error from the
simulated truth, ``scan_ratio`` (``scan_s`` / ``sweep_time_s``; issue 20's target <= 1.2) and
``plan_choices`` (the carriage's mode with a track). ``--length-mm`` / ``--width-mm`` run another plate on that cell (stated in the
JSON as ``plate_mm``); ``--no-placement`` locates on any plate.
Usage: ``python benchmarks/end_to_end.py [--plate demo|sail|long] [--small] [--keep DIR]``;
``--small`` (= ``--plate demo``) runs the demo's 600 x 400 mm plate instead. Prints one JSON object;
the processes' logs stay in the work directory.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def _peak_mb(pid: int) -> float:
    """VmHWM of a live process and its children (the worker's analysis child), MB."""
    total = 0.0
    pids = [pid]
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        pids += [int(c) for c in children]
    except OSError:
        pass
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    total += int(line.split()[1]) / 1024.0
        except OSError:
            continue
    return round(total, 1)


def _busy_processes(n: int, worker_busy: bool, work: Path, env: dict) -> list[subprocess.Popen]:
    """``n`` busy loops and, with ``worker_busy``, a large analysis in a loop (see the docstring)."""
    procs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)
        for _ in range(n)
    ]
    if worker_busy:
        big = work / "busy"
        cellctl = [sys.executable, "-m", "cellctl"]
        subprocess.run(
            [*cellctl, "synth", "--plate", "sail", "--out", str(big / "scan.ply"), "--profile-step-mm", "0.5"],
            check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        loop = (
            f"while true; do {' '.join(cellctl)} inspect {big}/scan.ply --design {big}/scan-design.ply "
            f"--out {big}/out >/dev/null 2>&1; done"
        )
        procs.append(
            subprocess.Popen(["bash", "-c", loop], env=env, stdin=subprocess.DEVNULL, start_new_session=True)
        )
    return procs


def _motion_realtime(log_path: Path) -> dict | None:
    """What the OS granted the motion process, from the daemon's log (``motion_process_started``)."""
    try:
        for line in log_path.read_text().splitlines():
            if '"motion_process_started"' in line:
                ev = json.loads(line)
                return {k: ev.get(k) for k in ("priority", "sched_fifo", "cpus", "memory_locked", "refused")}
    except (OSError, ValueError):
        pass
    return None


def _stale_in_stalls(data_dir: Path, job_id: str, platform: dict | None) -> int | None:
    """How many of the scan's stale cycles (raw/motion-record.npz ``stale_ns``) fell inside a stall
    of the platform probes: when a SCHED_FIFO thread of the highest priority was itself held back
    more than one cycle, so no process on this machine could have answered in time."""
    import numpy as np

    from benchmarks.platform_latency import in_stalls

    record = data_dir / "jobs" / job_id / "raw" / "motion-record.npz"
    if platform is None or not record.is_file():
        return None
    with np.load(record) as z:
        if "stale_ns" not in z.files:
            return None
        stale = z["stale_ns"]
    windows = np.stack([stale[:, 0] - stale[:, 1], stale[:, 0]], axis=1)
    return int(in_stalls(windows, platform["stalls"]).sum())


def _accuracy_rms_mm(data_dir: Path, job_id: str) -> float | None:
    """RMS distance of the job's cloud (cloud.bin, base frame) to the simulator's true top surface,
    over the points at least 10 mm inside the plate's edges."""
    import numpy as np

    from analysis.design.plates import FormingError, PlateSpec
    from cellctl.api.cloud_codec import decode_cloud
    from cellctl.simcell.truth import PlateTruth

    truth_path, cloud_path = data_dir / "sim-truth.json", data_dir / "jobs" / job_id / "cloud.bin"
    if not truth_path.is_file() or not cloud_path.is_file():
        return None
    t = json.loads(truth_path.read_text())
    truth = PlateTruth(
        spec=PlateSpec(**t["plate"]),
        error=None if t["forming_error"] is None else FormingError.from_dict(t["forming_error"]),
        T_base_plate=np.asarray(t["T_base_plate"], dtype=np.float64),
    )
    xyz = decode_cloud(cloud_path.read_bytes()).xyz_mm.astype(np.float64)
    d, inside = truth.distance_mm(xyz, edge_margin_mm=10.0)
    # the bed and supports the sensor also sees lie far below the plate's top: not the plate's points
    keep = inside & (np.abs(d) < 5.0)
    return round(float(np.sqrt(np.mean(d[keep] ** 2))), 4) if keep.any() else None


def _utc_s(stamp: str) -> float:
    """A job history time stamp (ISO 8601, Z) as Unix seconds."""
    from datetime import datetime

    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def main() -> int:
    from analysis.design.mesh import save_mesh
    from analysis.design.plates import design_mesh, plate_spec
    from benchmarks.platform_latency import start_probes, stop_probes
    from cellctl.commands.demo_cmd import (
        DEMO_DESIGN,
        Processes,
        demo_config,
        drive_scan,
        to_toml,
        wait_html_report,
        wait_ready_line,
    )
    from cellctl.config import load_config

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--small", action="store_true", help="the demo's 600 x 400 mm plate instead of the full one"
    )
    p.add_argument("--plate", choices=["demo", "sail", "long"], default=None,
                   help="demo 600 x 400, sail 1200 x 800 (default), long 6000 x 2000 on the long cell")  # fmt: skip
    p.add_argument("--length-mm", type=float, default=None, help="with --plate long: another plate length")
    p.add_argument("--width-mm", type=float, default=None, help="with --plate long: another plate width")
    p.add_argument(
        "--no-placement", action="store_true", help="trigger without a placement (the cell locates)"
    )
    p.add_argument(
        "--given-placement",
        action="store_true",
        help="with --plate long: trigger with the true placement (no locate)",
    )
    p.add_argument("--keep", default=None, help="work directory to keep (default: a temporary one)")
    p.add_argument(
        "--config",
        default=None,
        help="base cell.toml (default: cell.toml; long: docs/examples/cell-track.toml)",
    )
    p.add_argument(
        "--timeout-s", type=float, default=None, help="give up after this (default 3600; long 7200)"
    )
    p.add_argument("--load", type=int, default=0, help="N busy processes beside the cell")
    p.add_argument(
        "--protocol", choices=["hd8", "gige"], default=None,
        help="the sensor's protocol ([laser] protocol; gige: the simulator serves a GigE Vision device)",
    )  # fmt: skip
    p.add_argument("--worker-busy", action="store_true", help="a large analysis running beside the scan")
    args = p.parse_args()
    plate = args.plate or ("demo" if args.small else "sail")
    long_plate = plate == "long"
    config = args.config or str(REPO / ("docs/examples/cell-track.toml" if long_plate else "cell.toml"))
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="cellctl-e2e-bench-"))
    (work / "logs").mkdir(parents=True, exist_ok=True)
    (work / "designs").mkdir(parents=True, exist_ok=True)
    cfg_dict = demo_config(load_config(config).model_dump(mode="json"), work, full=plate != "demo")
    if long_plate:
        sp_d = cfg_dict["sim"]["plate"]
        sp_d.update(length_mm=args.length_mm or 6000.0, width_mm=args.width_mm or 2000.0)
    if args.protocol is not None:
        cfg_dict["laser"]["protocol"] = args.protocol
    cfg_path = work / "cell.toml"
    cfg_path.write_text(to_toml(cfg_dict))
    cfg = load_config(cfg_path)
    sp = cfg.sim.plate
    spec = plate_spec(sp.kind, length_mm=sp.length_mm, width_mm=sp.width_mm, thickness_mm=sp.thickness_mm,
                      radius_x_mm=sp.radius_x_mm, radius_y_mm=sp.radius_y_mm)  # fmt: skip
    save_mesh(design_mesh(spec, pitch_mm=5.0), work / "designs" / DEMO_DESIGN)
    env = dict(os.environ)
    env.setdefault("CELL_RWS_PASSWORD", "robotics")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    procs = Processes(work / "logs", cfg_path, env)
    peaks: dict[str, float] = {}
    busy: list[subprocess.Popen] = []
    probes: list[subprocess.Popen] = []
    platform = None
    try:
        sim = procs.start("sim", "sim")
        wait_ready_line(work / "logs" / "sim.out", sim, 180.0)
        daemon = procs.start("run", "run")
        worker = procs.start("worker", "worker")
        busy = _busy_processes(args.load, args.worker_busy, work, env)
        probes = start_probes()
        t0 = time.time()

        async def drive():
            timeout_s = args.timeout_s or (7200.0 if long_plate else 3600.0)
            task = asyncio.ensure_future(
                drive_scan(
                    cfg_dict,
                    cfg,
                    procs,
                    timeout_s,
                    placement=args.given_placement or not (long_plate or args.no_placement),
                )
            )
            while not task.done():  # sample peaks while the worker's analysis child is alive
                peaks["daemon"] = max(peaks.get("daemon", 0.0), _peak_mb(daemon.pid))
                peaks["worker"] = max(peaks.get("worker", 0.0), _peak_mb(worker.pid))
                await asyncio.sleep(0.5)
            return task.result()

        sys.stdout, real_stdout = sys.stderr, sys.stdout  # the progress lines go to stderr
        try:
            job_id, report, _ = asyncio.run(drive())
        finally:
            sys.stdout = real_stdout
        peaks["daemon"] = max(peaks["daemon"], _peak_mb(daemon.pid))
        peaks["worker"] = max(peaks["worker"], _peak_mb(worker.pid))
        # the job is done with report.json; the HTML / PDF render follows: wait for it to be recorded
        wait_html_report(cfg.cell.data_dir, job_id, 180.0)
        peaks["daemon"] = max(peaks["daemon"], _peak_mb(daemon.pid))
    finally:
        if probes:
            platform = stop_probes(probes)
        for b in busy:
            b.kill()
            b.wait()
        procs.stop_all()
    rec = json.loads((Path(cfg.cell.data_dir) / "jobs" / job_id / "job.json").read_text())
    info = rec["info"]
    last = info["last_profile_utc_s"]
    events = {h["message"]: h["t_utc"] for h in rec["history"]}
    # the first entry of each state (the scan starts with the first "scanning")
    for h in rec["history"]:
        events.setdefault(h["state"], h["t_utc"])
    created = rec["history"][0]["t_utc"]
    total_s = info["report_utc_s"] - _utc_s(created)  # from the trigger (the job accepted)
    sweep_s = info["plan"]["sweep_time_s"]
    out = {
        "plate_mm": [sp.length_mm, sp.width_mm],
        "scan_s": info["scan_s"],
        "report_after_last_profile_s": round(info["report_utc_s"] - last, 2),
        "total_s": round(total_s, 2),
        "overhead_ratio": round(total_s / sweep_s, 3) if sweep_s > 0 else None,
        "transitions_s": info["plan"]["transitions_s"],
        # issue 22 item 2: the trigger to the scan's start (design, plan, bring-up), the execution
        # beyond the plan (the move to the plan's start, mostly), the processes' own start-up (before
        # the trigger, not in total_s) and total_s with it
        "startup_s": round(_utc_s(events["scanning"]) - _utc_s(created), 3) if "scanning" in events else None,
        "execution_beyond_plan_s": round(info["scan_s"] - info["plan"]["scan_time_s"], 3),
        "move_to_start_s": info.get("move_to_start_s"),
        "processes_up_s": round(_utc_s(created) - t0, 2),
        "total_with_processes_s": round(info["report_utc_s"] - t0, 2),
        "trigger_to_report_s": round(info["report_utc_s"] - _utc_s(created), 2),
        "html_after_last_profile_s": info.get("html_after_last_profile_s"),
        "daemon_peak_mb": peaks["daemon"],
        "worker_peak_mb": peaks["worker"],
        "planned_scan_s": info["plan"]["scan_time_s"],
        "sweep_time_s": info["plan"]["sweep_time_s"],
        "profiles": info["profiles"],
        "points": info.get("points"),
        "assemble_s": info.get("assemble_s"),
        "published_after_last_profile_s": (
            round(info["published_utc_s"] - last, 2) if "published_utc_s" in info else None
        ),
        "html_s": info.get("html_s"),
        "analysis_timings_s": info.get("analysis_timings_s"),
        "analysis_stages_s": report.timings_s if report else None,
        "scan_complete_utc": events.get("scan complete"),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "verdict": report.verdict if report else None,
        "job_created_utc": created,
        "work_dir": str(work),
        "config": config,
        "plate": plate,
        "scan_ratio": round(info["scan_s"] / sweep_s, 3) if sweep_s > 0 else None,
        "locate_s": info.get("locate_s"),
        "plan_s": info.get("plan_s"),
        "track": cfg.robot.track is not None,
        "plan_choices": info["plan"].get("choices"),
        "load": args.load,
        "protocol": cfg.laser.protocol,
        "worker_busy": args.worker_busy,
    }
    motion = info.get("motion") or {}
    out.update(
        egm_stale_cycles=motion.get("egm_stale_cycles"),
        egm_lost_cycles=motion.get("egm_lost_cycles"),
        egm_reply_p50_us=motion.get("egm_reply_p50_us"),
        egm_reply_p99_us=motion.get("egm_reply_p99_us"),
        egm_reply_max_us=motion.get("egm_reply_max_us"),
        egm_cycles=motion.get("cycles"),
        max_tracking_error_mm=info.get("max_tracking_error_mm"),
        max_tracking_t_traj_s=motion.get("max_tracking_t_traj_s"),
        motion_realtime=_motion_realtime(work / "logs" / "run.log"),
        # the machine's own floor over the same time: how often a SCHED_FIFO thread of the highest
        # priority woke more than one EGM cycle late (benchmarks/platform_latency.py)
        platform_over_cycle=None if platform is None else platform["over_cycle"],
        egm_stale_in_platform_stalls=_stale_in_stalls(Path(cfg.cell.data_dir), job_id, platform),
        platform=platform,
        accuracy_rms_mm=_accuracy_rms_mm(Path(cfg.cell.data_dir), job_id),
    )
    found = info.get("placement_found")
    if found is not None:
        out["placement_found"] = found
        if found.get("source") != "given" and rec.get("placement"):
            from analysis.contracts.placement import Placement
            from analysis.register.locate import placement_offset

            d_mm, d_deg = placement_offset(
                Placement.model_validate(rec["placement"]), cfg.sim.placement.to_placement()
            )
            if found.get("resolved_by") == "convention" and d_deg > 90.0:
                # an outline the same half a turn round: the bed's convention chose the other of
                # the two equal yaws (docs/locate.md); the plate is found all the same
                d_deg = 180.0 - d_deg
                out["half_turn_by_convention"] = True
            out.update(placement_err_mm=round(d_mm, 3), placement_err_deg=round(d_deg, 4))
    if long_plate:
        out["targets"] = {"scan_ratio_max": 1.2}
        out["passed"] = bool(
            out["scan_ratio"] is not None and out["scan_ratio"] <= 1.2 and out["verdict"] is not None
            and found is not None and found.get("source") == "located"
        )  # fmt: skip
    if platform is not None:
        platform.pop("stalls")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
