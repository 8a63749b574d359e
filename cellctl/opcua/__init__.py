"""The cell's OPC UA server for a plant's systems (OPC 40210 GMS; docs/opcua.md)."""
