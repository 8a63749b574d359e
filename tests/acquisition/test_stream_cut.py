"""The scan's cloud cut pass by pass (cellctl/daemon/stream.py): the chunks are the whole cloud."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cellctl.acquisition.assembly import AssembledBatch, AssembledScan
from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan, pass_end_cut
from cellctl.acquisition.spill import release
from cellctl.api.cloud_codec import CloudMeta, concat_encoded, decode_cloud, write_concatenated
from cellctl.daemon.stream import ScanStream, _split
from cellctl.jobstore.rawstore import RawWriter
from tests.support.waits import wait_until

W = 40  # points per profile


def _batch(first: int, pass_ids: list[int], rng: np.random.Generator) -> AssembledBatch:
    n = len(pass_ids)
    xyz = rng.normal(0, 100, (n, W, 3)).astype(np.float32)
    valid = rng.random((n, W)) > 0.1
    xyz[~valid] = np.nan
    return AssembledBatch(
        profile_index=np.arange(first, first + n, dtype=np.int64),
        frame_index=np.arange(first, first + n, dtype=np.uint64),
        pass_id=np.asarray(pass_ids, dtype=np.int32),
        t_ns=(10**9 + np.arange(first, first + n, dtype=np.int64) * 5_000_000),
        xyz_mm=xyz,
        valid=valid,
        sensor_pos_mm=np.zeros((n, 3), np.float32),
    )


def _scan_batches(seed: int = 0) -> list[AssembledBatch]:
    """Transit, pass 0, transit, pass 1, pass 2 (no transit between), transit; edge pass 3 last."""
    rng = np.random.default_rng(seed)
    pids = [-1] * 7 + [0] * 30 + [-1] * 9 + [1] * 25 + [2] * 25 + [-1] * 5 + [3] * 20 + [-1] * 6
    out, i = [], 0
    for size in rng.integers(1, 9, 200):  # batches of 1 to 8 profiles, cut anywhere
        if i >= len(pids):
            break
        out.append(_batch(i, pids[i : i + int(size)], rng))
        i += int(size)
    return out


def test_pass_end_cut_finds_the_last_finished_pass() -> None:
    assert pass_end_cut(np.array([-1, -1, 0, 0])) is None  # pass 0 still open
    assert pass_end_cut(np.array([-1, 0, 0, -1])) == (3, 0)
    assert pass_end_cut(np.array([0, 0, 1, 1, -1, 2])) == (4, 1)  # 1 ended after 0: the later cut
    assert pass_end_cut(np.array([-1, -1, -1])) is None
    assert pass_end_cut(np.array([5])) is None


def test_split_cuts_inside_a_batch() -> None:
    batches = _scan_batches()
    for n in (0, 1, 13, 50, sum(len(b.t_ns) for b in batches)):
        head, tail = _split(batches, n)
        assert sum(len(b.t_ns) for b in head) == n
        whole = AssembledScan.concat(batches)
        again = AssembledScan.concat(head + tail)
        assert whole.digest() == again.digest()


class _Acq:
    """An acquisition seen from outside: its batches so far."""

    def __init__(self) -> None:
        self.batches: list[AssembledBatch] = []
        self.asked: list[int] = []  # the positions a reader asked from: what it has taken

    def batches_since(self, k: int) -> list[AssembledBatch]:
        self.asked.append(k)
        return self.batches[k:]


class _Dispatcher:
    def __init__(self) -> None:
        self.chunks: list[tuple[int, bytes, int]] = []
        self.last_pass: list[bool] = []
        self.ended = False
        self.abandoned: str | None = None

    def stream_chunk(
        self, job_id: str, pass_index: int, payload: bytes, points: int, *, last_pass: bool = False
    ) -> int:
        assert not self.ended
        self.chunks.append((pass_index, payload, points))
        self.last_pass.append(last_pass)
        return len(self.chunks) - 1

    def stream_payloads(self, job_id: str) -> list[bytes]:
        if self.ended:  # as the real one: a worker may report as soon as the stream ends
            raise ValueError(f"job {job_id!r} is not a pending streamed job")
        return [c[1] for c in self.chunks]

    def end_stream(self, job_id: str) -> None:
        self.ended = True

    def abandon(self, job_id: str, reason: str) -> None:
        self.abandoned = reason


@pytest.mark.parametrize(("seed", "spilled"), [(0, False), (1, False), (2, False), (0, True)])
def test_the_chunks_concatenated_are_the_whole_cloud_byte_for_byte(
    seed: int, spilled: bool, tmp_path
) -> None:
    # spilled: the stream follows a scan with raw files, its chunks kept in a file beside them (issue 42)
    writer = RawWriter(tmp_path / "raw", {}) if spilled else None
    settings = PublishSettings(native_pitch_mm=0.1, pitch_mm=0.2, edge_pitch_mm=0.4)
    batches = _scan_batches(seed)
    meta = CloudMeta(cell_id="cell-1")

    async def go() -> _Dispatcher:
        disp, acq = _Dispatcher(), _Acq()
        fut = asyncio.get_running_loop().create_future()
        stream = ScanStream(disp, fut, job_id="J", plate_id="P", settings=settings, first_edge_pass=3,
                            meta=meta, poll_s=0.01, last_pass=3)  # fmt: skip
        stream.follow(acq, writer)
        for b in batches:  # the scan goes on: batches arrive, the stream cuts behind them
            acq.batches.append(b)
            await asyncio.sleep(0.005)  # stays: pacing, batches arrive as a scan's do
        await wait_until(lambda: len(disp.chunks) >= 4, 0.05, "the four passes cut behind the scan")
        await stream.finish()
        assert stream.finished and stream.points == sum(c[2] for c in disp.chunks)
        # the chunks for cloud.bin stay with the stream: the job may be reported and forgotten
        assert stream.payloads == [c[1] for c in disp.chunks]
        return disp

    disp = asyncio.run(go())
    assert disp.ended and disp.abandoned is None
    passes = [c[0] for c in disp.chunks]
    assert passes[:4] == [0, 1, 2, 3] and passes[-1] == -1 and len(passes) == 5, passes
    # the chunk completing the plan's last pass says so: the worker may analyse before the retract ends
    assert disp.last_pass == [False, False, False, True, False]
    whole = AssembledScan.concat(batches)
    steps = column_steps(whole.pass_id, 3, settings)
    expected, n = encode_scan(whole, job_id="J", plate_id="P", column_step=steps, meta=meta)
    got = concat_encoded([c[1] for c in disp.chunks])
    assert bytes(got) == bytes(expected)
    assert all(isinstance(c[1], memoryview) for c in disp.chunks) == spilled
    write_concatenated(tmp_path / "cloud.bin", [c[1] for c in disp.chunks], read=release)
    assert (tmp_path / "cloud.bin").read_bytes() == bytes(expected)  # cloud.bin as the handover writes it
    if writer is not None:
        writer.close()
    assert decode_cloud(got).n_points == n
    # each chunk's rows: the transit before a pass and the pass, nothing of the next pass
    first = decode_cloud(disp.chunks[0][1])
    assert set(np.unique(first.pass_id).tolist()) == {0}


def test_a_stream_abandoned_before_the_end_gives_the_job_up() -> None:
    async def go() -> _Dispatcher:
        disp, acq = _Dispatcher(), _Acq()
        fut = asyncio.get_running_loop().create_future()
        stream = ScanStream(disp, fut, job_id="J", plate_id="P", settings=PublishSettings(),
                            first_edge_pass=None, meta=CloudMeta(), poll_s=0.01)  # fmt: skip
        stream.follow(acq, None)
        acq.batches.extend(_scan_batches()[:3])
        await wait_until(lambda: 3 in acq.asked, 0.05, "the stream taking the three batches")
        await stream.abandon("aborted")
        await stream.abandon("again")  # once only
        return disp

    disp = asyncio.run(go())
    assert disp.abandoned == "aborted" and not disp.ended


def test_the_worker_of_a_streamed_job_is_named_whether_or_not_it_has_reported() -> None:
    from cellctl.api.models import ReportEnvelope
    from cellctl.daemon.handover import _streamed_worker

    class Disp:
        pending: list[str] = []

        def assignment(self, job_id: str) -> tuple[str | None, int]:
            return "w-holding", 1

    async def go() -> tuple[str | None, str | None, str | None]:
        fut = asyncio.get_running_loop().create_future()
        d = Disp()
        d.pending = ["J"]
        holding = _streamed_worker(d, "J", fut)
        d.pending = []  # reported and forgotten before the handover looked (a fast analysis)
        before = _streamed_worker(d, "J", fut)
        fut.set_result(
            ReportEnvelope(job_id="J", plate_id="P", worker_id="w-reported", attempt=1, ok=False, error="x")
        )
        return holding, before, _streamed_worker(d, "J", fut)

    assert asyncio.run(go()) == ("w-holding", None, "w-reported")
