"""Publish a large cloud daemon -> worker over Zenoh on loopback: encode, transfer, decode times.

The daemon side (this process) opens a peer session listening on 127.0.0.1 (multicast off), as
`cellctl run` does; the worker side is a separate process with a client session, as
`cellctl worker` is. The cloud has every field of the layout (xyz_mm, pass_id, profile_index,
point_index, t_s). Each run: encode (daemon), put with CongestionControl.BLOCK, arrival of the
sample in the worker's callback, ``payload.to_bytes()``, decode. The first message after connect
is reported separately (Zenoh's first large transfer is slower). Wall clocks of the two processes
are the same host clock. Prints one JSON object on stdout.

    .venv/bin/python benchmarks/zenoh_cloud.py [--points 10000000] [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cellctl.api.cloud_codec import ENCODING, Cloud, CloudMeta, decode_cloud, encode_cloud  # noqa: E402
from cellctl.api.session import build_zenoh_config, close_session, open_session  # noqa: E402
from cellctl.config import ZenohSection  # noqa: E402
from tests.support.ports import free_port  # noqa: E402


def make_cloud(n: int, job_id: str) -> Cloud:
    """A synthetic scan of n points: 500-point profiles, 60 passes, 200 Hz."""
    rng = np.random.default_rng(1)
    prof = np.arange(n, dtype=np.uint32) // 500
    return Cloud(
        xyz_mm=rng.uniform(-600, 600, (n, 3)).astype(np.float32),
        pass_id=(prof // 2000 % 60).astype(np.uint16),
        profile_index=prof % 2000,
        point_index=(np.arange(n) % 500).astype(np.uint16),
        t_s=prof.astype(np.float64) / 200.0,
        job_id=job_id,
        plate_id="bench",
        meta=CloudMeta(cell_id="bench"),
    )


def receiver(port: int, prefix: str) -> None:
    """Worker side: decode every cloud that arrives and send the timings back."""
    section = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"])
    session = open_session(build_zenoh_config(section, role="connect"), what="bench receiver")
    done = threading.Event()

    def on_cloud(sample: zenoh.Sample) -> None:
        t_arrive = time.time()
        t0 = time.perf_counter()
        raw = sample.payload.to_bytes()
        t1 = time.perf_counter()
        cloud = decode_cloud(raw)
        t2 = time.perf_counter()
        out = {
            "job_id": cloud.job_id,
            "t_arrive": t_arrive,
            "to_bytes_s": t1 - t0,
            "decode_s": t2 - t1,
            "t_decoded": time.time(),
            "n_points": cloud.n_points,
        }
        session.put(f"{prefix}/bench/timing", json.dumps(out))
        if cloud.job_id == "stop":
            done.set()

    try:
        session.declare_subscriber(f"{prefix}/bench/cloud", on_cloud)
        session.liveliness().declare_token(f"{prefix}/bench/alive")
        done.wait(600)
    finally:
        close_session(session)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=10_000_000)
    ap.add_argument("--runs", type=int, default=3, help="timed runs after the first (warm-up) message")
    ap.add_argument(
        "--shm", action="store_true", help="put through an explicit shared-memory buffer (same host only)"
    )
    ap.add_argument("--receiver", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--prefix", default="bench/zc", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.receiver:
        receiver(args.receiver, args.prefix)
        return
    run(args)


def run(args: argparse.Namespace) -> None:
    port = free_port()
    prefix = f"bench/zc{os.getpid()}"
    section = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"])
    session = open_session(build_zenoh_config(section, role="serve"), what="bench daemon")
    proc = None
    timings: list[dict] = []
    got = threading.Condition()
    alive = threading.Event()

    def on_timing(sample: zenoh.Sample) -> None:
        with got:
            timings.append(json.loads(sample.payload.to_bytes()))
            got.notify_all()

    def wait_timing(count: int) -> dict:
        with got:
            if not got.wait_for(lambda: len(timings) >= count, 120):
                raise RuntimeError("receiver did not answer within 120 s")
            return timings[count - 1]

    try:
        session.declare_subscriber(f"{prefix}/bench/timing", on_timing)
        session.liveliness().declare_subscriber(f"{prefix}/bench/alive", lambda s: alive.set(), history=True)
        proc = subprocess.Popen(
            [sys.executable, __file__, "--receiver", str(port), "--prefix", prefix],
            stdout=subprocess.DEVNULL,
        )
        if not alive.wait(60):
            raise RuntimeError("receiver did not come up within 60 s")
        pub = session.declare_publisher(
            f"{prefix}/bench/cloud", encoding=ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
        )
        provider = zenoh.shm.ShmProvider.default_backend(2 * args.points * 28 + 2**20) if args.shm else None
        runs = []
        for i in range(args.runs + 1):
            cloud = make_cloud(args.points, f"run{i}")
            t0 = time.perf_counter()
            payload = encode_cloud(cloud)
            encode_s = time.perf_counter() - t0
            t_put = time.time()
            t1 = time.perf_counter()
            if provider is not None:
                buf = provider.alloc(len(payload), zenoh.shm.BlockOn(zenoh.shm.GarbageCollect()))
                buf[0 : len(payload)] = payload
                pub.put(buf)
                del buf
            else:
                pub.put(payload)
            put_s = time.perf_counter() - t1
            r = wait_timing(i + 1)
            runs.append(
                {
                    "encode_s": encode_s,
                    "put_s": put_s,
                    "transfer_s": r["t_arrive"] - t_put,
                    "to_bytes_s": r["to_bytes_s"],
                    "decode_s": r["decode_s"],
                    "end_to_end_s": encode_s + (r["t_decoded"] - t_put),
                    "payload_mb": len(payload) / 1e6,
                }
            )
            del payload, cloud
        pub.put(encode_cloud(make_cloud(1, "stop")))
        wait_timing(args.runs + 2)
    finally:
        close_session(session)
        if proc is not None:
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    steady = runs[1:]

    def med(key: str) -> float:
        return round(statistics.median(r[key] for r in steady), 4)

    out = {
        "benchmark": "zenoh_cloud",
        "n_points": args.points,
        "fields": ["xyz_mm", "pass_id", "profile_index", "point_index", "t_s"],
        "payload_mb": round(runs[0]["payload_mb"], 1),
        "runs": args.runs,
        "encode_s": med("encode_s"),
        "put_s": med("put_s"),
        "transfer_s": med("transfer_s"),
        "to_bytes_s": med("to_bytes_s"),
        "decode_s": med("decode_s"),
        "end_to_end_s": med("end_to_end_s"),
        "throughput_mb_s": round(runs[0]["payload_mb"] / med("transfer_s"), 1),
        "first_message_transfer_s": round(runs[0]["transfer_s"], 4),
        "transport": ("shared memory" if args.shm else "tcp loopback")
        + ", CongestionControl.BLOCK, peer (daemon) -> client (worker)",
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
