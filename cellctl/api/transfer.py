"""What crosses Zenoh so that a worker shares nothing with the daemon but the link (docs/api.md).

* **The design**, by content: the JobSpec names it by SHA-256 (:class:`DesignRef`); the worker asks
  the daemon's queryable ``Keys.design(sha256)`` for the bytes once, verifies the hash and keeps
  them in its cache (``<worker data dir>/designs/<sha256>/<name>``,
  :mod:`cellctl.worker.design_cache`). The daemon serves only the designs of jobs it has submitted
  (:class:`cellctl.daemon.design_server.DesignServer`), never a path.
* **The results**, by value: the worker's results directory (report.json, report.csv, results.npz,
  cloud.ply, ...) is packed into one bundle, bounded (``max_bytes``) and cut into chunks put on
  ``Keys.result_chunk(job, attempt, index)`` with ``CongestionControl.BLOCK``, each with a
  :class:`ResultChunk` attachment (its SHA-256); the ReportEnvelope that follows carries the
  :class:`ResultManifest` (every file's name, size and SHA-256). The daemon's
  :class:`cellctl.daemon.result_collector.ResultCollector` gathers the chunks and checks the bundle
  against it (:func:`unpack_results`); a missing, surplus or corrupt chunk or a file whose hash
  differs refuses the result (the dispatcher retries the job).

This module holds what both sides must compute alike: the messages, the design's ref and its check
(:func:`design_ref`, :func:`design_matches`), the bundle's packing and its check
(:func:`pack_results`, :func:`unpack_results`). What one side alone does lives on that side.
"""

from __future__ import annotations

import hashlib
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = [
    "CHUNK_BYTES",
    "MAX_DESIGN_BYTES",
    "MAX_RESULT_BYTES",
    "DesignRef",
    "ResultChunk",
    "ResultFile",
    "ResultManifest",
    "ResultRefused",
    "TransferError",
    "TransferSpec",
    "design_matches",
    "design_ref",
    "pack_results",
    "plain_name",
    "unpack_results",
]

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


def plain_name(v: str) -> str:
    """``v`` when it is a plain file name a design or a result file may have (ValueError otherwise)."""
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

    _name = field_validator("name")(plain_name)


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

    _name = field_validator("name")(plain_name)


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


def design_matches(ref: DesignRef, data: bytes) -> bool:
    """Whether ``data`` are the design ``ref`` names (its size and SHA-256): the daemon checks what it
    serves, the worker what it received and what its cache holds."""
    return len(data) == ref.size_bytes and _sha256(data) == ref.sha256


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


def unpack_results(job_id: str, manifest: ResultManifest, bundle: bytes) -> dict[str, bytes]:
    """The files of a result bundle (name -> bytes), checked against its manifest as
    :func:`pack_results` made them: the bundle's size and SHA-256 first, then every file's.
    ResultRefused says what does not match."""
    if len(bundle) != manifest.total_bytes:
        raise ResultRefused(job_id, "the bundle does not have the manifest's size and hash")
    # the bundle's hash beside the files' (as pack_results makes them); the bundle's is judged first
    with ThreadPoolExecutor(1, thread_name_prefix="bundle-hash") as pool:
        whole = pool.submit(_sha256, bundle)
        view = memoryview(bundle)
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
