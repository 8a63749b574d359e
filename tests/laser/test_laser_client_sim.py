"""The HD8 client against the sensor simulator over loopback TCP: delivery, faults, control, clock.

The simulator is driven through its sockets only: commands and data as the HD8 protocol has them,
faults and counters over its fault channel (``sensor_faults``, ``sensor_stats``). In process, and
said where it happens, are only what no protocol carries: the simulator's ground truth (its true
clock, ``sensor_time_us`` / ``exposure_mid_true_s``, to check the stamps against), the hardware
trigger edge (``sim.trigger``, an electrical input on a real sensor), the settings it took, and its
restart."""

from __future__ import annotations

import asyncio
import struct
import time

import numpy as np
import pytest
import structlog.testing
from hypothesis import given, settings
from hypothesis import strategies as st
from laser_helpers import collect, looking_down, run, sensor_faults, sensor_stats, sim_and_client

from drivers.laser import protocol as P
from drivers.laser.client import HD8Client, HD8ClientConfig
from drivers.laser.sim.scene import plane_scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig, fixed_pose
from drivers.laser.source import ProfileBatch, SourceEventKind
from drivers.sim.fault_channel import send_fault_request
from tests.support.waits import wait_until

# A long backlog: on a loaded CI machine the simulator may fall behind real time for a moment; it must
# then deliver late rather than skip frames (skipping is tested separately, with a short backlog).
FAST = SimConfig(rate_hz=1000.0, outlier_probability=0.0, seed=1, max_backlog_s=10.0)


def frames_of(batches: list[ProfileBatch]) -> np.ndarray:
    return np.concatenate([b.frame_index for b in batches]).astype(np.int64)


def test_client_receives_every_frame_in_order_at_1khz() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (_sim, client):
            await client.start()
            batches = await collect(client, 1500)
            fi = frames_of(batches)
            assert fi[0] == 0
            np.testing.assert_array_equal(fi, np.arange(len(fi)))
            st = client.stats
            assert st.gaps == 0 and st.decode_errors == 0 and st.duplicates_dropped == 0
            assert st.overflow_frames == 0 and st.reconnects == 0
            assert 500 < st.rate_hz < 1500  # loose: the machine may be shared
            b = ProfileBatch.concat(batches)
            assert b.x_mm.shape == (len(fi), 500) and b.x_mm.dtype == np.float32
            assert np.all(np.diff(b.host_recv_ns) >= 0)

    run(scenario())


def test_disconnect_mid_stream_resumes_without_duplicates_or_reordering() -> None:
    async def scenario() -> None:
        cfg = HD8ClientConfig(reconnect_initial_s=0.02)
        async with sim_and_client(config=FAST, client_config=cfg) as (sim, client):
            events = []
            client.add_listener(events.append)
            await client.start()
            first = await collect(client, 100)
            await sensor_faults(sim, disconnect_after_frames=150)
            rest = await collect(client, 600)
            fi = frames_of(first + rest)
            np.testing.assert_array_equal(fi, np.arange(fi[0], fi[0] + len(fi)))  # no loss, no dup
            assert client.stats.reconnects == 1
            assert client.stats.gaps == 0
            kinds = [e.kind for e in events]
            assert SourceEventKind.DISCONNECTED in kinds and SourceEventKind.RECONNECTED in kinds
            assert (await sensor_stats(sim))["data_connections"] == 2

    run(scenario())


def test_corrupted_frame_group_is_skipped_and_counted() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            await client.start()
            await collect(client, 50)
            await sensor_faults(sim, corrupt_groups=1, corrupt_mode="payload")
            batches = await collect(client, 300)
            assert client.stats.decode_errors == 1
            assert client.stats.reconnects == 0  # framing stayed intact: no reconnect needed
            fi = frames_of(batches)
            assert np.all(np.diff(fi) > 0)
            assert client.stats.gaps == 1 and client.stats.missing_frames >= 1

    run(scenario())


def test_broken_framing_reconnects_and_replays_the_lost_frames() -> None:
    async def scenario() -> None:
        cfg = HD8ClientConfig(reconnect_initial_s=0.02)
        async with sim_and_client(config=FAST, client_config=cfg) as (sim, client):
            await client.start()
            first = await collect(client, 50)
            await sensor_faults(sim, corrupt_groups=1, corrupt_mode="framing")
            rest = await collect(client, 400)
            fi = frames_of(first + rest)
            np.testing.assert_array_equal(fi, np.arange(fi[0], fi[0] + len(fi)))
            assert client.stats.decode_errors == 0 and client.stats.reconnects == 1

    run(scenario())


def test_dropped_frames_show_up_as_a_counted_gap() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            events = []
            client.add_listener(events.append)
            await client.start()
            await collect(client, 20)
            await sensor_faults(sim, drop_frames=7)
            await collect(client, 200)
            assert client.stats.gaps == 1 and client.stats.missing_frames == 7
            gap = [e for e in events if e.kind == SourceEventKind.GAP]
            assert gap and gap[0].detail["missing_frames"] == 7

    run(scenario())


def test_watchdog_reports_stall_and_resumption() -> None:
    async def scenario() -> None:
        cfg = HD8ClientConfig(watchdog_timeout_s=0.15)
        async with sim_and_client(config=FAST, client_config=cfg) as (sim, client):
            await client.start()
            await collect(client, 20)
            await sensor_faults(sim, stall_s=0.5, stall_acquire=True)
            kinds = []
            while SourceEventKind.RESUMED not in kinds:
                kinds.append((await asyncio.wait_for(client.events.get(), 3.0)).kind)
            assert kinds.index(SourceEventKind.STALLED) < kinds.index(SourceEventKind.RESUMED)
            assert client.stats.rate_hz == 0.0  # not the stale rate from before the stall
            batches = await collect(client, 300)
            # Acquisition went on during the stall: late, but nothing lost.
            assert client.stats.gaps == 0
            assert len(batches) > 0

    run(scenario())


def test_close_ends_promptly_while_the_stream_is_busy() -> None:
    """Regression: on Python 3.11 ``asyncio.wait_for`` dropped a cancellation that arrived as the read
    inside it completed; with a backlog streaming in, close() hung until a second cancel came (20 s in
    the stall test above). close() must end its tasks well within its own bounded wait."""
    from drivers.laser.client import _CLOSE_TIMEOUT_S

    async def scenario() -> None:
        sim = LaserSimulator(plane_scene(0.0), fixed_pose(looking_down(100.0)), config=FAST, fault_port=0)
        ctl, dat = await sim.start()
        client = HD8Client("127.0.0.1", ctl, dat, config=HD8ClientConfig(watchdog_timeout_s=0.15))
        try:
            await client.connect()
            await client.start()
            await collect(client, 20)
            await sensor_faults(sim, stall_s=0.5, stall_acquire=True)
            while (await asyncio.wait_for(client.events.get(), 3.0)).kind != SourceEventKind.RESUMED:
                pass
            await collect(client, 300)  # the held backlog is streaming in
            tasks = list(client._tasks)  # the client's own tasks: this checks how they end
            with structlog.testing.capture_logs() as logs:
                closing = asyncio.create_task(client.close())
                # generous: a close that hangs is stuck for good; a slow machine only delays it
                done, _ = await asyncio.wait({closing}, timeout=_CLOSE_TIMEOUT_S * 10)
            assert closing in done
            # every task ended on its first cancellation: none was left for the bounded wait to give up on
            assert tasks and all(t.done() for t in tasks)
            assert not [e for e in logs if e["event"] == "hd8_close_tasks_stuck"], logs
        finally:
            await client.close()
            await sim.stop()

    run(scenario())


def test_buffer_overflow_is_counted_and_reported_not_silent() -> None:
    async def scenario() -> None:
        cfg = HD8ClientConfig(buffer_profiles=30)
        async with sim_and_client(config=FAST, client_config=cfg) as (_sim, client):
            await client.start()
            # nobody reads: the sensor streams on until the buffer has overflowed
            await wait_until(
                lambda: (
                    client.stats.overflow_frames > 0
                    and client.stats.frames + client.stats.overflow_frames > 100
                ),
                0.3,
                "100 frames streamed and the buffer overflowed",
            )
            st = client.stats
            assert st.overflow_batches > 0 and st.overflow_frames > 0
            assert st.frames + st.overflow_frames > 100
            assert st.frames <= 30  # the bound holds
            kinds = set()
            while not client.events.empty():
                kinds.add(client.events.get_nowait().kind)
            assert SourceEventKind.OVERFLOW in kinds

    run(scenario())


def test_configure_applies_rate_and_rejects_changes_while_running() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            assert client.info is not None and client.info.width == 500 and client.info.x_pitch_nm == 100_000
            await client.configure(rate_hz=250.0, exposure_ns=3_000_000, profile_format="uniform")
            assert sim.settings.rate_hz == 250.0 and sim.settings.exposure_ns == 3_000_000  # rate first
            await client.configure(rate_hz=2000.0 / 3.0, exposure_ns=300_000)  # exposure first
            assert sim.settings.rate_hz == 666.667 and sim.settings.exposure_ns == 300_000
            await client.start()
            with pytest.raises(P.CommandError, match="INVALID_STATE"):
                await client.configure(rate_hz=100.0)
            with pytest.raises(P.CommandError, match=r"INVALID_PARAMETER.*exposure_ns"):
                await client.configure(exposure_ns=50)
            state = await client.get_state()
            assert state.state == P.SensorState.RUNNING
            await client.stop()
            assert (await client.get_state()).state == P.SensorState.READY

    run(scenario())


def test_point_pair_format_delivers_unresampled_points() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (_sim, client):
            await client.configure(profile_format=P.ProfileFormat.POINTS)
            await client.start()
            b = ProfileBatch.concat(await collect(client, 20))
            x = b.x_mm[b.valid]
            assert np.all(np.diff(b.x_mm[0][b.valid[0]]) > 0)  # the fan sweeps x monotonically
            assert -40 < x.min() < -20 and 20 < x.max() < 40
            np.testing.assert_allclose(np.nanmean(b.z_mm), 100.0, atol=0.01)

    run(scenario())


def test_simulator_answers_malformed_commands_and_keeps_serving() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            r, w = await asyncio.open_connection(client.host, client.control_port)
            w.write(P.encode_command(0x4999))  # unknown command
            w.write(P.encode_command(P.CommandId.SET_RATE, b"\x01"))  # short parameter
            w.write(P.encode_command(P.CommandId.START, b"junk"))  # payload where none is allowed
            await w.drain()
            framer = P.MessageFramer()
            replies: list[P.Message] = []
            while len(replies) < 3:
                replies += framer.feed(await asyncio.wait_for(r.read(4096), 2.0))
            statuses = [P.decode_reply(m).status for m in replies]
            assert statuses == [P.Status.UNKNOWN_COMMAND, P.Status.MALFORMED, P.Status.MALFORMED]
            assert b"SET_RATE" in replies[1].data
            w.write(struct.pack("<IH", 2, 0))  # broken framing: only this connection is dropped
            await w.drain()
            assert await asyncio.wait_for(r.read(), 2.0) == b""
            w.close()
            assert (await sensor_stats(sim))["malformed_commands"] == 4
            await client.command(P.CommandId.KEEP_ALIVE)  # the other connection still works
            await client.start()
            assert len(frames_of(await collect(client, 10))) >= 10

    run(scenario())


def test_simulator_drops_a_data_client_that_sends_no_subscribe() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            r, w = await asyncio.open_connection(client.host, client.data_port)
            w.write(P.encode_command(P.CommandId.START))  # not a SUBSCRIBE
            await w.drain()
            assert await asyncio.wait_for(r.read(), 2.0) == b""
            w.close()
            assert (await sensor_stats(sim))["malformed_commands"] == 1

    run(scenario())


def test_sensor_clock_has_offset_drift_and_mid_exposure_stamps() -> None:
    cfg = SimConfig(
        rate_hz=500.0, exposure_ns=1_000_000, clock_offset_us=5_000_000, clock_drift_ppm=200.0, seed=2
    )

    async def scenario() -> None:
        async with sim_and_client(config=cfg) as (sim, client):
            await client.start()
            b = ProfileBatch.concat(await collect(client, 200))
            t_us = b.sensor_time_us.astype(np.float64)
            period_us = np.diff(t_us) / np.diff(b.frame_index.astype(np.float64))
            # 2 ms period stretched by 200 ppm (the stamps are integer us)
            np.testing.assert_allclose(period_us.mean(), 2000.0 * (1 + 200e-6), atol=0.01)
            truth = sim.sensor_time_us(sim.exposure_mid_true_s(b.frame_index))
            np.testing.assert_allclose(t_us, np.floor(truth), atol=1.0)
            assert np.all(b.exposure_ns == 1_000_000)
            ts = await client.get_timestamp()
            assert ts.sensor_time_us > t_us[-1]

    run(scenario())


def test_hd8_millisecond_counter_wraps_mid_stream() -> None:
    # The counter starts 0.5 s before its wrap when the simulator is built; 1.2 s of frames cross it.
    cfg = SimConfig(rate_hz=1000.0, hd8_counter_start_ms=2**32 - 500, seed=3, max_backlog_s=10.0)

    async def scenario() -> None:
        async with sim_and_client(config=cfg) as (_sim, client):
            await client.start()
            b = ProfileBatch.concat(await collect(client, 1200))
            ms = b.hd8_ms.astype(np.int64)
            assert ms[0] > 2**31 and ms[-1] < 2**31  # wrapped inside this stream
            unwrapped = np.unwrap(ms, period=2**32)
            assert np.all(np.diff(unwrapped) >= 0)
            np.testing.assert_allclose(np.diff(unwrapped).mean(), 1.0, atol=0.05)
            await client.reset_timestamp()
            assert (await client.get_timestamp()).hd8_ms < 500  # counted from 0 again

    run(scenario())


def test_timestamp_jump_fault_steps_the_sensor_clock() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            await client.start()
            a = ProfileBatch.concat(await collect(client, 30))
            await sensor_faults(sim, clock_jump_us=250_000)
            b = ProfileBatch.concat(await collect(client, 100))
            d = np.diff(np.concatenate([a.sensor_time_us, b.sensor_time_us]).astype(np.int64))
            assert d.max() > 250_000 and np.median(d) == pytest.approx(1000, abs=2)

    run(scenario())


def test_sensor_time_from_ms_counter_has_millisecond_resolution() -> None:
    cfg = SimConfig(rate_hz=300.0, sensor_time_from_ms_counter=True, seed=4)

    async def scenario() -> None:
        async with sim_and_client(config=cfg) as (_sim, client):
            await client.start()
            b = ProfileBatch.concat(await collect(client, 30))
            assert np.all(b.sensor_time_us % 1000 == 0)
            assert np.all(b.status & P.StatusBits.TIME_FROM_MS_COUNTER)

    run(scenario())


def test_client_connect_to_closed_port_raises_connection_error() -> None:
    async def scenario() -> None:
        srv = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
        port = srv.sockets[0].getsockname()[1]
        srv.close()
        await srv.wait_closed()
        client = HD8Client("127.0.0.1", port, port)
        with pytest.raises(OSError):
            await client.connect()
        await client.close()

    run(scenario())


def test_start_fails_cleanly_when_the_data_port_is_closed() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            srv = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
            dead_port = srv.sockets[0].getsockname()[1]
            srv.close()
            await srv.wait_closed()
            client.data_port = dead_port
            with pytest.raises(OSError):
                await client.start()
            assert not sim.running  # START was never sent
            client.data_port = sim._servers[1].sockets[0].getsockname()[1]
            await client.start()  # a second attempt works
            assert len(frames_of(await collect(client, 5))) >= 5

    run(scenario())


def test_producer_overrun_skips_frames_and_flags_them() -> None:
    cfg = SimConfig(rate_hz=1000.0, max_backlog_s=0.05, outlier_probability=0.0, seed=8)
    blocked = {"done": False}

    def slow_pose(t: np.ndarray) -> np.ndarray:
        if not blocked["done"] and t[0] - t0["t"] > 0.05:
            blocked["done"] = True
            time.sleep(0.2)  # the sensor's processing falls 200 frames behind once
        return np.repeat(looking_down(100.0)[None], len(t), axis=0)

    t0 = {"t": time.monotonic()}

    async def scenario() -> None:
        sim = LaserSimulator(plane_scene(0.0), slow_pose, config=cfg, fault_port=0)
        ctl, dat = await sim.start()
        client = HD8Client("127.0.0.1", ctl, dat)
        try:
            await client.connect()
            t0["t"] = time.monotonic()
            await client.start()
            first = await collect(client, 300)
            assert (await sensor_stats(sim))["overrun_frames"] >= 100
            # every frame the client took in, so its gap count and the frames are the same set (a
            # later, small overrun on a loaded machine counts beyond the first 300)
            await client.stop()
            await client.close()
            b = ProfileBatch.concat(first + [batch async for batch in client])
            d = np.diff(b.frame_index.astype(np.int64))
            jumps = np.flatnonzero(d > 1)
            assert d.max() >= 100  # the long block, 200 frames minus the 50 kept in the backlog
            assert client.stats.missing_frames == int((d[jumps] - 1).sum())
            # every frame after a skip carries the OVERRUN bit, and no other frame does
            overrun = (b.status & P.StatusBits.OVERRUN) != 0
            assert np.array_equal(np.flatnonzero(overrun[1:]), jumps)
        finally:
            await client.close()
            await sim.stop()

    run(scenario())


def test_a_failing_pose_source_stops_acquisition_but_not_the_endpoint() -> None:
    def bad_pose(t: np.ndarray) -> np.ndarray:
        return np.zeros((len(t), 3, 3))  # wrong shape

    async def scenario() -> None:
        sim = LaserSimulator(plane_scene(0.0), bad_pose, config=FAST)
        ctl, dat = await sim.start()
        client = HD8Client("127.0.0.1", ctl, dat, config=HD8ClientConfig(watchdog_timeout_s=0.1))
        try:
            await client.connect()
            await client.start()
            event = await asyncio.wait_for(client.events.get(), 2.0)
            assert event.kind == SourceEventKind.STALLED
            assert (await client.get_state()).state == P.SensorState.READY  # the control port still answers
        finally:
            await client.close()
            await sim.stop()

    run(scenario())


def test_close_ends_a_running_iteration() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (_sim, client):
            await client.start()

            got: list[int] = []

            async def consume() -> int:
                async for b in client:
                    got.append(len(b))
                return sum(got)

            task = asyncio.create_task(consume())
            await wait_until(lambda: got, 0.1, "the iteration under way")
            await client.close()
            assert await asyncio.wait_for(task, 2.0) > 0

    run(scenario())


@settings(max_examples=20, deadline=None)
@given(
    runs=st.lists(st.tuples(st.integers(-5, 5), st.integers(1, 6)), min_size=1, max_size=12),
)
def test_client_delivers_strictly_increasing_frames_whatever_the_sensor_repeats_or_skips(
    runs: list[tuple[int, int]],
) -> None:
    # Each run starts `offset` frames after the previous run's last frame (<= 0: a replay overlap).
    groups = []
    last = -1
    for offset, n in runs:
        first = max(0, last + offset)
        groups.append(np.arange(first, first + n))
        last = first + n - 1
    scale = P.ProfileScale(100_000, 2000, 0, 100_000)
    blob = b"".join(
        P.encode_frame_group(
            frame_index=g.astype(np.uint64),
            sensor_time_us=g.astype(np.uint64),
            hd8_ms=g.astype(np.uint32),
            encoder=np.zeros(len(g), np.int64),
            status=np.zeros(len(g), np.uint32),
            exposure_ns=np.ones(len(g), np.uint32),
            scale=scale,
            z_raw=np.zeros((len(g), 3), np.int16),
        )
        for g in groups
    )
    sent = np.concatenate(groups)
    # What must come out: each frame that is newer than everything sent before it, in order.
    expected = sent[sent > np.maximum.accumulate(np.concatenate([[-1], sent[:-1]]))]
    jumps = np.diff(np.concatenate([[expected[0] - 1], expected])) - 1

    async def scenario() -> None:
        async def control(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            framer = P.MessageFramer()
            while chunk := await r.read(4096):
                for m in framer.feed(chunk):
                    w.write(P.encode_reply(m.type, P.Status.OK))

        async def data(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            await r.read(14)
            w.write(blob)
            await w.drain()
            await r.read()

        ctl = await asyncio.start_server(control, "127.0.0.1", 0)
        dat = await asyncio.start_server(data, "127.0.0.1", 0)
        client = HD8Client("127.0.0.1", ctl.sockets[0].getsockname()[1], dat.sockets[0].getsockname()[1])
        await client._open_control()
        await client.start()
        got = frames_of(await collect(client, len(expected)))
        np.testing.assert_array_equal(got, expected)
        assert client.stats.duplicates_dropped == len(sent) - len(expected)
        # Joining a stream at frame k is not a loss: only jumps after the first frame count.
        assert client.stats.missing_frames == int(jumps[1:].sum())
        await client.close()
        for s in (ctl, dat):
            s.close()
        await asyncio.sleep(0.01)  # stays: cleanup, the closed servers' handlers end before the loop

    run(scenario())


def test_random_drops_and_corruption_are_counted_and_never_break_order() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            await sensor_faults(sim, drop_probability=0.05, corrupt_probability=0.1)
            await client.start()
            st = client.stats
            batches = []
            # How many groups a run holds depends on the machine's load; read until both faults hit.
            while st.decode_errors == 0 or st.missing_frames == 0 or len(batches) < 50:
                batches += await collect(client, 1)
            b = ProfileBatch.concat(batches)
            assert np.all(np.diff(b.frame_index.astype(np.int64)) > 0)
            assert st.reconnects == 0 and st.duplicates_dropped == 0
            assert (await sensor_stats(sim))["frames_dropped_fault"] > 0

    run(scenario())


def test_client_follows_a_sensor_that_restarted_on_the_same_ports() -> None:
    async def scenario() -> None:
        cfg = HD8ClientConfig(reconnect_initial_s=0.02, keepalive_interval_s=0.1)
        async with sim_and_client(config=FAST, client_config=cfg) as (sim, client):
            await client.start()
            before = frames_of(await collect(client, 300))
            ctl, dat = client.control_port, client.data_port
            await sim.stop()
            sim2 = LaserSimulator(
                plane_scene(0.0),
                fixed_pose(looking_down(100.0)),
                config=FAST,
                control_port=ctl,
                data_port=dat,
            )
            await sim2.start()
            try:
                kinds = []
                while SourceEventKind.RESTARTED not in kinds:
                    kinds.append((await asyncio.wait_for(client.events.get(), 5.0)).kind)
                after = frames_of(await collect(client, 50))
                assert before[-1] >= 299 and after[0] < 50  # numbering restarted, frames accepted
                assert np.all(np.diff(after) == 1)
                assert sim2.running  # the client started the new sensor again
            finally:
                await sim2.stop()

    run(scenario())


def test_network_jitter_delays_groups_without_reordering_them() -> None:
    cfg = SimConfig(
        rate_hz=500.0, network_jitter_s=0.002, outlier_probability=0.0, seed=9, max_backlog_s=10.0
    )

    async def scenario() -> None:
        async with sim_and_client(config=cfg) as (sim, client):
            await client.start()
            b = ProfileBatch.concat(await collect(client, 200))
            fi = b.frame_index.astype(np.int64)
            np.testing.assert_array_equal(fi, np.arange(fi[0], fi[0] + len(fi)))
            # receive time minus true mid-exposure time: latency spread grows with the jitter
            true_ns = sim.exposure_mid_true_s(b.frame_index) * 1e9
            latency_ms = (b.host_recv_ns - true_ns) / 1e6
            assert latency_ms.min() > 0 and np.percentile(latency_ms, 90) - latency_ms.min() > 1.0

    run(scenario())


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_frames_held_by_a_stall_are_released_in_order_under_network_jitter(seed) -> None:
    """Regression (issue 10's stalled-sensor fault case): the groups held during a stall are released
    together; with network jitter they were scheduled at equal times, and the event loop's timer heap
    does not keep insertion order among equal times, so the client saw them out of order, counted
    them missing and then dropped them as stale."""
    cfg = SimConfig(
        rate_hz=500.0, network_jitter_s=0.0003, outlier_probability=0.0, seed=seed, max_backlog_s=10.0
    )

    async def scenario() -> None:
        ccfg = HD8ClientConfig(watchdog_timeout_s=0.15)
        async with sim_and_client(config=cfg, client_config=ccfg) as (sim, client):
            await client.start()
            first = await collect(client, 20)
            await sensor_faults(sim, stall_s=0.4, stall_acquire=True)
            b = ProfileBatch.concat([*first, *(await collect(client, 500))])
            fi = b.frame_index.astype(np.int64)
            np.testing.assert_array_equal(fi, np.arange(fi[0], fi[0] + len(fi)))
            st = client.stats
            assert (st.gaps, st.missing_frames, st.duplicates_dropped) == (0, 0, 0), st

    run(scenario())


def test_external_trigger_mode_gives_one_frame_per_edge_exposed_at_the_edge() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            with pytest.raises(P.CommandError, match="encoder"):
                await client.configure(trigger_mode=P.TriggerMode.ENCODER)
            await client.configure(trigger_mode=P.TriggerMode.EXTERNAL)
            await client.start()
            await asyncio.sleep(0.05)  # stays: time passing in which nothing must happen
            assert client.stats.frames == 0  # no edge, no frame
            edges = []
            for _ in range(12):
                t = time.monotonic()
                assert sim.trigger(t)
                assert not sim.trigger(t + 1e-4)  # too soon after the last edge: ignored
                edges.append(t)
                await asyncio.sleep(0.004)  # stays: pacing, edges apart as a trigger's are
            b = ProfileBatch.concat(await collect(client, 12))
            assert len(b) == 12 and (await sensor_stats(sim))["triggers_ignored"] == 12
            truth = sim.sensor_time_us(np.asarray(edges) + FAST.exposure_ns * 0.5e-9)
            np.testing.assert_allclose(b.sensor_time_us.astype(np.float64), np.floor(truth), atol=1.0)

    run(scenario())


@pytest.mark.slow  # spawns a process that imports open3d
@pytest.mark.process
def test_rendering_in_a_worker_process_streams_the_same_scene() -> None:
    cfg = SimConfig(rate_hz=500.0, render_process=True, outlier_probability=0.0, seed=10)

    async def scenario() -> None:
        async with sim_and_client(config=cfg) as (_sim, client):
            await client.start()
            b = ProfileBatch.concat(await collect(client, 100))
            fi = b.frame_index.astype(np.int64)
            np.testing.assert_array_equal(fi, np.arange(fi[0], fi[0] + len(fi)))
            assert b.valid.mean() > 0.99
            assert abs(float(np.nanmean(b.z_mm)) - 100.0) < 0.005

    run(scenario(), timeout_s=60.0)


def test_fault_channel_refuses_bad_requests_and_changes_nothing_then() -> None:
    async def scenario() -> None:
        async with sim_and_client(config=FAST) as (sim, client):
            address = sim.fault_address
            for bad in ({"laser": {"bogus": 1}}, {"laser": {"drop_probability": 1.5}}, {"egm": {}}, [1]):
                reply = await send_fault_request(address, bad)
                assert not reply["ok"] and reply["error"], (bad, reply)
            state = await sensor_faults(sim)
            assert state["faults"]["drop_probability"] == 0.0 and state["faults"]["stall_remaining_s"] == 0.0
            set_ = await sensor_faults(sim, drop_frames=3, disconnect_after_frames=10)
            assert set_["faults"]["drop_frames"] == 3 and set_["faults"]["disconnect_after_frames"] == 10
            assert (await sensor_faults(sim, disconnect_after_frames=0))["faults"][
                "disconnect_after_frames"
            ] is None
            await client.start()
            fi = frames_of(await collect(client, 50))
            # the first three frames never left the sensor; the disarmed disconnect never came
            assert fi[0] == 3 and np.all(np.diff(fi) == 1) and client.stats.reconnects == 0

    run(scenario())
