"""The GigE Vision source against Aravis's own fake device (arv-fake-gv-camera-0.8) on 127.0.0.1.

The fake device is a third-party GigE Vision implementation (GVCP, GVSP, the GenICam XML over the
wire); a profiler description (drivers.laser.sim.gige_xml) adds the SFNC Scan3dControl features over
its registers, and its stock diagonal ramp (Mono16: ``256 * (column + block id + row) mod 65535``)
provides the range rows, so every converted point can be checked.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from drivers.laser.gige import (
    GigeProfileSource,
    GigeSourceConfig,
    MissingFeatureError,
    NotAProfilerError,
    PixelFormatError,
    discover,
)
from drivers.laser.gige.errors import DeviceNotFoundError
from drivers.laser.source import SourceEventKind
from tests.laser.gige_helpers import (
    A_OFFSET,
    A_SCALE,
    ADDRESS,
    C_OFFSET,
    C_SCALE,
    fake_device,
    profiler_xml,
)
from tests.laser.laser_helpers import collect, run

pytestmark = [pytest.mark.process, pytest.mark.slow]

#: the fake device's ramp is exact at 10 ms exposure (its gain is 1 + log10(exposure / 10 ms))
RAMP_EXPOSURE_NS = 10_000_000


def _config(**kw) -> GigeSourceConfig:
    base = dict(rows_per_buffer=100, packet_size=8192, watchdog_timeout_s=0.3, lost_after_s=1.0)
    return GigeSourceConfig(**{**base, **kw})


def _raw_codes(z_mm: np.ndarray) -> np.ndarray:
    return np.rint(np.nan_to_num((z_mm - C_OFFSET) / C_SCALE, nan=-1.0)).astype(np.int64)  # -1: no return


def test_discovery_finds_the_fake_device_on_loopback(tmp_path):
    with fake_device("WT49DISC", profiler_xml(tmp_path)):
        found = [d for d in discover() if d["serial"] == "WT49DISC"]
    assert found and found[0]["address"] == ADDRESS and found[0]["protocol"] == "GigEVision"
    assert found[0]["vendor"] == "Aravis"


def test_a_plain_camera_is_refused_as_not_a_profiler_naming_the_missing_features():
    async def go():
        src = GigeProfileSource(ADDRESS)
        with pytest.raises(NotAProfilerError, match="Scan3dCoordinateScale") as err:
            await src.connect()
        assert "Scan3dCoordinateSelector" in err.value.missing
        await src.close()

    with fake_device("WT49PLAIN"):  # Aravis's stock description: an area camera
        run(go())


def test_no_device_at_the_address_is_a_clear_error():
    async def go():
        src = GigeProfileSource("127.0.0.1")
        with pytest.raises(DeviceNotFoundError, match=r"127\.0\.0\.1"):
            await src.connect()

    run(go())


def test_region_line_rate_and_exposure_from_configuration_are_what_the_device_reports(tmp_path):
    async def go():
        src = GigeProfileSource(ADDRESS, config=_config(rows_per_buffer=50))
        await src.connect()
        await src.configure(rate_hz=5000.0, exposure_ns=2_000_000, width=300, x_offset=16)
        lay = src.layout
        assert (lay.width, lay.line_rate_hz) == (300, pytest.approx(5000.0))
        assert (lay.a_scale_mm, lay.a_offset_mm, lay.c_scale_mm, lay.c_offset_mm) == (
            A_SCALE, A_OFFSET, C_SCALE, C_OFFSET,
        )  # fmt: skip
        assert lay.invalid_value == 0
        dev = src._link.camera.get_device()
        assert dev.get_integer_feature_value("OffsetX") == 16
        assert dev.get_integer_feature_value("Height") == 50
        assert dev.get_float_feature_value("ExposureTimeAbs") == pytest.approx(2000.0)
        assert src.info.vendor == "Aravis" and src.info.serial == "WT49FEAT"
        await src.close()

    with fake_device("WT49FEAT", profiler_xml(tmp_path)):
        run(go())


def test_streamed_range_rows_become_profiles_in_order_with_the_scan3d_scale_and_offset(tmp_path):
    async def go():
        src = GigeProfileSource(ADDRESS, config=_config())
        await src.connect()
        await src.configure(rate_hz=10_000.0, exposure_ns=RAMP_EXPOSURE_NS, width=500)
        await src.start()
        batches = await collect(src, 2000, timeout_s=10)
        await src.close()
        return batches, src.stats

    with fake_device("WT49STREAM", profiler_xml(tmp_path)):
        batches, stats = run(go())
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    assert fi[0] == 0 and (np.diff(fi) == 1).all()  # no loss on a clean loopback
    assert stats.gaps == 0 and stats.torn_buffers == 0 and stats.duplicates_dropped == 0
    b = batches[0]
    np.testing.assert_allclose(b.x_mm[0], A_OFFSET + A_SCALE * np.arange(500), atol=1e-4)
    codes = _raw_codes(b.z_mm)
    # the ramp: +256 per column and per row (mod 65535); invalid only where the ramp hits 0
    ok = b.valid[:, :-1] & b.valid[:, 1:]
    step = np.diff(codes, axis=1)[ok]
    assert np.isin(step, [256, 256 - 65535]).all()
    assert np.isin(np.diff(codes[:, 0])[b.valid[1:, 0] & b.valid[:-1, 0]], [256, 256 - 65535]).all()
    # sensor time: one line period (100 us at 10 kHz) between the rows of a buffer
    assert (np.diff(b.sensor_time_us.astype(np.int64)) == 100).all()
    assert (b.exposure_ns == RAMP_EXPOSURE_NS).all()
    assert b.hd8_ms[0] == (int(b.sensor_time_us[0]) // 1000) & 0xFFFFFFFF


def test_a_device_without_a_16_bit_format_is_refused_with_the_formats_it_offers(tmp_path):
    xml = profiler_xml(tmp_path)
    text = xml.read_text()
    start = text.index('<EnumEntry Name="Mono16"')
    xml.write_text(text[:start] + text[text.index("</EnumEntry>", start) + len("</EnumEntry>") :])

    async def go():
        src = GigeProfileSource(ADDRESS)
        with pytest.raises(PixelFormatError, match=r"offers only .*Mono8"):
            await src.connect()

    with fake_device("WT49PIX", xml):
        run(go())


def test_exposure_on_a_device_without_an_exposure_feature_is_a_missing_feature(tmp_path):
    xml = profiler_xml(tmp_path)
    xml.write_text(xml.read_text().replace('"ExposureTimeAbs"', '"VendorExposure"').replace(
        ">ExposureTimeAbs<", ">VendorExposure<"))  # fmt: skip

    async def go():
        src = GigeProfileSource(ADDRESS)
        await src.connect()
        with pytest.raises(MissingFeatureError, match="ExposureTime"):
            await src.configure(exposure_ns=1_000_000)
        await src.close()

    with fake_device("WT49NOEXP", xml):
        run(go())


def test_lost_packets_tear_buffers_that_are_counted_never_delivered_and_show_as_gaps(tmp_path):
    """``-r 20``: 2 % of GVSP packets dropped. Aravis asks for them again (PACKETRESEND); Aravis's fake
    device does not serve resends (0.8.26 to its main branch), so a buffer missing a packet stays torn."""

    async def go():
        src = GigeProfileSource(ADDRESS, config=_config(rows_per_buffer=20, packet_timeout_ms=5))
        await src.connect()
        await src.configure(rate_hz=4000.0, exposure_ns=RAMP_EXPOSURE_NS, width=500)
        await src.start()
        batches = await collect(src, 3000, timeout_s=20)
        await src.close()
        return batches, src.stats

    with fake_device("WT49LOSS", profiler_xml(tmp_path), lost_per_thousand=20):
        batches, stats = run(go(), timeout_s=40)
    fi = np.concatenate([b.frame_index for b in batches]).astype(np.int64)
    assert (np.diff(fi) > 0).all()  # strictly increasing: nothing twice, nothing out of order
    # the source's own count of torn buffers; Aravis's missing-packet counter is Aravis's bookkeeping
    # (a CI run saw it at 0 with 46 buffers torn, read at close) and is not what this test is about
    assert stats.torn_buffers > 0
    # every profile is accounted for: delivered, or counted missing (whole torn buffers)
    assert stats.frames + stats.missing_frames == stats.last_frame_index + 1
    assert stats.missing_frames % 20 == 0  # whole buffers only
    for b in batches:  # what is delivered is intact: the ramp holds in every delivered row
        codes = _raw_codes(b.z_mm)
        ok = b.valid[:, :-1] & b.valid[:, 1:]
        assert np.isin(np.diff(codes, axis=1)[ok], [256, 256 - 65535]).all()


def test_a_device_that_vanishes_and_returns_delivers_no_duplicate_or_reordered_profile(tmp_path):
    xml = profiler_xml(tmp_path)

    async def go(dev):
        src = GigeProfileSource(ADDRESS, config=_config(rows_per_buffer=50))
        kinds = []
        src.add_listener(lambda e: kinds.append(e.kind))
        await src.connect()
        await src.configure(rate_hz=5000.0, exposure_ns=RAMP_EXPOSURE_NS, width=200)
        await src.start()
        before = await collect(src, 1000, timeout_s=10)
        await asyncio.to_thread(dev.kill)
        await asyncio.sleep(1.5)  # stays: the fault, a 1.5 s outage (its length is asserted in lines)
        await asyncio.to_thread(dev.start)
        t0 = time.monotonic()
        after = []
        async with asyncio.timeout(20):
            async for b in src:
                after.append(b)
                if src.stats.reconnects and sum(len(a) for a in after) >= 1000:
                    break
        assert time.monotonic() - t0 < 20
        await src.close()
        return before, after, kinds, src.stats

    with fake_device("WT49GONE", xml) as dev:
        before, after, kinds, stats = run(go(dev), timeout_s=60)
    fi = np.concatenate([b.frame_index for b in before + after]).astype(np.int64)
    assert (np.diff(fi) > 0).all()
    assert stats.reconnects == 1 and stats.duplicates_dropped == 0
    assert SourceEventKind.DISCONNECTED in kinds and SourceEventKind.RECONNECTED in kinds
    assert kinds.index(SourceEventKind.DISCONNECTED) < kinds.index(SourceEventKind.RECONNECTED)
    # the outage shows as one gap of about its length in lines (5 kHz), not as renumbered profiles
    assert stats.missing_frames >= 5000
    # the device clock ran on through the outage (the fake device stamps with the host's real time)
    assert int(after[0].sensor_time_us[0]) > int(before[-1].sensor_time_us[-1])


def test_a_stopped_source_starts_again_and_numbers_on(tmp_path):
    async def go():
        src = GigeProfileSource(ADDRESS, config=_config(rows_per_buffer=50))
        await src.connect()
        await src.stop()  # as the daemon does before configuring: nothing runs yet
        await src.configure(rate_hz=5000.0, exposure_ns=RAMP_EXPOSURE_NS, width=200)
        await src.start()
        first = await collect(src, 500, timeout_s=10)
        await src.stop()
        await asyncio.sleep(0.3)  # stays: the source stopped a while, as between two jobs
        await src.start()
        second = await collect(src, 500, timeout_s=10)
        await src.close()
        return first, second

    with fake_device("WT49AGAIN", profiler_xml(tmp_path)):
        first, second = run(go())
    fi = np.concatenate([b.frame_index for b in first + second]).astype(np.int64)
    assert (np.diff(fi) > 0).all()
    assert int(second[-1].frame_index[-1]) > int(first[-1].frame_index[-1])
