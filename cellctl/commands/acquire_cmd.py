"""`cellctl reassemble JOB_DIR` and `cellctl calibrate time-offset|hand-eye JOB_DIR`.

``reassemble`` rebuilds a scan's cloud from its raw files (bit for bit what the cell published) and
writes ``cloud.ply``, ``cloud.las`` and ``cloud.e57``; ``calibrate`` computes a calibration from a calibration job's
raw files, prints its residual report and, with ``--write``, stores the result in cell.toml
(``[laser] latency_ms`` or ``[robot.sensor_in_flange]``) and a record beside the raw files.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import structlog

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config

log = structlog.get_logger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reassemble", help="rebuild a scan's cloud from its raw files (PLY + LAS)")
    p.add_argument("job_dir", help="the job directory holding job.json and the *.craw raw files")
    p.add_argument(
        "--out", default=None, help="where cloud.ply / cloud.las / cloud.e57 go (default: the job directory)"
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="repeat the live assembly (online clock fits) instead of the final one",
    )
    p.add_argument(
        "--latency-ms", type=float, default=None, help="assemble with this latency instead of the job's"
    )
    p.set_defaults(func=run_reassemble)

    c = sub.add_parser("calibrate", help="calibrations from a calibration job's raw files")
    csub = c.add_subparsers(dest="calibration", metavar="WHAT", required=True)
    t = csub.add_parser("time-offset", help="latency from back-and-forth passes at several speeds")
    t.add_argument("job_dir")
    t.add_argument("--iterations", type=int, default=2)
    _common(t)
    t.set_defaults(func=run_time_offset)
    h = csub.add_parser("hand-eye", help="sensor-in-flange transform from stop-and-shoot sphere captures")
    h.add_argument("job_dir")
    h.add_argument("--radius-mm", type=float, required=True, help="the calibration sphere's certified radius")
    _common(h)
    h.set_defaults(func=run_hand_eye)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config", default=str(DEFAULT_CONFIG_PATH), help="the cell.toml to update (default ./cell.toml)"
    )
    p.add_argument(
        "--write", action="store_true", help="store the result in the config file (default: report only)"
    )


def _fail(msg: str) -> int:
    print(f"cellctl: error: {msg}", file=sys.stderr)
    return 2


def run_reassemble(args: argparse.Namespace) -> int:
    from cellctl.acquisition.cloud_files import write_e57, write_las, write_ply
    from cellctl.acquisition.reassemble import reassemble
    from cellctl.jobstore.rawstore import RawFormatError

    overrides = {} if args.latency_ms is None else {"latency_ms": args.latency_ms}
    try:
        res = reassemble(args.job_dir, overrides, final=not args.live)
    except (RawFormatError, FileNotFoundError) as exc:
        return _fail(str(exc))
    out = Path(args.out) if args.out else Path(args.job_dir)
    out.mkdir(parents=True, exist_ok=True)
    ply = write_ply(res.cloud, out / "cloud.ply")
    las = write_las(res.cloud, out / "cloud.las")
    e57 = write_e57(res.cloud, out / "cloud.e57")
    summary = {
        "profiles": len(res.cloud),
        "points": res.cloud.n_valid,
        "digest": res.cloud.digest(),
        "final": res.final,
        "ply": str(ply),
        "las": str(las),
        "e57": str(e57),
        "read": {"chunks": res.read.chunks, "torn_bytes": res.read.torn_bytes, "problems": res.read.problems},
        "sensor_clock": res.quality.get("sensor_clock"),
        "robot_clock": res.quality.get("robot_clock"),
    }
    print(json.dumps(summary, indent=2, default=float))
    return 0


def _config_path(args: argparse.Namespace) -> Path | None:
    if not args.write:
        return None
    try:
        load_config(args.config)
    except ConfigError as err:
        raise SystemExit(_fail(f"{err.source}: {'; '.join(err.problems)}")) from None
    return Path(args.config)


def run_time_offset(args: argparse.Namespace) -> int:
    from cellctl.calibration.record import CalibrationWriteError, set_toml_values, write_calibration_record
    from cellctl.calibration.time_offset import TimeOffsetError, calibrate_time_offset
    from cellctl.jobstore.rawstore import RawFormatError

    cfg_path = _config_path(args)
    try:
        res = calibrate_time_offset(args.job_dir, iterations=args.iterations)
    except (RawFormatError, TimeOffsetError, FileNotFoundError) as exc:
        return _fail(str(exc))
    report = res.report()
    print(json.dumps(report, indent=2, default=float))
    if cfg_path is not None:
        try:
            set_toml_values(cfg_path, "laser", {"latency_ms": round(res.latency_ms, 4)})
        except CalibrationWriteError as exc:
            return _fail(str(exc))
        write_calibration_record(args.job_dir, "time-offset", report)
        log.info("calibration_written", what="time-offset", config=str(cfg_path), latency_ms=res.latency_ms)
    return 0


def run_hand_eye(args: argparse.Namespace) -> int:
    from cellctl.calibration.hand_eye import HandEyeError, calibrate_hand_eye
    from cellctl.calibration.record import CalibrationWriteError, set_toml_values, write_calibration_record
    from cellctl.jobstore.rawstore import RawFormatError

    cfg_path = _config_path(args)
    try:
        res = calibrate_hand_eye(args.job_dir, args.radius_mm)
    except (RawFormatError, HandEyeError, FileNotFoundError) as exc:
        return _fail(str(exc))
    report = res.report()
    print(json.dumps(report, indent=2, default=float))
    if cfg_path is not None:
        try:
            set_toml_values(
                cfg_path,
                "robot.sensor_in_flange",
                {
                    "pos_mm": [round(float(v), 4) for v in res.pos_mm],
                    "rpy_deg": [round(float(v), 5) for v in res.rpy_deg],
                },
            )
        except CalibrationWriteError as exc:
            return _fail(str(exc))
        write_calibration_record(args.job_dir, "hand-eye", report)
        log.info("calibration_written", what="hand-eye", config=str(cfg_path))
    return 0
