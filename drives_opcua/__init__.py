"""drives-opcua: the fleet as an OPC UA server (docs/opcua.md)."""
