"""Writing calibration results where cell.toml reads them, keeping the file's layout and comments.

Only the value of an existing ``key = value`` line inside the named table is replaced (the comment
after it stays); a key that is missing is added at the end of its table. The result is re-validated
with :func:`cellctl.config.parse_config` before it replaces the file (atomically, via a temporary
file), so a calibration can never leave an unloadable cell.toml behind.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path
from typing import Any

from cellctl.config import parse_config

__all__ = ["CalibrationWriteError", "set_toml_values", "write_calibration_record"]

_TABLE = re.compile(r"^\s*\[([A-Za-z0-9_.\-]+)\]\s*(#.*)?$")


class CalibrationWriteError(ValueError):
    """The configuration file cannot take the calibrated values (names the file and the key)."""


def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(round(value, 6))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return json.dumps(value)


def set_toml_values(path: str | Path, table: str, values: dict[str, Any]) -> None:
    """Set ``values`` in ``[table]`` of the TOML file at ``path`` (see the module docstring)."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    start = end = None
    for i, line in enumerate(lines):
        m = _TABLE.match(line)
        if m and start is None and m.group(1) == table:
            start = i + 1
        elif m and start is not None:
            end = i
            break
    if start is None:
        raise CalibrationWriteError(f"{path}: no [{table}] table to write {sorted(values)} into")
    end = len(lines) if end is None else end
    todo = dict(values)
    for i in range(start, end):
        m = re.match(r"^([ \t]*)([A-Za-z0-9_]+)([ \t]*=[ \t]*)([^#\n]*?)([ \t]*)(#.*)?(\n?)$", lines[i])
        if m and m.group(2) in todo:
            indent, key, eq, _old, _sp, comment, nl = m.groups()
            head = f"{indent}{key}{eq}{_fmt(todo.pop(key))}"
            if comment:
                # keep the comment in its column when the new value fits, else two spaces after it
                column = len(lines[i]) - len(comment) - len(nl)
                head = head + " " * max(2, column - len(head)) + comment
            lines[i] = head + nl
    insert_at = end
    while insert_at > start and not lines[insert_at - 1].strip():
        insert_at -= 1  # keep the blank line before the next table
    for key, value in todo.items():
        lines.insert(insert_at, f"{key} = {_fmt(value)}\n")
        insert_at += 1
    text = "".join(lines)
    try:
        parse_config(tomllib.loads(text), str(path))
    except Exception as exc:  # a TOML syntax error or a ConfigError: never write it
        raise CalibrationWriteError(f"{path}: the calibrated file would not validate: {exc}") from exc
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_calibration_record(job_dir: str | Path, name: str, report: dict) -> Path:
    """Store a calibration's report beside the job's raw files (``calibration-<name>.json``)."""
    out = Path(job_dir) / f"calibration-{name}.json"
    out.write_text(json.dumps(report, indent=2, sort_keys=True, default=float))
    return out
