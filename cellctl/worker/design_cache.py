"""The worker's side of the design transfer: the designs it fetched by hash, kept in
``<worker data dir>/designs/<sha256>/<name>`` and checked against their :class:`DesignRef` on the way
in and on every use (docs/api.md "Transfers").
"""

from __future__ import annotations

import os
from pathlib import Path

from cellctl.api.transfer import DesignRef, TransferError, design_matches

__all__ = ["cache_design", "cached_design"]


def cached_design(cache_dir: Path, ref: DesignRef) -> Path | None:
    """The cached copy of a design when it is there and its bytes still have the hash."""
    path = cache_dir / ref.sha256 / ref.name
    try:
        if path.stat().st_size == ref.size_bytes and design_matches(ref, path.read_bytes()):
            return path
    except OSError:
        return None
    return None


def cache_design(cache_dir: Path, ref: DesignRef, data: bytes) -> Path:
    """Verify fetched design bytes against their ref and store them (atomically) in the cache."""
    if not design_matches(ref, data):
        raise TransferError(f"design {ref.name}: the received bytes do not have hash {ref.sha256[:12]}")
    d = cache_dir / ref.sha256
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f".{ref.name}.{os.getpid()}.tmp"
    tmp.write_bytes(data)
    tmp.replace(d / ref.name)
    return d / ref.name
