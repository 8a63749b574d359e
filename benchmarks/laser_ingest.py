"""HD8 ingest benchmark: client decode + delivery throughput, and the simulator's rendering rate.

Client side: a realistic stream (profiles ray-cast by the simulator's optics onto a curved plate, with
noise, quantised and encoded exactly as the simulator sends them) is served from memory over a
loopback TCP socket to :class:`drivers.laser.client.HD8Client`, which frames, validates, decodes and
queues it while a consumer drains the batches. ``profiles_per_s`` / ``points_per_s`` / ``cpu_s`` are
for groups of ``--group`` profiles (10 by default; the HD8 SDK's batch callback hands over 200 to
5000); the same figures for one profile per group (a sensor at 200 Hz sending every frame at once)
are given under ``single_profile_groups``.

``sim_realtime_1khz`` runs the simulator at 1 kHz for 3 s over the plate with a moving pose and a
client reading it in the same process: frames skipped for falling behind (``overrun_frames``, 0 when
it keeps up) and CPU seconds per second.

Simulator side: ``sim_profiles_per_s`` is ray casting + resampling + noise + quantisation of
500-point profiles on one thread (CPU time, groups of 5 as the simulator renders at 1 kHz), i.e. how
many profiles per second the simulator can produce; ``encode_profiles_per_s`` is the wire encoding.

``--protocol gige``: the GigE Vision source (drivers/laser/gige) against Aravis's own fake GigE Vision
device (``arv-fake-gv-camera-0.8``, a separate process, on 127.0.0.1) described as a profiler
(drivers/laser/sim/gige_xml.py): Mono16 range rows of 500 points, ``--rows`` per GVSP block, asked
for ``--line-rate`` profiles per second, for ``--seconds``. ``profiles_per_s`` is what arrived per wall
second (the fake device's own pace bounds it); ``profiles_per_cpu_s`` divides by the CPU time of this
process (Aravis's receive thread, the reader thread's conversion, the event loop), as the HD8 figure
does; torn buffers, gaps and Aravis's packet counters show whether anything was lost.

Prints exactly one JSON object.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from drivers.laser import protocol as P
from drivers.laser.client import HD8Client
from drivers.laser.sim.optics import LaserOptics, render_uniform
from drivers.laser.sim.scene import SceneRaycaster, cell_scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig


def curved_plate() -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.linspace(-600, 600, 61), np.linspace(-400, 400, 41)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = 2000.0 - np.sqrt(2000.0**2 - X**2) + 0.001 * Y**2 * 0.01
    v = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(len(xs) * len(ys)).reshape(len(xs), len(ys))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def sweep_poses(n: int) -> np.ndarray:
    """Sensor 100 mm above the plate, tilted 5 deg, sweeping along y."""
    T = np.repeat(np.eye(4)[None], n, axis=0)
    c, s = np.cos(np.radians(5)), np.sin(np.radians(5))
    T[:, :3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]]) @ np.array(
        [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    )
    T[:, 0, 3] = 150.0
    T[:, 1, 3] = np.linspace(-350, 350, n)
    T[:, 2, 3] = 100.0 + 2000.0 - np.sqrt(2000.0**2 - 150.0**2)
    return T


def render_pool(raycaster: SceneRaycaster, n_frames: int, group: int) -> tuple[np.ndarray, float]:
    """Render ``n_frames`` raw uniform profiles as the simulator does; return them and the CPU time."""
    cfg = SimConfig()
    optics: LaserOptics = cfg.optics()
    rng = np.random.default_rng(0)
    poses = sweep_poses(n_frames)
    out = []
    cpu0 = time.thread_time()
    for k0 in range(0, n_frames, group):
        r = render_uniform(raycaster, poses[k0 : k0 + group], optics, rng)
        out.append(P.quantize_mm(r.z_mm, r.valid, cfg.z_scale_nm, 100_000))
    return np.concatenate(out), time.thread_time() - cpu0


def encode_stream(pool: np.ndarray, n_frames: int, group: int) -> bytes:
    """Encode ``n_frames`` profiles (cycling through ``pool``) into frame groups of ``group``."""
    scale = P.ProfileScale(100_000, 2000, -24_950, 100_000)
    parts = []
    for k0 in range(0, n_frames, group):
        k1 = min(n_frames, k0 + group)
        n = k1 - k0
        idx = np.arange(k0, k1) % len(pool)
        parts.append(
            P.encode_frame_group(
                frame_index=np.arange(k0, k1, dtype=np.uint64),
                sensor_time_us=np.arange(k0, k1, dtype=np.uint64) * 5000,
                hd8_ms=(np.arange(k0, k1) * 5).astype(np.uint32),
                encoder=np.zeros(n, np.int64),
                status=np.zeros(n, np.uint32),
                exposure_ns=np.full(n, 500_000, np.uint32),
                scale=scale,
                z_raw=pool[idx],
            )
        )
    return b"".join(parts)


async def ingest(blob: bytes, n_frames: int) -> dict[str, float]:
    """Serve ``blob`` on the data port of a minimal control/data pair; time the client end to end."""

    async def control(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        framer = P.MessageFramer()
        while chunk := await reader.read(4096):
            for msg in framer.feed(chunk):
                payload = P.SensorInfo(
                    "BENCH", "0", 500, 100_000, -24_950, 70_000, 130_000, 10**6, 10**5, 3 * 10**6
                )
                writer.write(
                    P.encode_reply(msg.type, P.Status.OK, payload.to_bytes() if msg.type == 0x4001 else b"")
                )

    go = asyncio.Event()

    async def data(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(14)  # SUBSCRIBE
        await go.wait()
        writer.write(blob)
        await writer.drain()
        await reader.read()  # until the client closes

    ctl = await asyncio.start_server(control, "127.0.0.1", 0)
    dat = await asyncio.start_server(data, "127.0.0.1", 0)
    client = HD8Client("127.0.0.1", ctl.sockets[0].getsockname()[1], dat.sockets[0].getsockname()[1])
    await client.connect()
    await client.start()
    got = points = 0
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    go.set()
    async for batch in client:
        got += len(batch)
        points += batch.n_points
        if got >= n_frames:
            break
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    assert client.stats.decode_errors == 0 and client.stats.gaps == 0 and got == n_frames
    await client.close()
    for srv in (ctl, dat):
        srv.close()
        await srv.wait_closed()
    await asyncio.sleep(0.05)  # let the handlers see EOF and finish
    return {
        "profiles_per_s": round(got / cpu, 1),
        "points_per_s": round(points / cpu, 1),
        "cpu_s": round(cpu, 4),
        "wall_s": round(wall, 4),
        "profiles": got,
    }


async def sim_realtime(raycaster: SceneRaycaster, seconds: float) -> dict[str, float]:
    """Run the simulator at 1 kHz over the plate with a moving pose and a client reading; report CPU."""
    t_start = time.monotonic()
    base = sweep_poses(2)[0]

    def pose_at(t: np.ndarray) -> np.ndarray:
        T = np.repeat(base[None], len(t), axis=0)
        T[:, 1, 3] = -300.0 + 100.0 * (t - t_start)  # 100 mm/s along y
        return T

    sim = LaserSimulator(raycaster.scene, pose_at, config=SimConfig(rate_hz=1000.0, max_backlog_s=0.05))
    ctl, dat = await sim.start()
    client = HD8Client("127.0.0.1", ctl, dat)
    await client.connect()
    await client.start()
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    got = 0
    async for batch in client:
        got += len(batch)
        if time.perf_counter() - t0 >= seconds:
            break
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    await client.close()
    await sim.stop()
    return {
        "rate_hz": 1000.0,
        "profiles": got,
        "overrun_frames": sim.stats.overrun_frames,
        "cpu_s_per_s": round(cpu / wall, 3),  # simulator + client in one process
        "render_thread_s_per_s": round(sim.stats.render_s / wall, 3),
    }


async def gige_ingest(line_rate_hz: float, rows: int, seconds: float, packet_size: int) -> dict[str, object]:
    """Read the fake GigE Vision profiler for ``seconds``; count profiles, wall and CPU time."""
    from drivers.laser.gige import GigeProfileSource, GigeSourceConfig, GigeStats

    src = GigeProfileSource(
        "127.0.0.1",
        config=GigeSourceConfig(
            rows_per_buffer=rows, width=500, packet_size=packet_size, buffer_profiles=10 * rows + 100_000
        ),
    )
    await src.connect()
    await src.configure(rate_hz=line_rate_hz, exposure_ns=10_000_000)
    await src.start()
    got = points = 0
    async for _first in src:  # the first buffer: the stream is up
        break
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    async for batch in src:
        got += len(batch)
        points += batch.n_points
        if time.perf_counter() - t0 >= seconds:
            break
    wall = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    # Aravis's counters now, not after close's teardown
    st = GigeStats(**{k: v for k, v in vars(src.refresh_stats()).items() if not k.startswith("_")})
    await src.close()
    return {
        "profiles_per_s": round(got / wall, 1),
        "points_per_s": round(points / wall, 1),
        "profiles_per_cpu_s": round(got / cpu, 1),
        "cpu_s_per_s": round(cpu / wall, 3),
        "wall_s": round(wall, 3),
        "profiles": got,
        "asked_line_rate_hz": line_rate_hz,
        "rows_per_buffer": rows,
        "packet_size": packet_size,
        "gaps": st.gaps,
        "missing_frames": st.missing_frames,
        "torn_buffers": st.torn_buffers,
        "underruns": st.underruns,
        "missing_packets": st.missing_packets,
        "resent_packets": st.resent_packets,
    }


def gige_main(args: argparse.Namespace) -> None:
    """The GigE Vision figure: the source against Aravis's fake device in its own process."""
    import shutil
    import subprocess
    import tempfile

    from drivers.laser.sim.gige_xml import profiler_genicam_xml

    binary = shutil.which("arv-fake-gv-camera-0.8")
    if binary is None:
        raise SystemExit("arv-fake-gv-camera-0.8 is missing: run scripts/setup.sh (Debian aravis-tools)")
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "profiler.xml"
        xml.write_text(
            profiler_genicam_xml(a_scale_mm=0.1, a_offset_mm=-24.95, c_scale_mm=0.002, c_offset_mm=70.0)
        )
        proc = subprocess.Popen(
            [binary, "-i", "127.0.0.1", "-s", "BENCH", "-g", str(xml)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            time.sleep(1.0)
            runs = [
                asyncio.run(gige_ingest(args.line_rate, args.rows, args.seconds, args.packet_size)),
                asyncio.run(
                    gige_ingest(args.line_rate / 10, args.rows // 10, args.seconds, args.packet_size)
                ),
            ]
        finally:
            proc.kill()
            proc.wait()
    out = {
        "benchmark": "laser_ingest",
        "protocol": "gige",
        "device": "arv-fake-gv-camera-0.8 (Aravis 0.8.26) on 127.0.0.1, profiler description",
        **runs[0],
        "points_per_profile": 500,
        "low_latency_blocks": runs[1],
        "target_profiles_per_s": 50_000,
    }
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--protocol", choices=["hd8", "gige"], default="hd8")
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--group", type=int, default=10)
    ap.add_argument("--line-rate", type=float, default=400_000.0, help="gige: profiles/s asked of the device")
    ap.add_argument("--rows", type=int, default=2000, help="gige: profiles per GVSP block")
    ap.add_argument("--seconds", type=float, default=5.0, help="gige: how long to read")
    ap.add_argument("--packet-size", type=int, default=16_000, help="gige: GVSP packet bytes")
    args = ap.parse_args()
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR),
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
    )
    if args.protocol == "gige":
        gige_main(args)
        return
    v, t = curved_plate()
    rc = SceneRaycaster(cell_scene(v, t, thickness_mm=12.0))
    sim_n = 2000
    pool, sim_cpu = render_pool(rc, sim_n, 5)  # 5 per group: the simulator at 1 kHz
    encode_cpu0 = time.process_time()
    blob = encode_stream(pool, args.frames, args.group)
    encode_cpu = time.process_time() - encode_cpu0
    n_single = min(args.frames, 10_000)
    blob1 = encode_stream(pool, n_single, 1)
    grouped = asyncio.run(ingest(blob, args.frames))
    single = asyncio.run(ingest(blob1, n_single))
    realtime = asyncio.run(sim_realtime(rc, 3.0))
    out = {
        "benchmark": "laser_ingest",
        **grouped,
        "group_profiles": args.group,
        "points_per_profile": 500,
        "single_profile_groups": single,
        "sim_profiles_per_s": round(sim_n / sim_cpu, 1),
        "encode_profiles_per_s": round(args.frames / encode_cpu, 1),
        "sim_realtime_1khz": realtime,
        "sim_cpu_s_per_1000_profiles": round(sim_cpu / sim_n * 1000, 4),
        "target_profiles_per_s": 50_000,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
