"""A worker's settings (:class:`WorkerSettings`, from cell.toml's ``[analysis]`` and ``[worker]``)
and the BLAS threads of its analysis process."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULT_ANALYSIS = "analysis.pipeline:analyse_job"


@dataclass(frozen=True)
class WorkerSettings:
    """How a worker behaves; defaults suit a worker beside the daemon on the cell PC."""

    worker_id: str = ""
    analysis: str = DEFAULT_ANALYSIS
    heartbeat_s: float = 1.0
    start_timeout_s: float = 120.0
    connect_retry_s: float = 2.0
    # BLAS threads in the analysis process (0: the library's default). One: the analysis' matrix
    # products are (n, 3) x (3, 3), memory-bound, and on a busy 2-core machine OpenBLAS' spinning
    # threads made one such product of 2.5 M points take 1.5 s instead of 0.1 s (load 8).
    blas_threads: int = 1
    # MB of touched free heap the analysis process keeps ready while a streamed scan arrives (at
    # most; cellctl.worker.heap.RESERVE_BYTES_PER_POINT a point received), and it keeps what it frees until
    # the job ends: page faults were half the analysis' time on the sail plate. 0: neither.
    heap_reserve_mb: int = 1536
    # the worker's own files (design cache, a job's results until sent): never the daemon's
    data_dir: Path = Path("worker-data")
    design_timeout_s: float = 60.0
    # a free slot is held this long for a cell passed over while busy (longer than the dispatcher's
    # busy back-off, 2 s, so that cell's next offer finds it)
    fair_hold_s: float = 4.0
    # a streamed job: after StreamEnd a missing chunk is awaited this long before the whole cloud
    # is fetched from the daemon; no chunk at all for stream_idle_s (a pass takes minutes at most)
    # gives the attempt up; the whole cloud's fetch may take cloud_timeout_s
    stream_grace_s: float = 2.0
    stream_idle_s: float = 900.0
    cloud_timeout_s: float = 120.0
    # the chunk the daemon marks ``last_pass`` starts the analysis at once (the arm retracts); the
    # report stands when the rest of the stream adds no point, else the analysis runs again
    analyse_ahead: bool = True

    @classmethod
    def from_config(cls, config: Any, **override: Any) -> WorkerSettings:
        """From ``[analysis]`` and ``[worker]`` of a CellConfig; keyword arguments override (the
        command line)."""
        a = config.analysis
        values = {
            "analysis": a.callable,
            "heartbeat_s": a.heartbeat_s,
            "data_dir": config.worker.data_dir,
            "heap_reserve_mb": config.worker.heap_reserve_mb,
        }
        values.update({k: v for k, v in override.items() if v is not None})
        return cls(**values)


_BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads(n: int) -> None:
    """Ask the BLAS libraries for ``n`` threads (0: leave their default). Works only before numpy is
    first imported in this process (they read the environment when they load); an explicit setting
    in the environment wins."""
    if n > 0:
        for var in _BLAS_THREAD_VARS:
            os.environ.setdefault(var, str(n))


@contextlib.contextmanager
def blas_threads_for_children(n: int) -> Iterator[None]:
    """The environment a process spawned inside inherits asks its BLAS libraries for ``n`` threads
    (0: unchanged; an explicit setting in the environment wins); this process's environment is
    restored after. A spawned child imports numpy (and loads its OpenBLAS, which reads the variable
    once) before its own code runs, so the variable must be there when the child starts."""
    saved = {var: os.environ.get(var) for var in _BLAS_THREAD_VARS}
    limit_blas_threads(n)
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value
