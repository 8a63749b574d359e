"""The one loopback port picker (demo and tests): ports below the kernel's ephemeral range, each
handed out once, free when handed out."""

from __future__ import annotations

import socket

from cellctl.commands.demo_cmd import _ephemeral_floor, free_port


def test_ports_are_below_the_ephemeral_range_distinct_and_free():
    """Binding port 0 gave ports from the ephemeral range, where an outgoing connection could take
    one before its server bound it (a daemon failed to start in CI: address already in use)."""
    floor = _ephemeral_floor()
    tcp = [free_port() for _ in range(40)]
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(40)]
    ports = tcp + udp
    assert len(set(ports)) == len(ports)
    assert all(20000 <= p < floor for p in ports), (floor, sorted(ports)[-3:])
    for port, kind in [(p, socket.SOCK_STREAM) for p in tcp] + [(p, socket.SOCK_DGRAM) for p in udp]:
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", port))
