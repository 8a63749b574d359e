"""`cellctl opcua`: the GMS nodeset chain loads, and an asyncua client reads the cell's state and
its latest result from a server fed only through the Zenoh API (a test publisher on loopback)."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.crypto.uacrypto import CertProperties

from analysis.contracts.job import Report
from cellctl.api import CellState, CellStatus, Keys, ReportEnvelope
from cellctl.api.session import build_zenoh_config, close_session, open_session
from cellctl.config import ConfigError, parse_config
from cellctl.hmi.auth import add_user
from cellctl.opcua.address_space import GMS_NS_URI, MACHINERY_ITEM_STATE
from cellctl.opcua.results import CONTENT_FORMAT, report_characteristics
from cellctl.opcua.server import ERROR_NO_RESULT, CellOpcuaServer, OpcuaConfigError
from tests.support.pki import Pki
from tests.support.ports import free_port
from tests.support.reports import report_dict
from tests.support.waits import wait_subscribed, wait_until

NODE_CLIENT = Path(__file__).parent / "node" / "client.mjs"

LINES = [
    {"family": "transverse", "index": 1, "zmax_mm": 1.25, "sz_avg_mm": 0.4, "sz_mm2": 120.0, "ci": 0.013,
     "sc_avg_per_mm": 4.3e-5, "cmax_per_mm": 2.1e-4, "pass": True},
    {"family": "longitudinal", "index": 2, "zmax_mm": 3.6, "sz_avg_mm": 1.9, "sz_mm2": 570.0, "ci": 0.02,
     "sc_avg_per_mm": 6.6e-5, "cmax_per_mm": 3.3e-4, "pass": False},
]  # fmt: skip


def _config(tmp_path, zenoh_port: int, opcua_port: int, **opcua):
    return parse_config({
        "cell": {"id": "c7", "data_dir": str(tmp_path / "data"), "designs_dir": str(tmp_path)},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{zenoh_port}"], "multicast_scouting": False},
        "opcua": {"enabled": True, "port": opcua_port, **opcua},
    })  # fmt: skip


def test_refuses_a_key_others_may_read_and_a_missing_users_file(tmp_path):
    cfg, _ = _secured_config(tmp_path, free_port(), free_port())
    assert cfg.opcua.bind == "127.0.0.1" and not cfg.opcua.allow_insecure
    cfg.opcua.key_file.chmod(0o644)
    with pytest.raises(OpcuaConfigError, match="chmod 600"):
        CellOpcuaServer(cfg)
    cfg.opcua.key_file.chmod(0o600)
    cfg.opcua.users_file.unlink()
    with pytest.raises(OpcuaConfigError, match="hmi-users"):
        CellOpcuaServer(cfg)


def test_characteristics_follow_the_report_and_its_tolerances():
    report = Report.model_validate(report_dict(LINES, plate_id="P-9", job_id="j1"))
    doc = report_characteristics(report)
    by_id = {c.CharacteristicIdentifier: c for c in doc.characteristics}
    assert doc.verdict == "fail" and len(by_id) == 12
    assert by_id["T1.Zmax"].ResultValue == 1.25 and by_id["T1.Zmax"].ResultEvaluation == "OK"
    assert by_id["L2.Zmax"].UpperToleranceLimit == 3.0 and by_id["L2.Zmax"].ResultEvaluation == "NotOK"
    assert by_id["L2.SZ"].ResultValue == 570.0 and by_id["L2.SZ"].ResultEvaluation == "Undefined"
    judged_at_standard = report.model_copy(
        update={"tolerances": report.tolerances.__class__(judge_at="standard")}
    )
    assert {
        c.CharacteristicIdentifier: c for c in report_characteristics(judged_at_standard).characteristics
    }["T1.Zmax"].UpperToleranceLimit == 2.0
    assert set(MACHINERY_ITEM_STATE) == {s.value for s in CellState}


@pytest.mark.slow
def test_a_client_reads_the_gms_object_the_state_and_the_latest_result(tmp_path):
    asyncio.run(_client_reads(tmp_path))


@pytest.mark.slow
@pytest.mark.process
def test_node_opcua_reads_the_latest_result(tmp_path):
    """An independent client (node-opcua, installed by scripts/setup.sh) finds the GMSType object and
    calls GetLatestResult (Good, Error 0, the result's bytes; node-opcua does not decode the
    Machinery/Result structure: docs/opcua.md)."""
    asyncio.run(_client_reads(tmp_path, node=True))


async def _node_client_reads(endpoint: str) -> None:
    assert (NODE_CLIENT.parent / "node_modules" / "node-opcua").is_dir(), (
        "node-opcua is not installed: run scripts/setup.sh (npm install in tests/opcua/node)"
    )
    proc = await asyncio.create_subprocess_exec(
        "node",
        str(NODE_CLIENT),
        endpoint,
        "c7",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 60.0)
    assert proc.returncode == 0, err.decode()
    lines = [ln for ln in out.decode().splitlines() if ln.startswith("CELLCTL-RESULT ")]
    assert len(lines) == 1, out.decode()[-2000:]  # node-opcua prints its own lines too
    got = json.loads(lines[0].removeprefix("CELLCTL-RESULT "))
    assert "failure" not in got, json.dumps(got)[:1500]
    assert got["type"].endswith("GMSType") and got["status"] == "Good" and got["error"] == 0
    # the Result arrives (an ExtensionObject as big as the report's content), undecoded by node-opcua
    assert got["resultType"] == "OpaqueStructure" and got["resultBytes"] > 2000


async def _client_reads(tmp_path, *, node: bool = False) -> None:
    cfg = _config(tmp_path, free_port(), free_port(), allow_insecure=True)
    keys = Keys(cfg.key_prefix)
    daemon = await asyncio.to_thread(
        open_session, build_zenoh_config(cfg.zenoh, role="serve"), what="test publisher"
    )
    srv = CellOpcuaServer(cfg)
    stop = asyncio.Event()
    runner = None
    try:
        await srv.start(link_timeout_s=20.0)
        runner = asyncio.ensure_future(srv.run(stop))
        await wait_subscribed(daemon, keys.report("j1"), 10.0, "the OPC UA server's report subscriber")
        await wait_subscribed(daemon, keys.state, 10.0, "the OPC UA server's state subscriber")
        report = Report.model_validate(report_dict(LINES, plate_id="P-9", job_id="j1"))
        env = ReportEnvelope(job_id="j1", plate_id="P-9", worker_id="w1", attempt=1, ok=True, report=report)
        daemon.put(keys.report("j1"), env.model_dump_json())
        status = CellStatus(cell_id="c7", state="scanning", t_utc="2026-12-07T20:00:00Z")
        daemon.put(keys.state, status.model_dump_json())
        await wait_until(lambda: srv.latest is not None, 10.0, "the report reaching the server")
        if node:
            await _node_client_reads(srv.endpoint)
            return

        async with Client(srv.endpoint, timeout=10) as client:
            await client.load_data_type_definitions()
            gms_ns = await client.get_namespace_index(GMS_NS_URI)
            cells = [n for n in await client.nodes.objects.get_children()
                     if (await n.read_browse_name()).Name == "Cell-c7"]  # fmt: skip
            assert len(cells) == 1
            cell = cells[0]
            assert (await cell.read_type_definition()) == ua.NodeId(1002, gms_ns)  # GMSType
            di = await client.get_namespace_index("http://opcfoundation.org/UA/DI/")
            ident = await cell.get_child(f"{di}:Identification")
            assert await (await ident.get_child(f"{di}:SerialNumber")).read_value() == "c7"
            mns = await client.get_namespace_index("http://opcfoundation.org/UA/Machinery/")
            state = await cell.get_child(
                [f"{mns}:MachineryBuildingBlocks", f"{mns}:MachineryItemState", "0:CurrentState"]
            )
            # the state publication is mirrored by the server's loop: wait on a subscription's change
            executing = asyncio.Event()

            class _OnChange:
                def datachange_notification(self, node, val, data) -> None:
                    if getattr(val, "Text", None) == "Executing":
                        executing.set()

            sub = await client.create_subscription(50, _OnChange())
            try:
                await sub.subscribe_data_change(state)
                await asyncio.wait_for(executing.wait(), 10.0)
            finally:
                await sub.delete()
            assert (await state.read_value()).Text == "Executing"

            result_ns = await client.get_namespace_index("http://opcfoundation.org/UA/Machinery/Result/")
            rm = await cell.get_child(f"{gms_ns}:ResultManagement")
            method = await rm.get_child(f"{result_ns}:GetLatestResult")
            handle, result, error = await rm.call_method(method, ua.Variant(1000, ua.VariantType.Int32))
            assert error == 0 and handle >= 1
            meta = result.ResultMetaData
            assert meta.ResultId == "j1" and meta.PartId == "P-9"
            assert meta.ResultEvaluation == ua.ResultEvaluationEnum.NotOK
            assert len(result.ResultContent) == 1 and meta.FileFormat == [CONTENT_FORMAT]
            content = json.loads(result.ResultContent[0].Value)
            got = {c["CharacteristicIdentifier"]: c for c in content["characteristics"]}
            assert got["T1.Zmax"]["ResultValue"] == 1.25 and got["L2.Zmax"]["ResultEvaluation"] == "NotOK"
            assert got["L2.Cmax"]["ResultValue"] == 3.3e-4 and got["T1.CI"]["ResultValue"] == 0.013
    finally:
        stop.set()
        if runner is not None:
            await runner
        await srv.stop()
        await asyncio.to_thread(close_session, daemon)


def _secured_config(tmp_path, zenoh_port: int, opcua_port: int):
    pki = Pki(tmp_path / "pki", rsa=True)
    cert, key = pki.leaf("opcua-c7", uri="urn:cellctl:opcua:c7")
    users = tmp_path / "hmi-users"
    add_user(users, "olga", "operator", "operator-pass-1")
    trusted = tmp_path / "trusted"  # the clients' CA: the cell's
    trusted.mkdir()
    shutil.copy(pki.ca_file, trusted / "cell-ca.pem")
    files = {
        "cert_file": str(cert),
        "key_file": str(key),
        "users_file": str(users),
        "trusted_dir": str(trusted),
    }
    return _config(tmp_path, zenoh_port, opcua_port, **files), pki


def test_the_secured_endpoint_needs_its_files(tmp_path):
    with pytest.raises(ConfigError, match="cert_file, key_file, users_file, trusted_dir"):
        _config(tmp_path, free_port(), free_port())


@pytest.mark.slow
def test_the_secured_endpoint_takes_an_hmi_user_and_refuses_anonymous_wrong_passwords_and_no_security(
    tmp_path,
):
    asyncio.run(_secured(tmp_path))


async def _secured(tmp_path) -> None:
    cfg, pki = _secured_config(tmp_path, free_port(), free_port())
    client_cert, client_key = pki.leaf("plant-mes", uri="urn:plant:mes")
    foreign_cert, foreign_key = Pki(tmp_path / "foreign", ca_cn="someone-else", rsa=True).leaf(
        "mes", uri="urn:plant:mes"
    )
    daemon = await asyncio.to_thread(
        open_session, build_zenoh_config(cfg.zenoh, role="serve"), what="test publisher"
    )
    srv = CellOpcuaServer(cfg)

    def client(user: str | None, password: str | None) -> Client:
        c = Client(srv.endpoint, timeout=10)
        c.application_uri = "urn:plant:mes"
        if user is not None:
            c.set_user(user)
            c.set_password(password or "")
        return c

    async def secure(c: Client, cert=client_cert, key=client_key) -> Client:
        await c.set_security(
            SecurityPolicyBasic256Sha256, certificate=str(cert),
            private_key=CertProperties(key, extension="pem"),
            mode=ua.MessageSecurityMode.SignAndEncrypt,
        )  # fmt: skip
        return c

    try:
        await srv.start(link_timeout_s=20.0)
        async with await secure(client("olga", "operator-pass-1")) as c:
            gms_ns = await c.get_namespace_index(GMS_NS_URI)
            result_ns = await c.get_namespace_index("http://opcfoundation.org/UA/Machinery/Result/")
            await c.load_data_type_definitions()
            cell = await c.nodes.objects.get_child(
                f"{await c.get_namespace_index('urn:cellctl:opcua:c7')}:Cell-c7"
            )
            rm = await cell.get_child(f"{gms_ns}:ResultManagement")
            _, _, error = await rm.call_method(
                await rm.get_child(f"{result_ns}:GetLatestResult"), ua.Variant(0, ua.VariantType.Int32)
            )
            assert error == ERROR_NO_RESULT  # no report has reached the server yet
        refusals = [
            ("olga", "wrong", ua.uaerrors.BadUserAccessDenied),
            ("nobody", "operator-pass-1", ua.uaerrors.BadUserAccessDenied),
            (None, None, ua.uaerrors.BadIdentityTokenRejected),  # anonymous
        ]
        for user, password, refusal in refusals:
            with pytest.raises(refusal):
                async with await secure(client(user, password)):
                    pass
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):  # a certificate from another CA
            async with await secure(client("olga", "operator-pass-1"), foreign_cert, foreign_key):
                pass
        with pytest.raises(ua.UaError, match="No matching endpoints"):  # no endpoint without security
            async with client("olga", "operator-pass-1"):
                pass
    finally:
        await srv.stop()
        await asyncio.to_thread(close_session, daemon)
