"""Memory and time of a 6000 x 2000 mm plate's data, without the robot: the daemon's acquisition
path and the analysis worker's pipeline, each in its own process, peak RSS (VmHWM) measured.

* ``daemon``: a long-plate-sized profile stream (default 340 000 profiles of 500 points at 200 Hz,
  57 passes, 250 Hz of joint feedback) through :class:`cellctl.acquisition.pipeline.Acquisition` with
  its raw writer (fsync'ed chunks in a temporary directory), the whole scan taken as the daemon
  takes it (``Acquisition.cloud``), then thinned and encoded for publication as
  :mod:`cellctl.daemon.handover` does (``column_steps`` + ``encode_scan`` at ``--publish-pitch-mm``)
  and the payload written as ``cloud.bin``. Peaks per stage (``/proc/self/clear_refs`` resets VmHWM
  between stages).
* ``worker``: a synthetic scan of a 6000 x 2000 x 15 mm formed plate (``analysis.synth``) at the
  published density (0.5 mm along the line, 1 mm between profiles: what the cell publishes from the
  HD8), encoded with the cloud codec in a first process; a second process does what the worker's
  analysis child does: decode the bytes, ``analysis.pipeline.analyse_job`` with the plate's
  detection lines (the paper's spacing over the whole plate) and the results directory written.
  Its VmHWM and the analysis time are the worker's figures.

``--length-mm`` / ``--width-mm`` size the plate (default 6000 x 2000): the worker side's (the beams
every metre, the radii scaled with the size) and the daemon side's stream (340 000 profiles in 57
passes scaled: the passes with the width, their profiles with the length; ``--profiles`` /
``--passes`` set them instead). The daemon's whole-scan arrays go to a spill file beside its raw
files (``--dir``: a disk, not a tmpfs). ``--stages`` adds ``stages``, the analysis stage by stage
(:class:`StageProfile`: time, peak and after RSS, the numpy heap live at the stage's end and at its
peak, the arrays its result holds, in bytes per point of the input cloud) and ``worker_peak_b_per_pt``;
docs/operations.md "The analysis' memory, stage by stage" has the table. On the daemon side ``--stages``
adds ``daemon_heap_peak_b_per_pt``, the numpy heap's peak per stage (docs/operations.md "The daemon's
memory, stage by stage").

Prints one JSON object: ``daemon_peak_mb``, ``daemon_stages_mb`` (acquire / cloud / publish) and
the same in bytes per raw point (``daemon_stages_b_per_pt``, ``daemon_peak_b_per_pt``),
``daemon_s``, ``profiles``, ``raw_points``, ``published_points``, ``cloud_bytes``, ``cloud_sha256``,
``worker_peak_mb``, ``analysis_s``, ``analysis_stages_s``, ``analysed_points``, ``lines``,
``verdict``, ``load_avg_1min``. ``--part daemon|worker`` runs one side only.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def _hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return round(int(line.split()[1]) / 1024.0, 1)
    return float("nan")


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024.0, 1)
    return float("nan")


def _reset_hwm() -> None:
    """Reset VmHWM to the current RSS (Linux: ``5`` into clear_refs)."""
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _stage_end(stages: dict[str, float], heap: dict[str, int], name: str) -> None:
    """The stage's peak RSS (and with tracemalloc on, ``--stages``, the numpy heap's peak), then both
    reset for the next stage."""
    import tracemalloc

    stages[name] = _hwm_mb()
    if tracemalloc.is_tracing():
        heap[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
    _reset_hwm()


# ---- daemon side -------------------------------------------------------------------------------


def feed_stream(acq, *, n_profiles: int, n_passes: int, width: int, batch: int, epoch_ns: int,
                seed: int = 0, between=None) -> None:  # fmt: skip
    """A long plate's profile stream into ``acq`` (not finished): ``n_profiles`` profiles of ``width``
    points at 200 Hz in ``batch``-profile frame groups through the HD8 protocol's encoder and decoder,
    ``n_passes`` passes, 250 Hz of joint feedback (tests/acquisition/test_daemon_memory.py feeds a
    scaled-down one). ``between``: called after each group (the event loop's turn)."""
    import numpy as np

    from drivers.laser import protocol as P

    rate_hz = 200.0
    per_pass = n_profiles // n_passes
    scale = P.ProfileScale(x_scale_nm=100_000, z_scale_nm=2000, x_offset_um=-25_000, z_offset_um=100_000)
    rng = np.random.default_rng(seed)
    t_r_step = 0.004032
    next_r = 0.0
    pass_open = False
    for k0 in range(0, n_profiles, batch):
        k = np.arange(k0, min(n_profiles, k0 + batch))
        t_s = k / rate_hz
        # the robot samples received up to this group's arrival (250 Hz of joints)
        t_r = np.arange(next_r, t_s[-1] + 0.01, t_r_step)
        if len(t_r):
            next_r = t_r[-1] + t_r_step
            q = np.column_stack(
                [5 * np.sin(t_r / 70), 15 + 2 * np.sin(t_r / 50), 29 + np.cos(t_r / 30),
                 0 * t_r, 45 + 0 * t_r, 180 + 0 * t_r]
            )  # fmt: skip
            host = epoch_ns + np.rint((t_r + 0.0002) * 1e9).astype(np.int64)
            ctrl = np.rint(t_r * 1e6).astype(np.int64) + 555_000_000
            acq.feed_robot(host, ctrl, q)
        p = int(k0 // per_pass)
        if not pass_open and p < n_passes:
            acq.begin_pass(p, epoch_ns + int(t_s[0] * 1e9) - 1000)
            pass_open = True
        t_us = np.rint(t_s * 1e6).astype(np.uint64) + 1_000_000
        z = 100.0 + rng.normal(0, 5, (len(k), width))
        valid = rng.random((len(k), width)) > 0.02
        raw = P.encode_frame_group(
            frame_index=k.astype(np.uint64), sensor_time_us=t_us,
            hd8_ms=(t_us // 1000).astype(np.uint32), encoder=np.zeros(len(k), np.int64),
            status=np.zeros(len(k), np.uint32), exposure_ns=np.full(len(k), 500_000, np.uint32),
            scale=scale, z_raw=P.quantize_mm(z, valid, scale.z_scale_nm, scale.z_offset_um),
        )  # fmt: skip
        msgs = P.MessageFramer().feed(raw)
        acq.feed_profiles(P.decode_group(msgs, epoch_ns + int(t_us[-1] - 1_000_000) * 1000 + 1_000_000))
        if pass_open and (int((k0 + batch) // per_pass) != p):
            acq.end_pass(epoch_ns + int(t_s[-1] * 1e9) + 1000)
            pass_open = False
        if between is not None:
            between()


class _HeldChunks:
    """What :class:`cellctl.daemon.dispatch.Dispatcher` does with a streamed job's chunks, without
    Zenoh: each kept with its sha256 until the stream ends (``--stream``)."""

    def __init__(self) -> None:
        self.chunks: list[tuple] = []

    def stream_chunk(self, job_id, pass_index, payload, points, *, last_pass=False) -> int:
        self.chunks.append((pass_index, points, hashlib.sha256(payload).hexdigest(), payload, last_pass))
        return len(self.chunks) - 1

    def stream_payloads(self, job_id) -> list:
        return [c[3] for c in self.chunks]

    def end_stream(self, job_id) -> None:
        pass


def _streamed(
    args, acq, writer, n_profiles: int, n_passes: int, epoch_ns: int, tmp: str, stages: dict, heap: dict
) -> dict:
    """``--stream``: the scan's cloud cut pass by pass while it is acquired (:class:`ScanStream` in
    the same event loop as the acquisition, as in the daemon), the chunks held as the dispatcher holds
    them (``spill``: in a file beside the raw ones; ``memory``: in memory, as before issue 42), then
    ``cloud.bin`` written from them as the hand-over does."""
    import asyncio

    from cellctl.acquisition.publish import PublishSettings
    from cellctl.acquisition.spill import release
    from cellctl.api.cloud_codec import CloudMeta, write_concatenated
    from cellctl.daemon.stream import ScanStream

    loop = asyncio.new_event_loop()
    held = _HeldChunks()
    stream = ScanStream(held, loop.create_future(), job_id="long", plate_id="long",
                        settings=PublishSettings(pitch_mm=args.publish_pitch_mm, edge_pitch_mm=args.publish_pitch_mm),
                        first_edge_pass=n_passes - 4, meta=CloudMeta())  # fmt: skip

    async def follow() -> None:
        stream.follow(acq, writer if args.stream == "spill" else None)

    loop.run_until_complete(follow())
    feed_stream(acq, n_profiles=n_profiles, n_passes=n_passes, width=args.width, batch=args.batch,
                epoch_ns=epoch_ns, between=lambda: loop.run_until_complete(asyncio.sleep(0)))  # fmt: skip
    acq.finish()
    writer.close()
    loop.run_until_complete(stream.finish())
    _stage_end(stages, heap, "acquire")
    payloads = stream.payloads
    size = write_concatenated(Path(tmp) / "cloud.bin", payloads, read=release)
    _stage_end(stages, heap, "publish")
    scan = acq.cloud()
    raw_points = scan.n_valid
    digest = hashlib.sha256(Path(tmp, "cloud.bin").read_bytes()).hexdigest()
    loop.close()
    return {"profiles": len(scan), "raw_points": raw_points, "published_points": stream.points,
            "cloud_bytes": size, "cloud_sha256": digest, "stream_chunks": stream.chunks}  # fmt: skip


def _daemon_figures(stages: dict[str, float], heap: dict[str, int], **more) -> dict:
    """The daemon side's JSON: peak RSS per stage in MB and in bytes per raw point (and the numpy
    heap's peak per stage in bytes per raw point with ``--stages``), then ``more`` (``raw_points`` in it)."""
    raw_points = more["raw_points"]
    mib_per_pt = 2**20 / max(raw_points, 1)
    out = {
        "daemon_stages_mb": stages,
        "daemon_stages_b_per_pt": {k: round(v * mib_per_pt, 2) for k, v in stages.items()},
        "daemon_peak_mb": max(stages.values()),
        "daemon_peak_b_per_pt": round(max(stages.values()) * mib_per_pt, 2),
    }
    if heap:
        out["daemon_heap_peak_b_per_pt"] = {k: round(v / max(raw_points, 1), 2) for k, v in heap.items()}
    return {**out, **more}


def daemon_part(args: argparse.Namespace) -> dict:
    from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
    from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan
    from cellctl.jobstore.rawstore import RawWriter

    n_profiles, n_passes = _daemon_size(args)
    epoch_ns = 10**12
    settings = AcquisitionSettings(epoch_ns=epoch_ns)
    stages: dict[str, float] = {}
    heap: dict[str, int] = {}
    if args.stages:
        import tracemalloc

        tracemalloc.start(1)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        writer = RawWriter(Path(tmp) / "job", {"acquisition": settings.to_json()})
        expected = n_profiles if args.presize else None
        acq = Acquisition(
            settings, writer, keep_batches=True, **({"expected_profiles": expected} if expected else {})
        )
        if args.stream:
            out = _streamed(args, acq, writer, n_profiles, n_passes, epoch_ns, tmp, stages, heap)
            return _daemon_figures(stages, heap, stream=args.stream,
                                   daemon_acquire_s=round(time.perf_counter() - t0, 1), **out)  # fmt: skip
        feed_stream(acq, n_profiles=n_profiles, n_passes=n_passes, width=args.width, batch=args.batch,
                    epoch_ns=epoch_ns)  # fmt: skip
        acq.finish()
        writer.close()
        _stage_end(stages, heap, "acquire")
        acquire_s = time.perf_counter() - t0
        # as cellctl/daemon/scan.py: the whole scan taken while the acquisition is still alive
        scan = acq.take_cloud() if hasattr(acq, "take_cloud") else acq.cloud()
        raw_points = scan.n_valid
        profiles = len(scan)
        del acq
        _stage_end(stages, heap, "cloud")
        t1 = time.perf_counter()
        steps = column_steps(
            scan.pass_id,
            n_passes - 4,
            PublishSettings(pitch_mm=args.publish_pitch_mm, edge_pitch_mm=args.publish_pitch_mm),
        )
        payload, n_points = encode_scan(scan, job_id="long", plate_id="long", column_step=steps)
        del scan, steps
        (Path(tmp) / "cloud.bin").write_bytes(payload)
        publish_s = time.perf_counter() - t1
        _stage_end(stages, heap, "publish")
        raw_bytes = writer.bytes_written
    return _daemon_figures(
        stages, heap,
        daemon_acquire_s=round(acquire_s, 1),
        daemon_publish_s=round(publish_s, 1),
        profiles=profiles,
        raw_points=raw_points,
        raw_mb=round(raw_bytes / 1e6, 1),
        published_points=n_points,
        cloud_bytes=len(payload),
        cloud_sha256=hashlib.sha256(payload).hexdigest(),
        daemon_presized=bool(args.presize),
    )  # fmt: skip


def _daemon_size(args: argparse.Namespace) -> tuple[int, int]:
    """Profiles and passes of the daemon side: ``--profiles`` / ``--passes``, or scaled from the 6 m
    plate's 340 000 profiles in 57 passes by the plate's size (passes along the length, so their count
    grows with the width and their profiles with the length: the profiles with the area)."""
    area = args.length_mm * args.width_mm / (6000.0 * 2000.0)
    profiles = args.profiles if args.profiles is not None else round(340_000 * area)
    passes = args.passes if args.passes is not None else max(5, round(57 * args.width_mm / 2000.0))
    return profiles, passes


# ---- worker side -------------------------------------------------------------------------------


def _long_spec(length_mm: float, width_mm: float):
    from analysis.design.plates import plate_spec

    # the sail's curvature over a plate five times as long and 2.5 times as wide (the 6 m plate): Rx,
    # Ry scaled with the size so the depth stays a formed shell plate's (about 225 mm along, 70 mm
    # across at 6000 x 2000), not a bowl
    return plate_spec("sail", length_mm=length_mm, width_mm=width_mm, radius_x_mm=20000.0 * length_mm / 6000.0,
                      radius_y_mm=7500.0 * width_mm / 2000.0)  # fmt: skip


def synth_part(args: argparse.Namespace) -> dict:
    import numpy as np

    from analysis.design.mesh import save_mesh
    from analysis.design.plates import default_forming_error, design_mesh
    from analysis.synth import BedScene, ScanSettings, SupportBox, synthesize_scan
    from cellctl.api.cloud_codec import Cloud, encode_cloud

    spec = _long_spec(args.length_mm, args.width_mm)
    # beams every metre under the plate (six under a 6 m plate), across its full width
    n_beams = max(2, round(args.length_mm / 1000.0))
    half_y = args.width_mm / 2 + 300.0
    beams_x = (np.arange(n_beams) - (n_beams - 1) / 2) * 1000.0
    scene = BedScene(supports=tuple(SupportBox(x - 40.0, x + 40.0, -half_y, half_y, 60.0)
                                    for x in beams_x.tolist()))  # fmt: skip
    pitch = args.publish_pitch_mm
    st = ScanSettings(point_pitch_mm=pitch, points_per_profile=round(49.9 / pitch) + 1, profile_step_mm=1.0,
                      pass_overlap_mm=5.0)  # fmt: skip
    from analysis.contracts.placement import Placement

    scan = synthesize_scan(spec, default_forming_error(spec), settings=st, scene=scene,
                           placement=Placement.on_bed(10.0, -5.0, 0.4), seed=args.seed)  # fmt: skip
    c = scan.cloud
    cloud = Cloud(xyz_mm=c.xyz_mm.astype(np.float32), job_id="long", plate_id="long",
                  pass_id=c.pass_id.astype(np.uint16), profile_index=c.profile_index.astype(np.uint32),
                  point_index=c.point_index.astype(np.uint16))  # fmt: skip
    out = Path(args.work)
    (out / "cloud.bin").write_bytes(encode_cloud(cloud))
    save_mesh(design_mesh(spec, pitch_mm=10.0), out / "design.ply")
    return {"synth_points": cloud.n_points, "synth_peak_mb": _hwm_mb()}


def _trace_peaks(period_s: float = 0.5) -> None:
    """Print (stderr) the threads' stacks each time the RSS passes its previous peak by 200 MB."""
    import threading
    import traceback

    def run() -> None:
        top = 0.0
        me = threading.get_ident()
        while True:
            rss = _rss_mb()
            if rss > top + 200:
                top = rss
                lines = [f"--- rss {rss:.0f} MB"]
                for tid, frame in sys._current_frames().items():
                    if tid != me:
                        st = traceback.extract_stack(frame)[-4:]
                        lines += [f"  {f.filename.split('/')[-1]}:{f.lineno} {f.name}" for f in st] + ["  ."]
                print("\n".join(lines), file=sys.stderr, flush=True)
            time.sleep(period_s)

    threading.Thread(target=run, daemon=True).start()


#: the analysis' stages as :func:`analysis.pipeline.inspect_cloud` and :func:`analysis.pipeline._inspect_job`
#: call them (names looked up in ``analysis.pipeline`` at call time): each is wrapped to measure it
STAGES = ("prepare_design", "segment_plate", "find_corners", "surface_cell_mm", "height_grid_mesh", "register",
          "register_from_placement", "cut_templates", "cut_templates_exact", "deflection_gaps", "_per_line_cuts",
          "_coverage_holes", "write_results")  # fmt: skip


def _held_arrays(obj, seen: set[int], prefix: str, out: dict[str, int], depth: int = 0) -> None:
    """The numpy arrays ``obj`` holds (dataclass fields, tuples, lists, dicts; each buffer counted once)
    by name -> bytes, into ``out``."""
    import dataclasses

    import numpy as np

    if depth > 3 or obj is None:
        return
    if isinstance(obj, np.ndarray):
        base = obj
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) not in seen and obj.nbytes >= 1 << 20:
            seen.add(id(base))
            out[prefix] = out.get(prefix, 0) + base.nbytes
        return
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        items = [(f.name, getattr(obj, f.name, None)) for f in dataclasses.fields(obj)]
    elif isinstance(obj, tuple | list):
        items = [(str(k), v) for k, v in enumerate(obj[:8])]
    elif isinstance(obj, dict):
        items = [(str(k), v) for k, v in list(obj.items())[:16]]
    else:
        return
    for name, v in items:
        _held_arrays(v, seen, f"{prefix}.{name}" if prefix else name, out, depth + 1)


class StageProfile:
    """Per stage of the analysis: wall time, the process' peak RSS during it (VmHWM, reset at its
    start), the RSS after it, the numpy heap (tracemalloc: numpy reports its buffers to it) live at
    its end and its peak during it, and the arrays its result holds. Bytes per point are per point of
    the input cloud."""

    def __init__(self, n_points: int) -> None:
        self.n = max(n_points, 1)
        self.rows: list[dict] = []
        self.calls: dict[str, int] = {}

    def wrap(self, module, name: str) -> None:
        """Replace ``module.name`` by the same function measured as a stage (a second call: ``name#2``)."""
        import tracemalloc

        fn = getattr(module, name)

        def stage(*a, **kw):
            k = self.calls[name] = self.calls.get(name, 0) + 1
            _reset_hwm()
            tracemalloc.reset_peak()
            t0 = time.perf_counter()
            out = fn(*a, **kw)
            self.mark(name if k == 1 else f"{name}#{k}", t0, out)
            return out

        setattr(module, name, stage)

    def mark(self, name: str, t0: float, held_obj=None) -> None:
        """The row of a stage that started at ``t0`` (VmHWM and the heap's peak reset then) and whose
        result is ``held_obj``."""
        import tracemalloc

        dt = time.perf_counter() - t0
        cur, peak = tracemalloc.get_traced_memory()
        held: dict[str, int] = {}
        _held_arrays(held_obj, set(), "", held)
        top = sorted(held.items(), key=lambda kv: -kv[1])[:4]
        self.rows.append({
            "stage": name, "s": round(dt, 2), "peak_rss_mb": _hwm_mb(), "rss_after_mb": _rss_mb(),
            "heap_live_b_per_pt": round(cur / self.n, 1), "heap_peak_b_per_pt": round(peak / self.n, 1),
            "result_b_per_pt": round(sum(held.values()) / self.n, 1),
            "result_arrays_b_per_pt": {k: round(v / self.n, 1) for k, v in top},
        })  # fmt: skip


def worker_part(args: argparse.Namespace) -> dict:
    import tracemalloc

    import analysis.pipeline as pipeline
    from analysis.contracts.job import AnalysisJob
    from analysis.contracts.settings import InspectionSettings
    from analysis.pipeline import analyse_job
    from analysis.templates import DetectionLayout
    from cellctl.api.cloud_codec import decode_cloud

    if args.trace:
        _trace_peaks()
    work = Path(args.work)
    raw = (work / "cloud.bin").read_bytes()
    profile = None
    if args.stages:
        tracemalloc.start(1)
        _reset_hwm()
    t0 = time.perf_counter()
    c0 = time.process_time()
    cloud = decode_cloud(raw)
    scan = cloud.scan_cloud()
    if args.stages:
        profile = StageProfile(len(scan))
        profile.mark("decode", t0, scan)
        for name in STAGES:
            profile.wrap(pipeline, name)
    settings = InspectionSettings(layout=DetectionLayout(transverse_count=None, longitudinal_count=None))
    job = AnalysisJob(design=str(work / "design.ply"), settings=settings, out_dir=str(work / "results"),
                      job_id="long", plate_id="long")  # fmt: skip
    report = analyse_job(scan, job)
    out = {
        "worker_peak_mb": _hwm_mb() if profile is None else max(r["peak_rss_mb"] for r in profile.rows),
        "analysis_s": round(time.perf_counter() - t0, 1),
        "analysis_cpu_s": round(time.process_time() - c0, 1),
        "analysis_stages_s": report.timings_s,
        "analysed_points": len(cloud.xyz_mm),
        "lines": len(report.lines),
        "verdict": report.verdict,
    }
    if profile is not None:
        out["worker_peak_b_per_pt"] = round(out["worker_peak_mb"] * 2**20 / profile.n, 1)
        out["stages"] = profile.rows
    return out


def _child(part: str, args: argparse.Namespace, extra: list[str]) -> dict:
    cmd = [sys.executable, __file__, "--part", part, *extra]
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"{part} failed:\n{r.stderr[-4000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--part", choices=["all", "daemon", "worker", "synth", "analysis"], default="all")
    p.add_argument(
        "--profiles",
        type=int,
        default=None,
        help="daemon side: profiles (default 340 000 scaled by the plate's area)",
    )
    p.add_argument("--passes", type=int, default=None,
                   help="daemon side: passes (default 57 scaled by the plate's width)")  # fmt: skip
    p.add_argument("--width", type=int, default=500)
    p.add_argument("--batch", type=int, default=20, help="profiles per frame group")
    p.add_argument("--publish-pitch-mm", type=float, default=0.5)
    p.add_argument("--presize", action="store_true", help="tell the acquisition the expected profile count")
    p.add_argument("--stream", choices=["spill", "memory"], default=None,
                   help="daemon side: the cloud streamed pass by pass while acquired, its chunks held in a "
                        "spill file or in memory, then cloud.bin written from them")  # fmt: skip
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--length-mm", type=float, default=6000.0, help="the plate's length (both sides)")
    p.add_argument("--width-mm", type=float, default=2000.0, help="the plate's width (both sides)")
    p.add_argument("--trace", action="store_true", help="worker side: print the stacks at each new RSS peak")
    p.add_argument("--stages", action="store_true",
                   help="worker side: a table of the analysis' stages (time, peak RSS, live numpy heap and the "
                        "arrays each result holds, in bytes per point; tracemalloc slows it a little); daemon "
                        "side: the numpy heap's peak per stage, bytes per raw point")  # fmt: skip
    p.add_argument("--dir", default=None, help="where the daemon side's raw files go")
    p.add_argument("--work", default=None, help="the worker side's work directory")
    args = p.parse_args()
    import structlog

    structlog.configure(
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
        wrapper_class=structlog.make_filtering_bound_logger(30),
    )
    if args.part == "daemon":
        print(json.dumps(daemon_part(args)))
        return 0
    if args.part == "synth":
        print(json.dumps(synth_part(args)))
        return 0
    if args.part == "analysis":
        print(json.dumps(worker_part(args)))
        return 0
    out: dict = {"plate_mm": [args.length_mm, args.width_mm], "publish_pitch_mm": args.publish_pitch_mm}
    common = ["--publish-pitch-mm", str(args.publish_pitch_mm), "--length-mm", str(args.length_mm),
              "--width-mm", str(args.width_mm)]  # fmt: skip
    if args.part in ("all", "daemon"):
        profiles, passes = _daemon_size(args)
        extra = [*common, "--profiles", str(profiles), "--passes", str(passes),
                 "--width", str(args.width), "--batch", str(args.batch), *(["--stages"] if args.stages else [])]  # fmt: skip
        if args.presize:
            extra.append("--presize")
        if args.stream:
            extra += ["--stream", args.stream]
        if args.dir:
            extra += ["--dir", args.dir]
        out.update(_child("daemon", args, extra))
    if args.part in ("all", "worker"):
        with tempfile.TemporaryDirectory(prefix="long-plate-") as tmp:
            work = args.work or tmp
            Path(work).mkdir(parents=True, exist_ok=True)
            extra = [*common, "--work", work, "--seed", str(args.seed), *(["--trace"] if args.trace else []),
                     *(["--stages"] if args.stages else [])]  # fmt: skip
            if not (Path(work) / "cloud.bin").exists():
                out.update(_child("synth", args, extra))
            out.update(_child("analysis", args, extra))
    out["load_avg_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
