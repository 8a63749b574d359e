"""Reading the JSON files of a job directory (``job.json``, ``report.json``) safely.

Every reader of a job directory (the daemon's job store and its start-up recovery, the plate history
of the HMI and of ``cellctl history``, the report's previous round) goes through
:func:`read_json_file`: a file larger than :data:`MAX_RECORD_BYTES` is refused before it is read, a
document nested deeper than :data:`MAX_JSON_DEPTH` is refused (the standard parser recurses per level:
a few thousand ``[`` raise ``RecursionError``, which would end the process), and anything but a
regular file (a FIFO, a device, a symlink) is refused without blocking on it. A job directory's name
is its job id: :func:`check_job_id` holds a record's ``job_id`` to the API's id grammar and to the
directory it was read from, so that no record can name a path outside the data directory or another
job's directory.
"""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path
from typing import Any

from cellctl.api.models import ID_PATTERN

__all__ = [
    "MAX_JSON_DEPTH",
    "MAX_RECORD_BYTES",
    "RecordError",
    "check_job_id",
    "is_job_id",
    "read_json_file",
]

#: the largest job.json or report.json read: a record is a few KB, a report of 200 lines with its
#: deviation summaries some hundred KB; 16 MiB leaves room for either and bounds the memory a
#: corrupt or planted file can take (a 1 GB record took 14 s and 3.4 GB to parse)
MAX_RECORD_BYTES = 16 * 1024 * 1024
#: the deepest nesting of arrays and objects accepted: a record nests 5 levels, a report 6
MAX_JSON_DEPTH = 64

_ID_RE = re.compile(ID_PATTERN)


class RecordError(ValueError):
    """A job directory's JSON file that is not read (too large, too deep, not JSON, not a regular
    file, a job id that is not its directory's); the message says which and why."""


def is_job_id(name: str) -> bool:
    """``name`` follows the API's id grammar (and so names no path: no ``/``, never ``.`` or ``..``)."""
    return bool(_ID_RE.fullmatch(name))


def check_job_id(value: Any, dir_name: str) -> str:
    """``value`` when it is a job id and equals ``dir_name`` (the record's directory), else RecordError."""
    if not isinstance(value, str):
        raise RecordError(f"job_id: expected a string, got {type(value).__name__}")
    if not is_job_id(value):
        raise RecordError(
            f"job_id {value[:80]!r} is not a job id (letters, digits, '_', '.', '-'; at most 64)"
        )
    if value != dir_name:
        raise RecordError(f"job_id {value!r} is not its directory's name {dir_name[:80]!r}")
    return value


def _depth_exceeds(obj: Any, limit: int) -> bool:
    """Whether ``obj`` (parsed JSON) nests deeper than ``limit``; no recursion."""
    stack = [(obj, 1)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict):
            children = node.values()
        elif isinstance(node, list):
            children = node
        else:
            continue
        if depth > limit:
            return True
        stack.extend((c, depth + 1) for c in children if isinstance(c, dict | list))
    return False


def read_json_file(
    path: str | Path, max_bytes: int = MAX_RECORD_BYTES, max_depth: int = MAX_JSON_DEPTH
) -> Any:
    """The JSON document in ``path``, read within the bounds above.

    Raises:
        OSError: the file cannot be opened or read (missing, permissions).
        RecordError: not a regular file, larger than ``max_bytes``, not UTF-8 JSON, or nested deeper
            than ``max_depth``.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise RecordError("not a regular file")
        if st.st_size > max_bytes:
            raise RecordError(f"{st.st_size} bytes, more than the {max_bytes} a record may hold")
        with os.fdopen(os.dup(fd), "rb") as f:
            data = f.read(max_bytes + 1)
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # grew while it was read
        raise RecordError(f"more than the {max_bytes} bytes a record may hold")
    try:
        doc = json.loads(data.decode("utf-8"))
    except RecursionError:
        raise RecordError(f"nested deeper than {max_depth} levels") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise RecordError(f"not JSON: {str(exc)[:200]}") from None
    if _depth_exceeds(doc, max_depth):
        raise RecordError(f"nested deeper than {max_depth} levels")
    return doc
