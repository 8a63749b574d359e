"""A process that cannot see given directories: a private mount namespace with tmpfs over them.

As root, ``chmod`` keeps nothing from a process; a mount namespace of its own (``unshare -m``, mount
propagation private) with an empty tmpfs over a directory does: what lies under it is not reachable
from that process, by any path. Used to show that a worker shares nothing with the daemon but Zenoh.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

__all__ = ["hidden_mounts_command", "start_hidden"]


def hidden_mounts_command(hide: list[Path], cwd: Path, argv: list[str]) -> list[str]:
    """``unshare -m`` running ``argv`` in ``cwd`` with an empty tmpfs over each of ``hide``."""
    mounts = " && ".join(f"mount -t tmpfs -o size=1m,mode=0700 tmpfs {shlex.quote(str(h))}" for h in hide)
    script = f"{mounts} && cd {shlex.quote(str(cwd))} && exec {shlex.join(argv)}"
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c", script]


def start_hidden(
    name: str, hide: list[Path], cwd: Path, cellctl_args: list[str], env: dict[str, str], log_dir: Path
) -> subprocess.Popen:
    """`python -m cellctl <args>` in its own mount namespace, ``hide`` unreachable; logs in log_dir."""
    argv = [sys.executable, "-m", "cellctl", "--log-format", "json", *cellctl_args]
    log_dir.mkdir(parents=True, exist_ok=True)
    with open(log_dir / f"{name}.out", "wb") as out, open(log_dir / f"{name}.log", "wb") as err:
        return subprocess.Popen(
            hidden_mounts_command(hide, cwd, argv), stdout=out, stderr=err, stdin=subprocess.DEVNULL,
            env={**os.environ, **env},
        )  # fmt: skip
