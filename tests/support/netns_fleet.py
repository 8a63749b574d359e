"""A fleet on one machine that shares nothing: Linux network namespaces as hosts (root only).

Hosts: ``<p>-r`` runs `cellctl router`; ``<p>-c<i>`` one simulated cell each (`cellctl sim` and
`cellctl run`, talking over that namespace's loopback); ``<p>-s`` the analysis server (workers).
Each non-router host has one veth pair to the router host, on a private /30 inside these
namespaces only (10.77.<link>.0/30). Every process also runs in a mount namespace of its own with an
empty tmpfs over every other host's directory and over /dev/shm (Zenoh's shared memory would
otherwise carry the payloads), so no file is reachable across hosts: what a worker
needs comes over Zenoh. ``tc netem`` can slow the server's link where the kernel has netem, else a
relay in user space (:meth:`Fleet.slow_link`, tests/support/slow_link.py); ``ip link`` cuts it.

Used by tests/fleet/test_fleet.py and benchmarks/fleet.py. Namespaces are named with a prefix
(:data:`PREFIX`) so that leftovers of a killed run are removed by :func:`remove_leftovers`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
PREFIX = "cflt"
ROUTER_PORT = 7447


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], check=check, capture_output=True, text=True)


def remove_leftovers(prefix: str = PREFIX) -> list[str]:
    """Delete every namespace whose name starts with ``prefix-`` (a killed earlier run's)."""
    names = [line.split()[0] for line in _ip("netns", "list").stdout.splitlines() if line.strip()]
    gone = [n for n in names if n.startswith(prefix + "-") or n.startswith(prefix)]
    for n in gone:
        # a killed run's processes may live on in its namespaces: stop them by their pids first
        for pid in _ip("netns", "pids", n, check=False).stdout.split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
        _ip("netns", "delete", n, check=False)
    return gone


@dataclass
class Proc:
    name: str
    host: str
    argv: list[str]
    popen: subprocess.Popen
    log: Path


@dataclass
class Fleet:
    """The namespaces, links and processes of one fleet; :meth:`close` removes everything."""

    base: Path
    cells: int = 2
    workers: int = 2
    tag: str = field(default_factory=lambda: uuid.uuid4().hex[:5])
    procs: list[Proc] = field(default_factory=list)
    links: dict[str, tuple[str, str, str, str]] = field(
        default_factory=dict
    )  # host -> (ns dev, r dev, ip, r ip)

    @property
    def ns_prefix(self) -> str:
        return f"{PREFIX}{self.tag}"

    def ns(self, host: str) -> str:
        return f"{self.ns_prefix}-{host}"

    @property
    def hosts(self) -> list[str]:
        return ["r", *[f"c{i}" for i in range(self.cells)], "s"]

    def host_dir(self, host: str) -> Path:
        return self.base / host

    @property
    def router_ip(self) -> str:
        return "10.77.0.1"

    # --------------------------------------------------------------------------------- network

    def create(self) -> None:
        """Namespaces, loopback up, one veth pair per host to the router host."""
        for host in self.hosts:
            _ip("netns", "add", self.ns(host))
            self.exec(host, ["ip", "link", "set", "lo", "up"])
            self.host_dir(host).mkdir(parents=True, exist_ok=True)
        # A star: each link its own /30, the router reachable at one address (10.77.0.1 on its
        # loopback) routed to from every host.
        self.exec("r", ["ip", "addr", "add", f"{self.router_ip}/32", "dev", "lo"])
        for k, host in enumerate(self.hosts[1:], start=1):
            a, b = f"v{self.tag}{host}", f"r{self.tag}{host}"
            _ip(
                "link",
                "add",
                a,
                "netns",
                self.ns(host),
                "type",
                "veth",
                "peer",
                "name",
                b,
                "netns",
                self.ns("r"),
            )
            ip_h, ip_r = f"10.77.{k}.2", f"10.77.{k}.1"
            self.exec(host, ["ip", "addr", "add", f"{ip_h}/30", "dev", a])
            self.exec("r", ["ip", "addr", "add", f"{ip_r}/30", "dev", b])
            self.exec(host, ["ip", "link", "set", a, "up"])
            self.exec("r", ["ip", "link", "set", b, "up"])
            self.exec(host, ["ip", "route", "add", f"{self.router_ip}/32", "via", ip_r])
            self.links[host] = (a, b, ip_h, ip_r)

    def netem(self, host: str, delay_ms: float = 20.0, loss_pct: float = 1.0) -> bool:
        """Delay and loss on a host's link, both directions. False when the kernel has no netem
        (sch_netem not built or loadable: "Specified qdisc kind is unknown"); the link is then as is."""
        a, b, _, _ = self.links[host]
        for h, dev in ((host, a), ("r", b)):
            try:
                self.exec(h, ["tc", "qdisc", "replace", "dev", dev, "root", "netem", "delay", f"{delay_ms}ms",
                              "loss", f"{loss_pct}%"])  # fmt: skip
            except subprocess.CalledProcessError as exc:
                if "unknown" in (exc.stderr or ""):
                    return False
                raise
        return True

    def slow_link(self, host: str, delay_ms: float = 20.0, loss_pct: float = 1.0) -> str:
        """Delay and loss in user space where the kernel has no netem: a relay
        (tests/support/slow_link.py) in the host's namespace, listening on its loopback and
        relaying to the router across the host's link. Returns the endpoint the host's processes
        connect to instead of the router's."""
        name = f"link-{host}"
        logs = self.host_dir(host) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        argv = ["--target", f"{self.router_ip}:{ROUTER_PORT}", "--delay-ms", str(delay_ms),
                "--loss-pct", str(loss_pct)]  # fmt: skip
        cmd = ["ip", "netns", "exec", self.ns(host), sys.executable, "-m", "tests.support.slow_link", *argv]
        with (logs / f"{name}.out").open("wb") as out, (logs / f"{name}.log").open("wb") as err:
            p = subprocess.Popen(cmd, stdout=out, stderr=err, stdin=subprocess.DEVNULL, env=env, cwd=REPO)
        self.procs.append(Proc(name, host, argv, p, logs / f"{name}.log"))
        return f"tcp/127.0.0.1:{self.wait_ready(name, 30)['port']}"

    def link(self, host: str, up: bool) -> None:
        """Cut (or restore) a host's link, as a pulled cable does: the router's end goes down, so
        the host sees its carrier lost. (Setting the host's own end down would also delete its
        route to the router, which nothing puts back when it comes up again: the host would stay
        cut off for good. The route is put back on restore all the same.)"""
        a, b, _, ip_r = self.links[host]
        self.exec("r", ["ip", "link", "set", b, "up" if up else "down"])
        if up:
            self.exec(host, ["ip", "link", "set", a, "up"])
            self.exec(host, ["ip", "route", "replace", f"{self.router_ip}/32", "via", ip_r])

    def link_bytes(self, host: str) -> int:
        """Bytes through a host's link so far (both directions)."""
        a, _, _, _ = self.links[host]
        out = self.exec(
            host,
            ["cat", f"/sys/class/net/{a}/statistics/rx_bytes", f"/sys/class/net/{a}/statistics/tx_bytes"],
        )
        return sum(int(x) for x in out.stdout.split())

    def run_in(
        self, host: str, cellctl_args: list[str], timeout_s: float = 120.0
    ) -> subprocess.CompletedProcess:
        """A short `cellctl` command on ``host`` (its namespace and directory), its output."""
        env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        return subprocess.run(
            ["ip", "netns", "exec", self.ns(host), sys.executable, "-m", "cellctl", *cellctl_args],
            capture_output=True, text=True, cwd=self.host_dir(host), env=env, timeout=timeout_s, check=False,
        )  # fmt: skip

    def exec(self, host: str, argv: list[str]) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["ip", "netns", "exec", self.ns(host), *argv], check=True, capture_output=True, text=True
        )

    # ------------------------------------------------------------------------------- processes

    def start(self, name: str, host: str, cellctl_args: list[str], env: dict[str, str] | None = None) -> Proc:
        """`python -m cellctl <args>` on ``host`` (its namespace, its directory as cwd), with every
        other host's directory hidden under an empty tmpfs, and a /dev/shm of its own."""
        others = [self.host_dir(h) for h in self.hosts if h != host]
        hidden = [f"mount -t tmpfs -o size=1m,mode=0700 tmpfs {shlex.quote(str(d))}" for d in others]
        # /dev/shm too: Zenoh 1.x hands every message over 3 kB through a shared-memory segment
        # when the other end can open it (transport/shared_memory, on by default), so with the
        # host's /dev/shm shared a cloud crossed the "link" as a reference (0.5 MB on the wire
        # for a 9 MB job). Each process gets its own, as on a machine of its own.
        mounts = " && ".join([*hidden, "mount -t tmpfs -o size=256m,mode=1777 tmpfs /dev/shm"])
        argv = [sys.executable, "-m", "cellctl", "--log-format", "json", *cellctl_args]
        script = f"{mounts} && cd {shlex.quote(str(self.host_dir(host)))} && exec {shlex.join(argv)}"
        cmd = [
            "ip",
            "netns",
            "exec",
            self.ns(host),
            "unshare",
            "--mount",
            "--propagation",
            "private",
            "sh",
            "-c",
            script,
        ]
        full_env = {**os.environ, "CELL_RWS_PASSWORD": "robotics", **(env or {})}
        full_env["PYTHONPATH"] = str(REPO) + os.pathsep + full_env.get("PYTHONPATH", "")
        logs = self.host_dir(host) / "logs"
        logs.mkdir(exist_ok=True)
        with (logs / f"{name}.out").open("wb") as out, (logs / f"{name}.log").open("wb") as err:
            p = subprocess.Popen(cmd, stdout=out, stderr=err, stdin=subprocess.DEVNULL, env=full_env)
        proc = Proc(name, host, cellctl_args, p, logs / f"{name}.log")
        self.procs.append(proc)
        return proc

    def proc(self, name: str) -> Proc:
        return next(p for p in reversed(self.procs) if p.name == name)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        p = self.proc(name)
        with contextlib.suppress(ProcessLookupError):
            p.popen.send_signal(sig)
        p.popen.wait(30)

    def restart(self, name: str) -> Proc:
        p = self.proc(name)
        return self.start(name, p.host, p.argv)

    def wait_ready(self, name: str, timeout_s: float = 120.0) -> dict[str, Any]:
        p = self.proc(name)
        out = p.log.with_suffix(".out")
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if p.popen.poll() is not None:
                raise RuntimeError(f"{name} exited with {p.popen.returncode}: {p.log.read_text()[-2000:]}")
            with contextlib.suppress(OSError, ValueError):
                for line in out.read_text().splitlines():
                    if line.startswith("{") and json.loads(line).get("ready"):
                        return json.loads(line)
            time.sleep(0.2)
        raise TimeoutError(f"{name} not ready within {timeout_s} s")

    def stop_all(self, grace_s: float = 20.0) -> dict[str, int | None]:
        codes: dict[str, int | None] = {}
        for p in reversed(self.procs):
            if p.popen.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.popen.send_signal(signal.SIGTERM)
        for p in reversed(self.procs):
            try:
                codes[p.name] = p.popen.wait(grace_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    p.popen.kill()
                codes[p.name] = p.popen.wait()
        return codes

    def close(self) -> None:
        """Stop every process and delete every namespace of this fleet (links go with them)."""
        with contextlib.suppress(Exception):
            self.stop_all()
        for host in self.hosts:
            _ip("netns", "delete", self.ns(host), check=False)
