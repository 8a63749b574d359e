"""The daemon's side of the design transfer: the designs of the jobs it submitted, served by hash on
``Keys.design(sha256)`` (docs/api.md "Transfers"), never by path. The ref and the check of the bytes
are the contract's (:mod:`cellctl.api.transfer`).
"""

from __future__ import annotations

from pathlib import Path

import structlog

from cellctl.api.transfer import DesignRef, design_matches, design_ref

__all__ = ["DesignServer"]

log = structlog.get_logger(__name__)


class DesignServer:
    """The daemon's designs by hash: only what :meth:`register` was given is served."""

    def __init__(self) -> None:
        self._designs: dict[str, tuple[Path, DesignRef]] = {}

    def register(self, path: Path) -> DesignRef:
        ref = design_ref(path)
        self._designs[ref.sha256] = (path, ref)
        return ref

    def read(self, sha256: str) -> bytes | None:
        """The bytes of a registered design whose content still has this hash (None otherwise)."""
        if sha256 not in self._designs:
            return None
        path, ref = self._designs[sha256]
        try:
            data = path.read_bytes()
        except OSError as exc:
            log.warning("design_unreadable", sha256=sha256, path=str(path), error=str(exc))
            return None
        if not design_matches(ref, data):  # changed on disk since the job was submitted
            log.warning("design_changed", sha256=sha256, path=str(path))
            return None
        return data
