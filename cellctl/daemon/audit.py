"""The audit log: who asked the cell to do what, one JSON line per trigger and control.

``<data_dir>/audit.jsonl``, opened for appending only (``O_APPEND``, mode 600), never rewritten
or truncated by the daemon: ``{"t_utc", "user", "zenoh_identity", "action", "job_id",
"outcome", "message"}``. ``user`` is the request's ``requested_by`` (the HMI's logged-in user;
None when the request did not say, a CLI or MES client). ``zenoh_identity`` is None: the Zenoh
binding does not tell a queryable who sent a query (``Query.source_info`` is empty unless the
sender sets it, and then it says what the sender chose); the ACL decides which identities may ask
at all (docs/api.md, "Access control"). A line the disk does not take is logged
(``audit_write_failed``) and the action goes on: the audit log never stops the cell.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import structlog

from cellctl.api import now_utc

__all__ = ["AUDIT_FILE", "AuditLog"]

log = structlog.get_logger(__name__)

AUDIT_FILE = "audit.jsonl"


class AuditLog:
    """Appends one JSON line per action to ``<data_dir>/audit.jsonl``."""

    def __init__(self, data_dir: str | Path) -> None:
        self.path = Path(data_dir) / AUDIT_FILE

    def write(
        self,
        action: str,
        *,
        user: str | None,
        job_id: str | None,
        outcome: str,
        message: str = "",
        zenoh_identity: str | None = None,
    ) -> None:
        entry: dict[str, Any] = {
            "t_utc": now_utc(), "user": user, "zenoh_identity": zenoh_identity, "action": action,
            "job_id": job_id, "outcome": outcome, "message": message[:300],
        }  # fmt: skip
        line = (json.dumps(entry, ensure_ascii=True) + "\n").encode()
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
            try:
                os.write(fd, line)  # one write of a short line: appended whole
            finally:
                os.close(fd)
        except OSError as exc:
            log.error("audit_write_failed", action=action, job_id=job_id, user=user, error=str(exc))
