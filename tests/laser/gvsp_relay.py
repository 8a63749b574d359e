"""A loopback GigE Vision relay that answers PACKETRESEND: a device that serves resends, in front of
one that does not (Aravis's ``arv-fake-gv-camera-0.8``), for the GigE source's tests.

The client opens the relay's address (127.0.0.2 by default) as the device::

    with GvspRelay(drop_every=29) as relay:            # the fake device runs on 127.0.0.1
        src = GigeProfileSource(relay.address, ...)
        ...
        relay.stats.dropped, relay.stats.resent

* GVCP (UDP 3956 on ``address``): every command from a client socket goes to the device
  (127.0.0.1:3956) from a socket of the relay's own for that client (the device sees one controller
  per client socket, as without the relay), every answer back from port 3956. Writes of stream
  channel 0's destination (SCDA, 0x0D18) and host port (SCP, 0x0D00), by WRITEREG or WRITEMEM,
  are noted as the client's stream address and rewritten to the relay's GVSP socket, so the device
  streams to the relay; reads of them answer the client's values. The GVCP capability register
  (0x0934) is answered with the PACKET_RESEND bit set: Aravis's ``ArvGvDevice`` reads it and turns a
  new stream's ``packet-resend`` to NEVER on a device without it.
* GVSP: every packet from the device is kept in a bounded cache under (block id, packet id) and sent
  on to the client's stream address from ``address`` (Aravis's packet-socket reader, used when it
  runs as root, filters on the device's address); payload packets chosen by ``drop_every`` (every
  Nth) or ``drop_ratio`` (seeded) are not sent. Leaders and trailers always pass (Aravis asks for a
  missing packet when a later one arrives). Test packets (the packet-size check) pass as any other.
* PACKETRESEND_CMD (0x0040, no acknowledge): the packets of the range asked are sent again from the
  cache (never dropped), in the standard form (word 0: stream channel << 16 | 16-bit block id, then
  first and last 24-bit packet ids, as Aravis 0.8.26 sends it with the channel 0) and the extended
  one (flag 0x10: channel word, first and last 32-bit packet ids, 64-bit block id). With
  ``answer_resends`` False they are counted and ignored, as the fake device does.

Every counter is in :attr:`GvspRelay.stats` (written by the relay's thread only). Test support:
production code never imports it. Only loopback addresses are bound or dialled.
"""

from __future__ import annotations

import random
import selectors
import socket
import struct
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

__all__ = ["GvspRelay", "RelayStats", "parse_gvsp_header", "parse_packet_resend"]

GVCP_PORT = 3956

# GVCP (GigE Vision 2.x; Aravis's src/arvgvcpprivate.h)
_CMD_TYPE = 0x42
_FLAG_EXTENDED_IDS = 0x10
PACKET_RESEND_CMD = 0x0040
READREG_CMD, READREG_ACK = 0x0080, 0x0081
WRITEREG_CMD = 0x0082
READMEM_CMD, READMEM_ACK = 0x0084, 0x0085
WRITEMEM_CMD = 0x0086
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_HEADER = struct.Struct(">BBHHH")  # type, flags, command, length, request id

# bootstrap registers
GVCP_CAPABILITY = 0x0934
CAPABILITY_PACKET_RESEND = 1 << 2
SCP0 = 0x0D00  # stream channel 0: host port in the low 16 bits
SCDA0 = 0x0D18  # stream channel 0: destination address

# GVSP (Aravis's src/arvgvspprivate.h)
_EXTENDED_ID_BIT = 0x80  # in byte 4, the first byte of packet_infos
CONTENT_LEADER, CONTENT_TRAILER, CONTENT_PAYLOAD = 0x01, 0x02, 0x03


def parse_gvsp_header(packet: bytes) -> tuple[int, int, int, bool] | None:
    """(block id, packet id, content type, extended ids) of a GVSP packet, None if too short."""
    if len(packet) < 8:
        return None
    if packet[4] & _EXTENDED_ID_BIT:
        if len(packet) < 20:
            return None
        (infos,) = struct.unpack_from(">I", packet, 4)
        block, pid = struct.unpack_from(">QI", packet, 8)
        return block, pid, (infos >> 24) & 0x7F, True
    block, infos = struct.unpack_from(">HI", packet, 2)
    return block, infos & 0x00FFFFFF, (infos >> 24) & 0x7F, False


def parse_packet_resend(packet: bytes) -> tuple[int, int, int, int] | None:
    """(stream channel, block id, first packet id, last packet id) of a PACKETRESEND_CMD, else None."""
    if len(packet) < _HEADER.size + 12:
        return None
    kind, flags, command, _length, _req = _HEADER.unpack_from(packet)
    if kind != _CMD_TYPE or command != PACKET_RESEND_CMD:
        return None
    if flags & _FLAG_EXTENDED_IDS:
        if len(packet) < _HEADER.size + 20:
            return None
        channel, first, last, block = struct.unpack_from(">IIIQ", packet, _HEADER.size)
        return channel >> 16, block, first, last
    word0, first, last = struct.unpack_from(">III", packet, _HEADER.size)
    return word0 >> 16, word0 & 0xFFFF, first & 0x00FFFFFF, last & 0x00FFFFFF


def _ip_to_u32(ip: str) -> int:
    return struct.unpack(">I", socket.inet_aton(ip))[0]


def _u32_to_ip(value: int) -> str:
    return socket.inet_ntoa(struct.pack(">I", value))


@dataclass
class RelayStats:
    """What crossed the relay (written by its thread; plain ints, read from any thread)."""

    gvcp_commands: int = 0  # forwarded to the device
    gvcp_answers: int = 0  # forwarded back to a client
    stream_redirects: int = 0  # SCDA / SCP writes rewritten to the relay
    gvsp_received: int = 0  # from the device
    gvsp_forwarded: int = 0  # to the client (resends not included)
    gvsp_unrouted: int = 0  # arrived before the client's stream address was known
    dropped: int = 0  # payload packets not forwarded
    resend_commands: int = 0  # PACKETRESEND_CMDs received
    extended_resend_commands: int = 0  # of which in the extended-id form
    requested: int = 0  # packets those commands asked for
    resent: int = 0  # packets sent again from the cache
    unavailable: int = 0  # asked for, not in the cache (never sent, or evicted)
    dropped_keys: list[tuple[int, int]] = field(default_factory=list)  # (block id, packet id)
    resent_keys: list[tuple[int, int]] = field(default_factory=list)


class GvspRelay:
    """A GVCP/GVSP relay on ``address`` in front of the device at ``device``, run by a thread.

    Args:
        device: the real device's GVCP address (its port 3956).
        address: the loopback address the client opens as the device (its port 3956 and a GVSP port).
        drop_every: drop every Nth payload packet (0: none).
        drop_ratio: drop this fraction of the payload packets at random (``seed``).
        answer_resends: serve PACKETRESEND from the cache (False: count and ignore them).
        cache_packets: how many recent GVSP packets are kept for resends.
    """

    def __init__(
        self,
        device: str = "127.0.0.1",
        address: str = "127.0.0.2",
        *,
        drop_every: int = 0,
        drop_ratio: float = 0.0,
        seed: int = 0,
        answer_resends: bool = True,
        cache_packets: int = 4096,
    ) -> None:
        for ip in (device, address):
            if not ip.startswith("127."):
                raise ValueError(f"{ip!r}: the relay binds and dials loopback addresses only")
        self.device = (device, GVCP_PORT)
        self.address = address
        self.drop_every = drop_every
        self.answer_resends = answer_resends
        self.cache_packets = cache_packets
        self.stats = RelayStats()
        self.client_stream: tuple[str, int] | None = None
        self._drop_ratio = drop_ratio
        self._rng = random.Random(seed)
        self._payload_seen = 0
        self._cache: OrderedDict[tuple[int, int], bytes] = OrderedDict()
        self._client_scp = 0  # the client's last SCP0 value (its high bits kept on rewrite)
        self._client_scda = 0
        self._upstream: dict[tuple[str, int], socket.socket] = {}  # client GVCP address -> socket
        self._pending: dict[tuple[tuple[str, int], int], tuple[int, tuple[int, ...]]] = {}
        self._sel: selectors.BaseSelector | None = None
        self._gvcp: socket.socket | None = None
        self._gvsp: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ control (any thread)

    def start(self) -> GvspRelay:
        """Bind ``address``:3956 and a GVSP port, and relay in a background thread; returns self."""
        self._gvcp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._gvsp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._gvcp.bind((self.address, GVCP_PORT))
            try:  # room for a stall of the relay's thread (beyond rmem_max: needs CAP_NET_ADMIN)
                self._gvsp.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, 8 << 20)
            except OSError:
                self._gvsp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            self._gvsp.bind((self.address, 0))
        except OSError:
            self._close_sockets()
            raise
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._gvcp, selectors.EVENT_READ, self._on_gvcp)
        self._sel.register(self._gvsp, selectors.EVENT_READ, self._on_gvsp)
        self._thread = threading.Thread(target=self._run, name="gvsp-relay", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread; it closes every socket."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        else:
            self._close_sockets()
        if self._error is not None:
            raise RuntimeError(f"the GVSP relay failed: {self._error!r}") from self._error

    def __enter__(self) -> GvspRelay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def stream_port(self) -> int:
        """The relay's GVSP port (where the device streams)."""
        assert self._gvsp is not None
        return self._gvsp.getsockname()[1]

    # ---------------------------------------------------------------------- the relay thread

    def _run(self) -> None:
        assert self._sel is not None
        try:
            while not self._stop.is_set():
                for key, _ in self._sel.select(timeout=0.05):
                    key.data(key.fileobj)
        except BaseException as exc:  # reported by close()
            self._error = exc
        finally:
            self._close_sockets()

    def _close_sockets(self) -> None:
        if self._sel is not None:
            self._sel.close()
            self._sel = None
        for s in [self._gvcp, self._gvsp, *self._upstream.values()]:
            if s is not None:
                s.close()
        self._upstream.clear()

    def _on_gvcp(self, sock: socket.socket) -> None:
        """A command from a client (its control socket, or its stream socket's PACKETRESEND)."""
        try:
            data, client = sock.recvfrom(65536)
        except (BlockingIOError, ConnectionRefusedError):
            return
        if len(data) < _HEADER.size:
            return
        kind, _flags, command, _length, req = _HEADER.unpack_from(data)
        if kind == _CMD_TYPE and command == PACKET_RESEND_CMD:
            self._on_resend(data)
            return
        if kind == _CMD_TYPE and command == WRITEREG_CMD:
            data = self._rewrite_writereg(data)
        elif kind == _CMD_TYPE and command == WRITEMEM_CMD:
            data = self._rewrite_writemem(data)
        elif kind == _CMD_TYPE and command == READREG_CMD:
            n = (len(data) - _HEADER.size) // 4
            self._pending[(client, req)] = (READREG_CMD, struct.unpack_from(f">{n}I", data, _HEADER.size))
        elif kind == _CMD_TYPE and command == READMEM_CMD and len(data) >= _HEADER.size + 8:
            address, _reserved, size = struct.unpack_from(">IHH", data, _HEADER.size)
            self._pending[(client, req)] = (READMEM_CMD, (address, size))
        while len(self._pending) > 1024:  # reads the device never answered
            del self._pending[next(iter(self._pending))]
        up = self._upstream.get(client)
        if up is None:
            up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            up.bind((self.address, 0))
            self._upstream[client] = up
            assert self._sel is not None
            self._sel.register(up, selectors.EVENT_READ, lambda s, c=client: self._on_answer(s, c))
        up.sendto(data, self.device)
        self.stats.gvcp_commands += 1

    def _on_answer(self, sock: socket.socket, client: tuple[str, int]) -> None:
        """The device's answer to ``client``'s command: the reads of patched registers fixed up."""
        try:
            data = sock.recv(65536)
        except (BlockingIOError, ConnectionRefusedError):
            return  # ICMP port unreachable: the device is not running; the client times out
        if len(data) >= _HEADER.size:
            _kind, _flags, command, _length, req = _HEADER.unpack_from(data)
            asked = self._pending.pop((client, req), None)
            if asked is not None and command == READREG_ACK and asked[0] == READREG_CMD:
                data = self._patch_readreg(data, asked[1])
            elif asked is not None and command == READMEM_ACK and asked[0] == READMEM_CMD:
                data = self._patch_readmem(data)
        assert self._gvcp is not None
        self._gvcp.sendto(data, client)
        self.stats.gvcp_answers += 1

    # ---------------------------------------------------------------- register interception

    def _register_to_device(self, address: int, value: int) -> int:
        """The value written to the device for a client's write of ``value`` at ``address``."""
        if address == SCDA0:
            self._client_scda = value
            self._update_client_stream()
            self.stats.stream_redirects += 1
            return _ip_to_u32(self.address) if value else 0
        if address == SCP0:
            self._client_scp = value
            self._update_client_stream()
            self.stats.stream_redirects += 1
            return (value & 0xFFFF0000) | self.stream_port if value & 0xFFFF else value
        return value

    def _register_to_client(self, address: int, value: int) -> int:
        """The value a client reads at ``address`` (the device holds the relay's stream address)."""
        if address == SCDA0:
            return self._client_scda
        if address == SCP0:
            return (value & 0xFFFF0000) | (self._client_scp & 0xFFFF)
        if address == GVCP_CAPABILITY:
            return value | CAPABILITY_PACKET_RESEND
        return value

    def _update_client_stream(self) -> None:
        port = self._client_scp & 0xFFFF
        self.client_stream = (_u32_to_ip(self._client_scda), port) if self._client_scda and port else None

    def _rewrite_writereg(self, data: bytes) -> bytes:
        out = bytearray(data)
        for off in range(_HEADER.size, len(data) - 7, 8):
            address, value = struct.unpack_from(">II", data, off)
            struct.pack_into(">I", out, off + 4, self._register_to_device(address, value))
        return bytes(out)

    def _rewrite_writemem(self, data: bytes) -> bytes:
        (base,) = struct.unpack_from(">I", data, _HEADER.size)
        out = bytearray(data)
        start = _HEADER.size + 4
        for reg in (SCP0, SCDA0):
            off = start + reg - base
            if base <= reg and off + 4 <= len(data):
                (value,) = struct.unpack_from(">I", data, off)
                struct.pack_into(">I", out, off, self._register_to_device(reg, value))
        return bytes(out)

    def _patch_readreg(self, data: bytes, addresses: tuple[int, ...]) -> bytes:
        out = bytearray(data)
        for i, address in enumerate(addresses):
            off = _HEADER.size + 4 * i
            if off + 4 <= len(data):
                (value,) = struct.unpack_from(">I", data, off)
                struct.pack_into(">I", out, off, self._register_to_client(address, value))
        return bytes(out)

    def _patch_readmem(self, data: bytes) -> bytes:
        (base,) = struct.unpack_from(">I", data, _HEADER.size)
        out = bytearray(data)
        start = _HEADER.size + 4
        for reg in (GVCP_CAPABILITY, SCP0, SCDA0):
            off = start + reg - base
            if base <= reg and off + 4 <= len(data):
                (value,) = struct.unpack_from(">I", data, off)
                struct.pack_into(">I", out, off, self._register_to_client(reg, value))
        return bytes(out)

    # ------------------------------------------------------------------------------ GVSP

    def _on_gvsp(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(65536)
        except (BlockingIOError, ConnectionRefusedError):
            return
        st = self.stats
        st.gvsp_received += 1
        head = parse_gvsp_header(data)
        if head is None:
            return
        block, pid, content, _ext = head
        key = (block, pid)
        self._cache[key] = data
        self._cache.move_to_end(key)
        while len(self._cache) > self.cache_packets:
            self._cache.popitem(last=False)
        if self.client_stream is None:
            st.gvsp_unrouted += 1
            return
        if content == CONTENT_PAYLOAD and self._drop_this():
            st.dropped += 1
            st.dropped_keys.append(key)
            return
        sock.sendto(data, self.client_stream)
        st.gvsp_forwarded += 1

    def _drop_this(self) -> bool:
        self._payload_seen += 1
        if self.drop_every and self._payload_seen % self.drop_every == 0:
            return True
        return bool(self._drop_ratio) and self._rng.random() < self._drop_ratio

    def _on_resend(self, data: bytes) -> None:
        asked = parse_packet_resend(data)
        if asked is None:
            return
        _channel, block, first, last = asked
        st = self.stats
        st.resend_commands += 1
        if data[1] & _FLAG_EXTENDED_IDS:
            st.extended_resend_commands += 1
        st.requested += max(0, last - first + 1)
        if not self.answer_resends or self.client_stream is None or last - first >= self.cache_packets:
            return  # (a range longer than the cache cannot be served: ignored, as a whole)
        assert self._gvsp is not None
        for pid in range(first, last + 1):
            packet = self._cache.get((block, pid))
            if packet is None:
                st.unavailable += 1
                continue
            self._gvsp.sendto(packet, self.client_stream)
            st.resent += 1
            st.resent_keys.append((block, pid))
