"""The daemon's side of the result transfer: a worker's result chunks gathered per (job, attempt),
bounded, checked against the manifest of the report that follows them (the check is the contract's,
:func:`cellctl.api.transfer.unpack_results`), and the verified files written into the job's results
directory (docs/api.md "Transfers").
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import structlog

from cellctl.api.transfer import (
    MAX_RESULT_BYTES,
    ResultChunk,
    ResultManifest,
    ResultRefused,
    plain_name,
    unpack_results,
)

__all__ = ["ResultCollector", "store_results"]

log = structlog.get_logger(__name__)


@dataclass
class _Bundle:
    worker_id: str
    chunks: int
    parts: dict[int, bytes] = field(default_factory=dict)
    size: int = 0


class ResultCollector:
    """The daemon's half of the result transfer: chunks gathered per (job, attempt), checked against
    the manifest when the report comes. Bounded: a bundle beyond ``max_bytes`` is dropped (the
    report then finds it incomplete), and at most ``max_bundles`` are held at once (oldest dropped)."""

    def __init__(self, *, max_bytes: int = MAX_RESULT_BYTES, max_bundles: int = 8) -> None:
        self.max_bytes = max_bytes
        self.max_bundles = max_bundles
        self._bundles: dict[tuple[str, int], _Bundle] = {}
        self._overflowed: set[tuple[str, int]] = set()
        self.bad_chunks = 0

    @property
    def held_bytes(self) -> int:
        return sum(b.size for b in self._bundles.values())

    def add(self, head: ResultChunk, data: bytes) -> bool:
        """Keep one chunk; False (and counted) when it is corrupt, inconsistent or over the bound."""
        key = (head.job_id, head.attempt)
        if (
            hashlib.sha256(data).hexdigest() != head.sha256
            or head.index >= head.chunks
            or key in self._overflowed
        ):
            self.bad_chunks += 1
            return False
        bundle = self._bundles.get(key)
        if bundle is None:
            while len(self._bundles) >= self.max_bundles:
                dropped = next(iter(self._bundles))
                log.warning("result_bundle_dropped", job_id=dropped[0], attempt=dropped[1], reason="too many")
                del self._bundles[dropped]
            bundle = self._bundles[key] = _Bundle(head.worker_id, head.chunks)
        if bundle.worker_id != head.worker_id or bundle.chunks != head.chunks:
            self.bad_chunks += 1
            return False
        if head.index not in bundle.parts:
            bundle.parts[head.index] = data
            bundle.size += len(data)
        if bundle.size > self.max_bytes:
            log.warning("result_bundle_dropped", job_id=head.job_id, attempt=head.attempt, reason="too large")
            del self._bundles[key]
            self._overflowed.add(key)
            return False
        return True

    def missing(self, job_id: str, attempt: int, manifest: ResultManifest) -> int:
        """How many chunks of the manifest have not arrived (yet)."""
        bundle = self._bundles.get((job_id, attempt))
        have = 0 if bundle is None else len(bundle.parts)
        return max(manifest.chunks - have, 0)

    def take(self, job_id: str, attempt: int, worker_id: str, manifest: ResultManifest) -> dict[str, bytes]:
        """The verified files of one bundle (name -> bytes), forgotten here. ResultRefused says why
        a bundle is not kept (then it is forgotten too)."""
        bundle = self._bundles.pop((job_id, attempt), None)
        self._overflowed.discard((job_id, attempt))
        if manifest.total_bytes > self.max_bytes:
            raise ResultRefused(job_id, f"{manifest.total_bytes} bytes, more than {self.max_bytes}")
        if manifest.chunks == 0:
            bundle = _Bundle(worker_id, 0)
        if bundle is None:
            raise ResultRefused(job_id, f"none of its {manifest.chunks} chunks arrived")
        if bundle.worker_id != worker_id:
            raise ResultRefused(job_id, f"chunks from {bundle.worker_id}, report from {worker_id}")
        if sorted(bundle.parts) != list(range(manifest.chunks)):
            raise ResultRefused(job_id, f"{len(bundle.parts)} of {manifest.chunks} chunks arrived")
        blob = b"".join(bundle.parts[i] for i in range(manifest.chunks))
        return unpack_results(job_id, manifest, blob)

    def forget(self, job_id: str) -> None:
        """Drop every bundle of a job (resolved or failed)."""
        for key in [k for k in self._bundles if k[0] == job_id]:
            del self._bundles[key]
        self._overflowed = {k for k in self._overflowed if k[0] != job_id}


def store_results(files: dict[str, bytes], results_dir: Path) -> list[Path]:
    """Write a verified bundle into the job's results directory (each file atomically, report.json
    last: its presence marks a complete results directory). Returns the written paths."""
    results_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in sorted(files, key=lambda n: n == "report.json"):
        path = results_dir / plain_name(name)
        tmp = results_dir / f".{name}.tmp"
        try:
            with tmp.open("wb") as f:
                f.write(files[name])
                f.flush()
                os.fsync(f.fileno())
            tmp.replace(path)
        except OSError:  # a full disk: no half-written temp file left (the caller keeps the bytes)
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        written.append(path)
    return written
