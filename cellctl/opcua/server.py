"""`cellctl opcua`: an asyncua server whose GMS object follows the cell through its Zenoh API.

One :class:`CellLink` (the HMI's client: the state publication and the report publications, no
live cloud) feeds it; the server never touches the daemon's files or process. The latest report
that reached it answers ``GetLatestResult``.
"""

from __future__ import annotations

import asyncio
import itertools
from typing import Any

import structlog
from asyncua import Server, ua

from cellctl import __version__
from cellctl.api import ReportEnvelope
from cellctl.config import CellConfig
from cellctl.hmi.link import CellLink
from cellctl.opcua.address_space import GmsNodes, load_gms_model
from cellctl.opcua.results import result_data

log = structlog.get_logger(__name__)

APP_URI_PREFIX = "urn:cellctl:opcua:"
#: GetLatestResult's Error output: 0 OK; below 0 application errors (Machinery/Result 1.00)
ERROR_NO_RESULT = -1


class OpcuaConfigError(Exception):
    """An [opcua] section this server cannot serve as asked."""


class CellOpcuaServer:
    def __init__(self, cfg: CellConfig) -> None:
        if not cfg.opcua.allow_insecure:
            raise OpcuaConfigError(
                "[opcua] this version serves no secured endpoint yet (Basic256Sha256 with the cell CA's "
                "certificate is the next step, docs/opcua.md): anonymous, unencrypted access is refused "
                "unless [opcua] allow_insecure = true (tests, a trusted loopback)"
            )
        self.cfg = cfg
        self.server = Server()
        self.nodes: GmsNodes | None = None
        self.latest: ReportEnvelope | None = None
        self._handles = itertools.count(1)
        self._state_dirty = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self.link = CellLink(cfg, self._on_event, live=False, who="opcua")
        self.link.on_report = self._on_report
        self.endpoint = f"opc.tcp://{cfg.opcua.bind}:{cfg.opcua.port}/cellctl/"

    # ---------------------------------------------------------------- set-up
    async def start(self, link_timeout_s: float = 60.0) -> None:
        self._loop = asyncio.get_running_loop()
        s = self.server
        await s.init()
        s.set_endpoint(self.endpoint)
        s.set_server_name(f"cellctl cell {self.cfg.cell.id}")
        await s.set_application_uri(f"{APP_URI_PREFIX}{self.cfg.cell.id}")
        s.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        await load_gms_model(s)
        await s.load_data_type_definitions()
        app_ns = await s.register_namespace(f"{APP_URI_PREFIX}{self.cfg.cell.id}")
        self.nodes = await GmsNodes(s).build(
            cell_id=self.cfg.cell.id, software_revision=__version__, app_ns=app_ns
        )
        s.link_method(self.nodes.get_latest_result, self._get_latest_result)
        await s.start()
        log.info("opcua_listening", endpoint=self.endpoint, security="none (allow_insecure)")
        await self.link.start(timeout_s=link_timeout_s)

    async def stop(self) -> None:
        await self.link.close()
        await self.server.stop()

    async def run(self, stop: asyncio.Event) -> None:
        """Mirror the cell's state into the address space until ``stop`` is set."""
        stopping = asyncio.ensure_future(stop.wait())
        try:
            while not stop.is_set():
                dirty = asyncio.ensure_future(self._state_dirty.wait())
                await asyncio.wait({dirty, stopping}, return_when=asyncio.FIRST_COMPLETED)
                dirty.cancel()
                self._state_dirty.clear()
                await self.sync_state()
        finally:
            stopping.cancel()

    async def sync_state(self) -> None:
        assert self.nodes is not None
        st = self.link.status
        await self.nodes.set_state(st.state.value if st is not None else None)

    # ---------------------------------------------------------------- the link's callbacks (its thread)
    def _on_event(self, event: dict[str, Any]) -> None:
        if event.get("type") == "status" and self._loop is not None:
            self._loop.call_soon_threadsafe(self._state_dirty.set)

    def _on_report(self, env: ReportEnvelope) -> None:
        if env.ok and env.report is not None:
            self.latest = env  # one reference swap: readers see the old or the new envelope

    # ---------------------------------------------------------------- methods
    async def _get_latest_result(self, parent: ua.NodeId, timeout_hint: ua.Variant) -> list[ua.Variant]:
        env = self.latest
        handle = ua.Variant(next(self._handles), ua.VariantType.UInt32)
        if env is None or env.report is None:
            empty = ua.ResultDataType(ResultMetaData=ua.ResultMetaDataType(ResultId=""), ResultContent=[])
            return [handle, ua.Variant(empty), ua.Variant(ERROR_NO_RESULT, ua.VariantType.Int32)]
        return [
            handle,
            ua.Variant(result_data(ua, env.report, env.job_id)),
            ua.Variant(0, ua.VariantType.Int32),
        ]


async def serve(cfg: CellConfig, stop: asyncio.Event) -> int:
    srv = CellOpcuaServer(cfg)
    try:
        await srv.start()
        await srv.run(stop)
    finally:
        await srv.stop()
    return 0
