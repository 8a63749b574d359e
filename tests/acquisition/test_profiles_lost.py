"""Every profile counted is on disk, or the count says what was lost (issue 43, item 3). A disk that
filled mid-scan left about 80 profiles counted in the status (0.4 s of scan) that never reached the
raw file: the chunk that failed and what was buffered behind it. Now, after a failed raw write, the
session's ``profiles`` is what the raw file holds and ``profiles_lost`` the rest, and the error says
both. A real session against the simulators; the disk fills by a file-size limit (EFBIG, as a full
disk's ENOSPC) in a child process, as in tests/acquisition/test_session.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cellctl.jobstore.rawstore import RawReader
from tests.acquisition.test_session import REPO, _cell, _playback, _session


async def _lost_main(tmp_path: Path) -> dict:
    async with _cell(tmp_path) as (endpoint, _sensor, cfg):
        errors: list[OSError] = []
        session, acq, writer = await _session(tmp_path, cfg, endpoint, errors)
        await session.start()
        written = sum(p.stat().st_size for p in (tmp_path / "raw").iterdir())
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        _soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (written + 256 * 1024, hard))
        playback_s, ended = _playback(5.0)
        try:
            await session.track(playback_s, lambda: ended() or bool(errors))
            await session.finish()
        except OSError:
            pass
        finally:
            if session._consumer is not None:
                await asyncio.wait({session._consumer}, timeout=5.0)
            await session.abort()
            with contextlib.suppress(OSError):
                writer.close()
        on_disk = sum(
            len(r.arrays["frame_index"])
            for r in RawReader(tmp_path / "raw").records()
            if r.stream == "profiles"
        )
        return {"counted": acq.stats.profiles_in, "profiles": session.profiles, "lost": session.profiles_lost,
                "on_disk": on_disk, "error": str(errors[0]) if errors else ""}  # fmt: skip


@pytest.mark.process
def test_after_a_failed_raw_write_the_profile_count_is_what_is_on_disk_and_the_rest_is_counted_lost(tmp_path):
    code = (
        "import asyncio, json, sys; from pathlib import Path; "
        "from tests.acquisition.test_profiles_lost import _lost_main; "
        "print(json.dumps(asyncio.run(asyncio.wait_for(_lost_main(Path(sys.argv[1])), 40.0))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, timeout=90, cwd=REPO
    )
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["error"], seen  # the disk did fill
    assert seen["profiles"] == seen["on_disk"] > 0, seen  # what the status counts is on disk
    assert seen["lost"] > 0 and seen["profiles"] + seen["lost"] == seen["counted"], seen
    assert f"{seen['on_disk']} profiles are on disk" in seen["error"] and "were lost" in seen["error"], seen
