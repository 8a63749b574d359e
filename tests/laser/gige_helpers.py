"""Aravis's fake GigE Vision device (``arv-fake-gv-camera-0.8``) on loopback for the GigE source's tests.

GigE Vision's control port is fixed (UDP 3956), so one fake device at a time: the tests that use it
carry the ``process`` marker and run one at a time (make test's cell tests).
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

from drivers.laser.sim.gige_xml import profiler_genicam_xml

FAKE_BINARY = "arv-fake-gv-camera-0.8"
ADDRESS = "127.0.0.1"

#: the Scan3d layout the tests' profiler description declares
A_SCALE, A_OFFSET, C_SCALE, C_OFFSET = 0.1, -24.95, 0.002, 70.0


def profiler_xml(tmp: Path) -> Path:
    """The fake device's own description plus Scan3dControl, written to ``tmp``."""
    path = tmp / "fake-profiler.xml"
    path.write_text(
        profiler_genicam_xml(
            a_scale_mm=A_SCALE, a_offset_mm=A_OFFSET, c_scale_mm=C_SCALE, c_offset_mm=C_OFFSET
        )
    )
    return path


def _answers(serial: str, timeout_s: float) -> bool:
    """Poll discovery until the device with ``serial`` answers."""
    from drivers.laser.gige import discover

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(d["serial"] == serial for d in discover()):
            return True
        time.sleep(0.1)
    return False


class FakeDevice:
    """One ``arv-fake-gv-camera-0.8`` process: start, kill, pause, resume."""

    def __init__(self, serial: str, genicam: Path | None, lost_per_thousand: float = 0.0) -> None:
        binary = shutil.which(FAKE_BINARY)
        assert binary, f"{FAKE_BINARY} is missing: scripts/setup.sh installs Debian's aravis-tools"
        self.cmd = [binary, "-i", ADDRESS, "-s", serial]
        if genicam is not None:
            self.cmd += ["-g", str(genicam)]
        if lost_per_thousand:
            self.cmd += ["-r", str(lost_per_thousand)]
        self.serial = serial
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        from drivers.laser.gige import discover

        other = [d["serial"] for d in discover() if d["address"] == ADDRESS]
        assert not other, f"another GigE Vision device answers on {ADDRESS} (serial {other}): stop it first"
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert _answers(self.serial, 10.0), f"the fake device {self.serial} did not answer discovery"
        assert self.proc.poll() is None, f"the fake device {self.serial} exited ({self.proc.returncode})"

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(5)
            self.proc = None

    def pause(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGCONT)


@contextlib.contextmanager
def fake_device(
    serial: str, genicam: Path | None = None, *, lost_per_thousand: float = 0.0
) -> Iterator[FakeDevice]:
    """A running fake device (the stock Mono8 camera without ``genicam``), killed afterwards."""
    dev = FakeDevice(serial, genicam, lost_per_thousand)
    dev.start()
    try:
        yield dev
    finally:
        if dev.proc is not None:
            dev.resume()
        dev.kill()
