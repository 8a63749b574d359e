"""The acquisition session without Zenoh: the real EGM endpoint fed by the controller simulator and
the real HD8 client fed by the sensor simulator, both over loopback sockets; the motion is stood in
for by a playback clock (the session needs only its time and whether it has ended)."""

from __future__ import annotations

import asyncio
import contextlib
import resource
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from cellctl.acquisition.pipeline import KIND_PASS_BEGIN, KIND_PASS_END, Acquisition, AcquisitionSettings
from cellctl.acquisition.session import AcquisitionSession, SessionSettings, pass_windows_s
from cellctl.config import CellConfig
from cellctl.daemon.wiring import hd8_client, laser_exposure_ns
from cellctl.jobstore.rawstore import RawReader, RawWriter
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig
from drivers.laser.sim.scene import plane_scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig, fixed_pose

REPO = Path(__file__).resolve().parents[2]
WINDOWS = pass_windows_s([0.3, 0.9], [0.4, 0.4])  # two passes, 0.2 s apart


def _looking_down(standoff_mm: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.0, 0.0, standoff_mm]
    return T


@contextlib.asynccontextmanager
async def _cell(tmp_path: Path) -> AsyncIterator[tuple[EgmEndpoint, LaserSimulator, CellConfig]]:
    endpoint = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0))
    _, port = await endpoint.start()
    controller = EgmControllerSim(EgmSimConfig(sensor_port=port, seed=1))
    sensor = LaserSimulator(
        plane_scene(0.0), fixed_pose(_looking_down(100.0)), config=SimConfig(rate_hz=200.0)
    )
    try:
        await controller.start()
        await endpoint.wait_for_feedback(2.0)
        ctl, dat = await sensor.start()
        cfg = CellConfig.model_validate(
            {"laser": {"host": "127.0.0.1", "control_port": ctl, "data_port": dat, "rate_hz": 200.0}}
        )
        yield endpoint, sensor, cfg
    finally:
        await sensor.stop()
        await controller.stop()
        await endpoint.close()


async def _session(tmp_path: Path, cfg: CellConfig, endpoint: EgmEndpoint, errors: list[OSError]):
    client = hd8_client(cfg.laser)
    await client.connect()
    await client.configure(rate_hz=cfg.laser.rate_hz, exposure_ns=laser_exposure_ns(cfg.laser))
    settings = AcquisitionSettings.from_config(cfg, epoch_ns=time.monotonic_ns())
    writer = RawWriter(tmp_path / "raw", {"acquisition": settings.to_json()}, flush_interval_s=0.05)
    acq = Acquisition(settings, writer)
    session = AcquisitionSession(
        acq, client, endpoint.history, WINDOWS, SessionSettings(marker_period_s=0.01, settle_s=0.3),
        on_write_error=errors.append,
    )  # fmt: skip
    return session, acq, writer


def _playback(duration_s: float):
    t0 = time.monotonic()
    return (lambda: time.monotonic() - t0), (lambda: time.monotonic() - t0 > duration_s)


def test_session_feeds_profiles_and_feedback_and_marks_each_pass_once(tmp_path):
    async def main() -> None:
        async with _cell(tmp_path) as (endpoint, _sensor, cfg):
            errors: list[OSError] = []
            session, acq, writer = await _session(tmp_path, cfg, endpoint, errors)
            await session.start()
            playback_s, ended = _playback(1.6)
            await session.track(playback_s, ended)
            await session.finish()
            writer.close()
            assert errors == []
            assert session.profiles > 200  # 200 Hz for ~1.9 s
            assert acq.stats.profiles_in == session.profiles
            assert acq.stats.robot_samples > 100  # 250 Hz feedback (fewer on a loaded machine)
            records = RawReader(tmp_path / "raw").records()
            # the pump hands over only what is new: every feedback sample once, in order
            t_robot = np.concatenate([r.arrays["t_host_ns"] for r in records if r.stream == "robot"])
            assert len(t_robot) == acq.stats.robot_samples and np.all(np.diff(t_robot) > 0)
            events = [r for r in records if r.stream == "events"]
            begins = [int(r.arrays["pass_id"]) for r in events if r.kind == KIND_PASS_BEGIN]
            ends = [int(r.arrays["t_ns"]) for r in events if r.kind == KIND_PASS_END]
            assert begins == [0, 1] and len(ends) == 2
            cloud = acq.cloud()
            # profiles exposed inside a window belong to its pass, none outside both
            assert set(np.unique(cloud.pass_id[cloud.pass_id >= 0]).tolist()) == {0, 1}

    asyncio.run(asyncio.wait_for(main(), 30.0))


async def _write_fault_main(tmp_path: Path) -> int:
    """The session hits a file-size limit mid-scan (EFBIG, as a full disk); returns the number of
    ``on_write_error`` calls after checking that finish() raised and the first records are intact."""
    async with _cell(tmp_path) as (endpoint, _sensor, cfg):
        errors: list[OSError] = []
        session, _acq, writer = await _session(tmp_path, cfg, endpoint, errors)
        await session.start()
        written = sum(p.stat().st_size for p in (tmp_path / "raw").iterdir())
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        _soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (written + 64 * 1024, hard))
        playback_s, ended = _playback(3.0)
        raised = False
        try:
            await session.track(playback_s, lambda: ended() or bool(errors))
            await session.finish()
        except OSError:
            raised = True
        finally:
            # the sensor's consumer fails too, on its next write (the limit holds): abort collects it
            consumer = session._consumer
            if consumer is not None:
                await asyncio.wait({consumer}, timeout=5.0)
                assert consumer.done() and not consumer.cancelled()
            await session.abort()
            with contextlib.suppress(OSError):
                writer.close()
        assert raised, "the write error must end the session"
        assert RawReader(tmp_path / "raw").records()  # what was written before stays readable
        return len(errors)


@pytest.mark.process
def test_a_write_that_fails_calls_the_owner_once_and_ends_the_session_with_the_error(tmp_path):
    """In a child process: the file-size limit must not touch the test runner's own files."""
    code = (
        "import asyncio, sys; from pathlib import Path; "
        "from tests.acquisition.test_session import _write_fault_main; "
        "print('errors', asyncio.run(asyncio.wait_for(_write_fault_main(Path(sys.argv[1])), 30.0))); "
        "import gc; gc.collect()"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "errors 1"
    # the consumer's write error was collected, not left for asyncio to log at the next job's start
    assert "never retrieved" not in out.stderr, out.stderr[-2000:]
