"""What crosses Zenoh so that a worker shares nothing with the daemon but the link (docs/api.md).

* **The design**, by content: the JobSpec names it by SHA-256 (:class:`DesignRef`); the worker asks
  the daemon's queryable ``Keys.design(sha256)`` for the bytes once, verifies the hash and keeps
  them in its cache (``<worker data dir>/designs/<sha256>/<name>``). The daemon serves only the
  designs of jobs it has submitted (:class:`DesignServer`), never a path.
* **The results**, by value: the worker's results directory (report.json, report.csv, results.npz,
  cloud.ply, ...) is packed into one bundle, bounded (``max_bytes``) and cut into chunks put on
  ``Keys.result_chunk(job, attempt, index)`` with ``CongestionControl.BLOCK``, each with a
  :class:`ResultChunk` attachment (its SHA-256); the ReportEnvelope that follows carries the
  :class:`ResultManifest` (every file's name, size and SHA-256). The daemon's
  :class:`ResultCollector` checks the bundle against it; a missing, surplus or corrupt chunk or a
  file whose hash differs refuses the result (the dispatcher retries the job).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = [
    "CHUNK_BYTES",
    "MAX_DESIGN_BYTES",
    "MAX_RESULT_BYTES",
    "DesignRef",
    "DesignServer",
    "ResultChunk",
    "ResultCollector",
    "ResultFile",
    "ResultManifest",
    "ResultRefused",
    "TransferError",
    "TransferSpec",
    "cache_design",
    "cached_design",
    "design_ref",
    "pack_results",
    "store_results",
]

log = structlog.get_logger(__name__)

#: one chunk of a result bundle (Zenoh fragments it further; a chunk is what one put carries)
CHUNK_BYTES = 1 << 20
#: the largest result bundle a daemon accepts (a 2.5 M point registered cloud is ~40 MB)
MAX_RESULT_BYTES = 512 << 20
#: the largest design a daemon serves (a plate's STL / PLY is a few MB)
MAX_DESIGN_BYTES = 64 << 20

_SHA256 = r"^[0-9a-f]{64}$"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


class TransferError(Exception):
    """A design or result transfer that cannot be done (too large, unreadable, hash mismatch)."""


class ResultRefused(TransferError):
    """A result bundle the daemon does not keep; ``reason`` says what was wrong with it."""

    def __init__(self, job_id: str, reason: str) -> None:
        self.job_id = job_id
        self.reason = reason
        super().__init__(f"job {job_id}: result refused: {reason}")


def _plain_name(v: str) -> str:
    if not _NAME.match(v) or v in (".", ".."):
        raise ValueError("must be a plain file name (letters, digits, '.', '_', '-'; no directory)")
    return v


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    def to_json(self) -> bytes:
        return self.model_dump_json().encode("utf-8")


class DesignRef(_Msg):
    """A design by content: its SHA-256 (hex), its file name (suffix decides the reader), its size."""

    sha256: Annotated[str, Field(pattern=_SHA256)]
    name: str
    size_bytes: Annotated[int, Field(ge=1, le=MAX_DESIGN_BYTES)]

    _name = field_validator("name")(_plain_name)


class TransferSpec(_Msg):
    """How a job's inputs and results travel (in the JobSpec). ``design``: fetch it by hash from the
    daemon; ``return_results``: pack the results directory back over Zenoh (the worker then writes it
    under its own data dir, never at the job's ``out_dir``)."""

    design: DesignRef | None = None
    return_results: bool = True
    chunk_bytes: Annotated[int, Field(ge=4096, le=64 << 20)] = CHUNK_BYTES
    max_result_bytes: Annotated[int, Field(ge=1, le=8 << 30)] = MAX_RESULT_BYTES


class ResultFile(_Msg):
    """One file of a result bundle: its place in the bundle (``offset_bytes``), size and SHA-256."""

    name: str
    offset_bytes: Annotated[int, Field(ge=0)]
    size_bytes: Annotated[int, Field(ge=0)]
    sha256: Annotated[str, Field(pattern=_SHA256)]

    _name = field_validator("name")(_plain_name)


class ResultManifest(_Msg):
    """A result bundle (in the ReportEnvelope): its files, chunk count and size, whole SHA-256."""

    files: list[ResultFile]
    chunks: Annotated[int, Field(ge=0)]
    chunk_bytes: Annotated[int, Field(ge=1)]
    total_bytes: Annotated[int, Field(ge=0)]
    sha256: Annotated[str, Field(pattern=_SHA256)]


class ResultChunk(_Msg):
    """The attachment of one chunk put (``Keys.result_chunk``): whose, which, and its SHA-256."""

    job_id: Annotated[str, Field(min_length=1)]
    worker_id: Annotated[str, Field(min_length=1)]
    attempt: Annotated[int, Field(ge=1)]
    index: Annotated[int, Field(ge=0)]
    chunks: Annotated[int, Field(ge=1)]
    sha256: Annotated[str, Field(pattern=_SHA256)]
    #: cellctl.api.proof.chunk_mac under the offer's key ("": unsigned, refused by the dispatcher)
    mac: Annotated[str, Field(pattern=r"^([0-9a-f]{64})?$")] = ""


def _sha256(data: bytes | bytearray | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


# ------------------------------------------------------------------------------------- designs


def design_ref(path: Path) -> DesignRef:
    """The DesignRef of a design file (hashes it; TransferError when too large or unreadable)."""
    try:
        size = path.stat().st_size
        if size > MAX_DESIGN_BYTES:
            raise TransferError(f"design {path.name}: {size} bytes, more than {MAX_DESIGN_BYTES}")
        h = hashlib.sha256()
        with path.open("rb") as f:
            while block := f.read(1 << 20):
                h.update(block)
    except OSError as exc:
        raise TransferError(f"design {path}: {exc}") from None
    return DesignRef(sha256=h.hexdigest(), name=path.name, size_bytes=size)


class DesignServer:
    """The daemon's designs by hash: only what :meth:`register` was given is served."""

    def __init__(self) -> None:
        self._paths: dict[str, Path] = {}

    def register(self, path: Path) -> DesignRef:
        ref = design_ref(path)
        self._paths[ref.sha256] = path
        return ref

    def read(self, sha256: str) -> bytes | None:
        """The bytes of a registered design whose content still has this hash (None otherwise)."""
        path = self._paths.get(sha256)
        if path is None:
            return None
        try:
            data = path.read_bytes()
        except OSError as exc:
            log.warning("design_unreadable", sha256=sha256, path=str(path), error=str(exc))
            return None
        if _sha256(data) != sha256:  # changed on disk since the job was submitted
            log.warning("design_changed", sha256=sha256, path=str(path))
            return None
        return data


def cached_design(cache_dir: Path, ref: DesignRef) -> Path | None:
    """The cached copy of a design when it is there and its bytes still have the hash."""
    path = cache_dir / ref.sha256 / ref.name
    try:
        if path.stat().st_size == ref.size_bytes and _sha256(path.read_bytes()) == ref.sha256:
            return path
    except OSError:
        return None
    return None


def cache_design(cache_dir: Path, ref: DesignRef, data: bytes) -> Path:
    """Verify fetched design bytes against their ref and store them (atomically) in the cache."""
    if len(data) != ref.size_bytes or _sha256(data) != ref.sha256:
        raise TransferError(f"design {ref.name}: the received bytes do not have hash {ref.sha256[:12]}")
    d = cache_dir / ref.sha256
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".{ref.name}.{os.getpid()}.tmp"
    tmp.write_bytes(data)
    tmp.replace(d / ref.name)
    return d / ref.name


# ------------------------------------------------------------------------------------- results


def pack_results(
    out_dir: Path, *, chunk_bytes: int = CHUNK_BYTES, max_bytes: int = MAX_RESULT_BYTES
) -> tuple[ResultManifest, list[bytes]]:
    """The regular files of a results directory as one bundle cut into chunks, and its manifest.

    Files are taken in name order, temporary ones (``*.tmp``, hidden) left out. TransferError when
    the bundle would exceed ``max_bytes`` or a file has a name the manifest cannot carry.
    """
    paths = sorted(
        p for p in out_dir.iterdir() if p.is_file() and not p.name.startswith(".") and p.suffix != ".tmp"
    )
    total = sum(p.stat().st_size for p in paths)
    if total > max_bytes:
        raise TransferError(f"results of {out_dir.name}: {total} bytes, more than {max_bytes}")
    datas = [p.read_bytes() for p in paths]
    bundle = b"".join(datas)
    # the bundle's hash beside the files' (hashlib lets go of the interpreter on large buffers): the
    # 44 MB of the sail's results hash in the time of one pass, not two, before the report can go
    with ThreadPoolExecutor(1, thread_name_prefix="bundle-hash") as pool:
        whole = pool.submit(_sha256, bundle)
        files = []
        offset = 0
        for p, data in zip(paths, datas, strict=True):
            try:
                files.append(
                    ResultFile(name=p.name, offset_bytes=offset, size_bytes=len(data), sha256=_sha256(data))
                )
            except ValueError as exc:
                raise TransferError(f"result file {p.name!r}: {exc}") from None
            offset += len(data)
        bundle_sha256 = whole.result()
    del datas
    chunks = [bundle[i : i + chunk_bytes] for i in range(0, len(bundle), chunk_bytes)]
    manifest = ResultManifest(
        files=files,
        chunks=len(chunks),
        chunk_bytes=chunk_bytes,
        total_bytes=len(bundle),
        sha256=bundle_sha256,
    )
    return manifest, chunks


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
        if _sha256(data) != head.sha256 or head.index >= head.chunks or key in self._overflowed:
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
        if len(blob) != manifest.total_bytes:
            raise ResultRefused(job_id, "the bundle does not have the manifest's size and hash")
        # the bundle's hash beside the files' (as pack_results makes them); the bundle's is judged first
        with ThreadPoolExecutor(1, thread_name_prefix="bundle-hash") as pool:
            whole = pool.submit(_sha256, blob)
            view = memoryview(blob)
            files: dict[str, bytes] = {}
            bad: str | None = None
            for f in manifest.files:
                data = view[f.offset_bytes : f.offset_bytes + f.size_bytes]
                if len(data) != f.size_bytes or _sha256(data) != f.sha256 or f.name in files:
                    bad = bad or f.name
                    continue
                files[f.name] = data.tobytes()
            whole_ok = whole.result() == manifest.sha256
        if not whole_ok:
            raise ResultRefused(job_id, "the bundle does not have the manifest's size and hash")
        if bad is not None:
            raise ResultRefused(job_id, f"file {bad} does not match the manifest")
        return files

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
        path = results_dir / _plain_name(name)
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
