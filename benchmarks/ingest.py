"""Profile ingestion throughput: decode, stamp, pose, transform, append to disk, on one core.

Frame groups of ``--batch`` uniform profiles of ``--width`` points are encoded beforehand with the HD8
protocol codec (the wire bytes a client reads); the timed loop decodes each group, feeds the robot
samples that cover it (250 Hz of joints), and runs the acquisition pipeline with its raw writer
(chunks fsync'ed every ``--flush-s``) in a temporary directory. numpy is limited to one thread.

Prints one JSON object: ``profiles_per_s`` (the issue's key: profiles per second of this process's CPU
time, i.e. the capacity of one core, which stays meaningful on a shared machine),
``profiles_per_s_wall`` (the same over wall time), ``points_per_s``, ``raw_mb_per_s`` and the
settings used. Target: >= 50,000 profiles/s of 500 points.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.jobstore.rawstore import RawWriter
from drivers.laser import protocol as P


def _groups(n_profiles: int, batch: int, width: int, rate_hz: float, rng: np.random.Generator) -> list[tuple]:
    scale = P.ProfileScale(x_scale_nm=100_000, z_scale_nm=2000, x_offset_um=-25_000, z_offset_um=100_000)
    out = []
    for k0 in range(0, n_profiles, batch):
        k = np.arange(k0, min(n_profiles, k0 + batch))
        t_us = np.rint(k * 1e6 / rate_hz).astype(np.uint64) + 1_000_000
        z = 100.0 + rng.normal(0, 5, (len(k), width))
        valid = rng.random((len(k), width)) > 0.02
        raw = P.encode_frame_group(
            frame_index=k.astype(np.uint64),
            sensor_time_us=t_us,
            hd8_ms=(t_us // 1000).astype(np.uint32),
            encoder=np.zeros(len(k), np.int64),
            status=np.zeros(len(k), np.uint32),
            exposure_ns=np.full(len(k), 500_000, np.uint32),
            scale=scale,
            z_raw=P.quantize_mm(z, valid, scale.z_scale_nm, scale.z_offset_um),
        )
        framer = P.MessageFramer()
        msgs = framer.feed(raw)
        out.append((msgs, int(t_us[-1])))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", type=int, default=60_000)
    ap.add_argument("--batch", type=int, default=200, help="profiles per frame group")
    ap.add_argument("--width", type=int, default=500)
    ap.add_argument("--rate-hz", type=float, default=200.0, help="sensor rate the stamps are made at")
    ap.add_argument("--flush-s", type=float, default=0.2)
    ap.add_argument("--dir", default=None, help="where the raw files go (default: a temporary directory)")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(0)
    groups = _groups(args.profiles, args.batch, args.width, args.rate_hz, rng)
    duration_s = args.profiles / args.rate_hz
    t_r = np.arange(0.0, duration_s + 1.0, 0.004032)
    q_r = np.column_stack(
        [
            5 * np.sin(t_r / 7),
            15 + 2 * np.sin(t_r / 5),
            29 + np.cos(t_r / 3),
            0 * t_r,
            45 + 0 * t_r,
            180 + 0 * t_r,
        ]
    )
    epoch_ns = 10**12
    host_r = epoch_ns + np.rint((t_r + 0.0002) * 1e9).astype(np.int64)
    ctrl_r = np.rint(t_r * 1e6).astype(np.int64) + 555_000_000
    settings = AcquisitionSettings(epoch_ns=epoch_ns)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        writer = RawWriter(
            Path(tmp) / "job", {"acquisition": settings.to_json()}, flush_interval_s=args.flush_s
        )
        acq = Acquisition(settings, writer, keep_batches=False)
        ri = 0
        points = 0
        t0 = time.perf_counter()
        c0 = time.process_time()
        for msgs, last_us in groups:
            host_ns = epoch_ns + (last_us - 1_000_000) * 1000 + 1_000_000
            batch = P.decode_group(msgs, host_ns)
            # the robot samples the endpoint received up to this group's arrival
            rj = int(np.searchsorted(host_r, host_ns + 10_000_000))
            if rj > ri:
                acq.feed_robot(host_r[ri:rj], ctrl_r[ri:rj], q_r[ri:rj])
                ri = rj
            for ab in acq.feed_profiles(batch):
                points += int(ab.valid.sum())
        for ab in acq.finish():
            points += int(ab.valid.sum())
        writer.close()
        elapsed = time.perf_counter() - t0
        cpu = time.process_time() - c0
        raw_mb = writer.bytes_written / 1e6
    print(
        json.dumps(
            {
                "profiles_per_s": round(args.profiles / cpu),
                "profiles_per_s_wall": round(args.profiles / elapsed),
                "points_per_s": round(points / cpu),
                "raw_mb_per_s": round(raw_mb / cpu, 1),
                "cpu_s": round(cpu, 3),
                "profiles": args.profiles,
                "width": args.width,
                "batch": args.batch,
                "flush_s": args.flush_s,
                "elapsed_s": round(elapsed, 3),
                "profiles_assembled": acq.stats.profiles_assembled,
                "target_profiles_per_s": 50_000,
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
