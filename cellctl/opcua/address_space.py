"""The OPC 40210 (GMS) information model in an asyncua server: the vendored nodesets loaded in
their dependency order, and the one asyncua importer gap they hit worked around (docs/opcua.md).
"""

from __future__ import annotations

from dataclasses import is_dataclass
from pathlib import Path
from typing import Any

import structlog
from asyncua import Server
from asyncua.common.xmlimporter import XmlImporter

log = structlog.get_logger(__name__)

NODESET_DIR = Path(__file__).parent / "nodesets"

#: the companion models in the order each one's required models are already there
#: (core -> DI -> IA -> Machinery -> Machinery/Result -> MachineTool -> GMS)
NODESET_CHAIN = (
    "Opc.Ua.Di.NodeSet2.xml",
    "Opc.Ua.IA.NodeSet2.xml",
    "Opc.Ua.Machinery.NodeSet2.xml",
    "Opc.Ua.Machinery.Result.NodeSet2.xml",
    "Opc.Ua.MachineTool.NodeSet2.xml",
    "Opc.Ua.Gms.NodeSet2.xml",
)

GMS_NS_URI = "http://opcfoundation.org/UA/GMS/"
DI_NS_URI = "http://opcfoundation.org/UA/DI/"
MACHINERY_NS_URI = "http://opcfoundation.org/UA/Machinery/"
MACHINETOOL_NS_URI = "http://opcfoundation.org/UA/MachineTool/"
RESULT_NS_URI = "http://opcfoundation.org/UA/Machinery/Result/"


class NodesetImporter(XmlImporter):
    """asyncua's importer, taught one thing it lacks: a structure field that is itself written as
    an ExtensionObject (``<TypeId>`` + ``<Body>``) inside a default value. Machinery/Result's
    ``ResultType`` default value has one (its ``ResultMetaData``); asyncua 2.1.0 looks the field
    ``TypeId`` up in the structure and fails with ``KeyError: 'TypeId'``. The body is the field's
    value, so it is unwrapped and handed back to the importer unchanged otherwise."""

    def _set_attr(self, atttype: Any, fargs: dict, attname: str, val: Any) -> None:
        if isinstance(val, list) and val and is_dataclass(_plain_type(atttype)):
            names = [name for name, _ in val]
            if names == ["TypeId", "Body"]:
                body = val[1][1]
                # the body is [(StructureName, fields)]; an empty body is the structure's default
                val = body[0][1] if body and isinstance(body[0][1], list) else []
        super()._set_attr(atttype, fargs, attname, val)


def _plain_type(atttype: Any) -> Any:
    from asyncua.ua.uatypes import type_from_optional, type_is_optional

    return type_from_optional(atttype) if type_is_optional(atttype) else atttype


async def load_gms_model(server: Server) -> None:
    """Import the nodeset chain into ``server`` (after ``server.init()``); strict: any node that
    does not import is an error, not a warning."""
    for name in NODESET_CHAIN:
        importer = NodesetImporter(server, strict_mode=True)
        await importer.import_xml(str(NODESET_DIR / name))
        log.debug("opcua_nodeset_loaded", nodeset=name)


#: the daemon's cell state -> Machinery's MachineryItemState (OPC 40001-1, 8.3): the cell executes
#: while it plans, scans, analyses or winds a job down; it is not executing when idle or paused
#: (a paused job waits for the operator); out of service when faulted or emergency-stopped; not
#: available while starting or when no state has reached the server.
MACHINERY_ITEM_STATE: dict[str, str] = {
    "starting": "NotAvailable",
    "idle": "NotExecuting",
    "planning": "Executing",
    "scanning": "Executing",
    "paused": "NotExecuting",
    "analysing": "Executing",
    "stopping": "Executing",
    "faulted": "OutOfService",
    "emergency_stopped": "OutOfService",
}
#: the state nodes of MachineryItemState_StateMachineType (Machinery 1.03 nodeset ids)
_STATE_NODE_IDS = {"Executing": 5006, "NotAvailable": 5005, "NotExecuting": 5007, "OutOfService": 5004}


class GmsNodes:
    """The cell's GMS object and the nodes the server writes or answers on."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self.gms: Any = None
        self.cell_state: Any = None  # String: the daemon's own state name
        self.item_state: Any = None  # LocalizedText: MachineryItemState's CurrentState
        self.item_state_id: Any = None  # NodeId: its Id property
        self.get_latest_result: Any = None
        self.machinery_ns = 0

    async def build(self, *, cell_id: str, software_revision: str, app_ns: int) -> GmsNodes:
        from asyncua import ua
        from asyncua.common.instantiate_util import instantiate

        s = self.server
        gms_ns = await s.get_namespace_index(GMS_NS_URI)
        di_ns = await s.get_namespace_index(DI_NS_URI)
        result_ns = await s.get_namespace_index(RESULT_NS_URI)
        self.machinery_ns = await s.get_namespace_index(MACHINERY_NS_URI)
        gms_type = s.get_node(ua.NodeId(1002, gms_ns))  # GMSType
        created = await instantiate(
            s.nodes.objects, gms_type, nodeid=ua.NodeId(f"cell-{cell_id}", app_ns),
            bname=ua.QualifiedName(f"Cell-{cell_id}", app_ns), dname=ua.LocalizedText(f"Cell {cell_id}"),
        )  # fmt: skip
        self.gms = s.get_node(created[0])  # then every child it made
        ident = await self.gms.get_child(f"{di_ns}:Identification")
        await (await ident.get_child(f"{di_ns}:Manufacturer")).write_value(ua.LocalizedText("cellctl", "en"))
        await (await ident.get_child(f"{di_ns}:SerialNumber")).write_value(cell_id)
        await (await ident.get_child(f"{di_ns}:ProductInstanceUri")).write_value(
            f"urn:cellctl:cell:{cell_id}"
        )
        await ident.add_property(di_ns, "Model", ua.LocalizedText("cellctl laser-scanning cell", "en"), ua.VariantType.LocalizedText)  # fmt: skip
        await ident.add_property(di_ns, "SoftwareRevision", software_revision, ua.VariantType.String)  # fmt: skip

        blocks = await self.gms.get_child(f"{self.machinery_ns}:MachineryBuildingBlocks")
        item_state = await blocks.get_child(f"{self.machinery_ns}:MachineryItemState")
        try:  # the state machine's CurrentState and its Id, as instantiated from the type
            self.item_state = await item_state.get_child("0:CurrentState")
            self.item_state_id = await self.item_state.get_child("0:Id")
        except ua.UaStatusCodeError:
            self.item_state = await item_state.add_variable(
                ua.NodeId(f"cell-{cell_id}.MachineryItemState.CurrentState", app_ns),
                ua.QualifiedName("CurrentState", 0), ua.LocalizedText("NotAvailable", "en"),
                varianttype=ua.VariantType.LocalizedText, datatype=ua.NodeId(ua.ObjectIds.LocalizedText),
            )  # fmt: skip
            self.item_state_id = await self.item_state.add_property(
                ua.NodeId(f"cell-{cell_id}.MachineryItemState.CurrentState.Id", app_ns),
                ua.QualifiedName("Id", 0), self._state_node("NotAvailable"), ua.VariantType.NodeId,
            )  # fmt: skip
        self.cell_state = await self.gms.add_variable(
            ua.NodeId(f"cell-{cell_id}.CellState", app_ns), ua.QualifiedName("CellState", app_ns), "",
            varianttype=ua.VariantType.String,
        )  # fmt: skip
        rm = await self.gms.get_child(f"{gms_ns}:ResultManagement")
        self.get_latest_result = await rm.get_child(f"{result_ns}:GetLatestResult")
        await self.set_state(None)
        return self

    def _state_node(self, name: str) -> Any:
        from asyncua import ua

        return ua.NodeId(_STATE_NODE_IDS[name], self.machinery_ns)

    async def set_state(self, cell_state: str | None) -> None:
        """Write the daemon's state (None: none known) and its MachineryItemState."""
        from asyncua import ua

        item = MACHINERY_ITEM_STATE.get(cell_state or "", "NotAvailable")
        await self.cell_state.write_value(cell_state or "")
        await self.item_state.write_value(ua.LocalizedText(item, "en"))
        await self.item_state_id.write_value(self._state_node(item), ua.VariantType.NodeId)
