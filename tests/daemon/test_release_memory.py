"""The daemon hands freed C-heap pages back after each job (glibc malloc_trim)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.process  # measured in a fresh interpreter


def test_freed_numpy_temporaries_leave_the_resident_set_after_the_release():
    """Medium numpy arrays (64 KB, below glibc's mmap threshold) live on the C heap; freed under a
    block still in use at the heap's top, their pages stay resident until released. Run in a fresh
    interpreter so the test's own heap does not blur the figure."""
    code = textwrap.dedent(
        """
        import numpy as np
        from drivers.runtime import release_freed_memory, rss_mb as _rss_mb
        arrs = [np.ones(8000) for _ in range(3000)]  # ~190 MB of 64 KB blocks
        pin = np.ones(8000)  # allocated last: the heap top stays in use
        del arrs
        before = _rss_mb()
        released = release_freed_memory()
        print(released, before - _rss_mb())
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    released, dropped_mb = out.stdout.split()
    assert released == "True"
    assert float(dropped_mb) > 100.0, out.stdout
