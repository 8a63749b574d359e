"""`cellctl opcua`: an asyncua server whose GMS object follows the cell through its Zenoh API.

One :class:`CellLink` (the HMI's client: the state publication and the report publications, no
live cloud) feeds it; the server never touches the daemon's files or process. The latest report
that reached it answers ``GetLatestResult``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from typing import Any

import structlog
from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator
from asyncua.crypto.validator import CertificateValidatorOptions as V
from asyncua.server.user_managers import UserManager

from cellctl import __version__
from cellctl.api import ReportEnvelope
from cellctl.config import CellConfig, ConfigError, check_secret_file_mode
from cellctl.hmi.auth import Authenticator, AuthError, load_users
from cellctl.hmi.link import CellLink
from cellctl.opcua.address_space import GmsNodes, load_gms_model
from cellctl.opcua.results import result_data

log = structlog.get_logger(__name__)

APP_URI_PREFIX = "urn:cellctl:opcua:"
#: GetLatestResult's Error output: 0 OK; below 0 application errors (Machinery/Result 1.00)
ERROR_NO_RESULT = -1


class OpcuaConfigError(Exception):
    """An [opcua] section this server cannot serve as asked."""


def _format(path: Any) -> str:
    with open(path, "rb") as f:
        return "pem" if f.read(11) == b"-----BEGIN " else "der"


class HmiUserManager(UserManager):
    """OPC UA users are the HMI's: its users file (``cellctl hmi adduser``) checked by its
    :class:`Authenticator`; anonymous and wrong passwords refused. The HMI role of a session's user
    (:meth:`role`) is what method checks use; asyncua's own role is only User."""

    def __init__(self, auth: Authenticator) -> None:
        self.auth = auth

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> User | None:
        if username is None or password is None:
            log.info("opcua_login_refused", user=username, why="anonymous")
            return None
        user = self.auth.verify(username, password)
        if user is None:
            log.info("opcua_login_refused", user=username, why="wrong name or password")
            return None
        log.info("opcua_login", user=username, role=user.role)
        return User(role=UserRole.User, name=username)

    def role(self, name: str | None) -> str | None:
        u = self.auth.users.get(name or "")
        return u.role if u else None


class CellOpcuaServer:
    def __init__(self, cfg: CellConfig) -> None:
        o = cfg.opcua
        self.users: HmiUserManager | None = None
        if not o.allow_insecure:
            if o.cert_file is None or o.key_file is None or o.users_file is None or o.trusted_dir is None:
                raise OpcuaConfigError(
                    "[opcua] the secured endpoint needs cert_file, key_file, users_file and trusted_dir "
                    "(or allow_insecure = true: no security, anonymous; tests and a trusted loopback only)"
                )
            try:
                check_secret_file_mode(o.key_file, what="opcua.key_file")
                self.users = HmiUserManager(Authenticator(load_users(o.users_file)))
            except (AuthError, ConfigError, OSError) as exc:
                raise OpcuaConfigError(f"[opcua] {exc}") from None
            if not o.trusted_dir.is_dir():
                raise OpcuaConfigError(f"[opcua] trusted_dir {o.trusted_dir}: not a directory")
        self.cfg = cfg
        self.server = Server(user_manager=self.users)
        self.nodes: GmsNodes | None = None
        self.latest: ReportEnvelope | None = None
        self._handles = itertools.count(1)
        self._state_dirty = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._listening = False
        self.link = CellLink(cfg, self._on_event, live=False, who="opcua")
        self.link.on_report = self._on_report
        self.endpoint = f"opc.tcp://{cfg.opcua.bind}:{cfg.opcua.port}/cellctl/"

    # ---------------------------------------------------------------- set-up
    async def start(self, link_timeout_s: float = 60.0) -> None:
        # asyncua's own log at INFO and below names every call and its parameters (a log-in's
        # token among them): warnings and errors only
        logging.getLogger("asyncua").setLevel(max(logging.WARNING, logging.getLogger("asyncua").level))
        self._loop = asyncio.get_running_loop()
        s = self.server
        await s.init()
        s.set_endpoint(self.endpoint)
        s.set_server_name(f"cellctl cell {self.cfg.cell.id}")
        await s.set_application_uri(f"{APP_URI_PREFIX}{self.cfg.cell.id}")
        o = self.cfg.opcua
        if o.allow_insecure:
            s.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            security = "none (allow_insecure)"
        else:
            assert o.cert_file is not None and o.key_file is not None
            # PEM or DER by content, not by the file's suffix (asyncua's default)
            await s.load_certificate(str(o.cert_file), format=_format(o.cert_file))
            await s.load_private_key(str(o.key_file), format=_format(o.key_file))
            s.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            s.set_security_IDs(["Username"])
            assert o.trusted_dir is not None
            trust = TrustStore([o.trusted_dir], [])
            await trust.load()
            # validity period, the application URI in the certificate, issued by (or being) a trusted
            # certificate; key usage is not required (docs/opcua.md)
            checks = V.TIME_RANGE | V.URI | V.TRUSTED | V.PEER_CLIENT
            s.set_certificate_validator(CertificateValidator(checks, trust))
            security = "Basic256Sha256 SignAndEncrypt, users"
        await load_gms_model(s)
        await s.load_data_type_definitions()
        app_ns = await s.register_namespace(f"{APP_URI_PREFIX}{self.cfg.cell.id}")
        self.nodes = await GmsNodes(s).build(
            cell_id=self.cfg.cell.id, software_revision=__version__, app_ns=app_ns
        )
        s.link_method(self.nodes.get_latest_result, self._get_latest_result)
        await s.start()
        self._listening = True
        log.info("opcua_listening", endpoint=self.endpoint, security=security)
        await self.link.start(timeout_s=link_timeout_s)

    async def stop(self) -> None:
        await self.link.close()
        if self._listening:
            self._listening = False
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
    """Serve until ``stop``; a stop while the server still waits for the daemon ends it at once."""
    srv = CellOpcuaServer(cfg)
    starting = asyncio.ensure_future(srv.start())
    stopping = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({starting, stopping}, return_when=asyncio.FIRST_COMPLETED)
        if not starting.done():
            starting.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await starting
            return 0
        starting.result()  # its error, if it failed (the daemon never answered: ZenohSetupError)
        await srv.run(stop)
    finally:
        stopping.cancel()
        await srv.stop()
    return 0
