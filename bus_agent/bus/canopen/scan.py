"""Find the CANopen nodes on a bus and describe them: identity (0x1018), device type (0x1000),
name (0x1008), heartbeat time (0x1017) and PDO mappings (0x1400..0x1A03), all read by SDO.

Nodes are found with python-canopen's ``NodeScanner``: an SDO upload of 0x1000 to every node id
(or the ids given), plus any heartbeat, EMCY or PDO heard meanwhile. Read-only: nothing is
written and no NMT command is sent. Not for a running agent's bus while it cycles (it would only
add SDO traffic, but a scan is a commissioning tool).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Sequence

from bus_agent.bus.base import BusError
from bus_agent.bus.canopen import pdo as pdo_mod, sdo as sdo_mod
from bus_agent.bus.canopen.bus import open_network
from bus_agent.bus.canopen.cob import SDO_RX_BASE
from bus_agent.bus.mapping import SlaveMapping, split_entry

#: How long answers are collected after the search requests.
LISTEN_S = 0.5


@dataclass(frozen=True)
class NodeReport:
    """What a scan found out about one node (``error``: why some of it could not be read)."""

    node_id: int
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    device_type: int | None = None
    name: str = ""
    heartbeat_ms: int | None = None
    mapping: SlaveMapping | None = None
    error: str = ""

    def pdos(self, tx: bool) -> list[tuple[int, list[tuple[int, int, int]]]]:
        """(COB-ID, [(index, subindex, bits)]) of every valid RPDO (``tx`` False) or TPDO."""
        m = self.mapping
        if m is None:
            return []
        cobs = dict(m.cob_ids)
        return [(cobs[p], [split_entry(e) for e in pdo_mod.pdo_entries(m, p)]) for p in (m.tx_pdos if tx else m.rx_pdos)]

    def as_dict(self) -> dict[str, Any]:
        def pdos(tx: bool) -> list[dict]:
            return [{"cob_id": cob, "entries": [f"0x{i:04X}:{s}/{b}" for i, s, b in entries]}
                    for cob, entries in self.pdos(tx)]
        return {"node_id": self.node_id, "vendor_id": self.vendor_id, "product_code": self.product_code,
                "revision": self.revision, "serial": self.serial, "device_type": self.device_type,
                "name": self.name, "heartbeat_ms": self.heartbeat_ms,
                "rpdo": pdos(False), "tpdo": pdos(True), "error": self.error}


def scan(channel: str, interface: str, node_ids: Sequence[int] = (), listen_s: float = LISTEN_S,
         sdo_timeout_s: float = 0.3) -> list[NodeReport]:
    """Search the bus and read every node found. Raises BusError when the bus cannot be opened."""
    net = open_network(channel, interface)
    try:
        ids = sorted(set(node_ids)) or list(range(1, 128))
        for nid in ids:
            net.send_message(SDO_RX_BASE + nid, b"\x40\x00\x10\x00\x00\x00\x00\x00")  # upload 0x1000:0
        time.sleep(listen_s)
        found = sorted(n for n in net.scanner.nodes if not node_ids or n in ids)
        return [_describe(net, nid, sdo_timeout_s) for nid in found]
    finally:
        net.disconnect()


def _describe(net: Any, nid: int, sdo_timeout_s: float) -> NodeReport:
    import canopen

    node = canopen.RemoteNode(nid, canopen.ObjectDictionary())
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
    net.add_node(node)

    def read(index: int, sub: int) -> bytes:
        return sdo_mod.read(node.sdo, nid, index, sub)

    try:
        ident = [sdo_mod.read_uint(read, 0x1018, s) for s in (1, 2, 3, 4)]
        device_type = sdo_mod.read_uint(read, 0x1000, 0)
    except BusError as e:
        return NodeReport(nid, error=str(e))
    name, heartbeat, mapping, error = "", None, None, ""
    try:
        name = read(0x1008, 0).decode(errors="replace")
    except BusError:
        pass
    try:
        heartbeat = sdo_mod.read_uint(read, 0x1017, 0)
        mapping = pdo_mod.read_mapping(read)
    except BusError as e:
        error = str(e)
    vendor, product, revision, serial = ident
    return NodeReport(nid, vendor, product, revision, serial, device_type=device_type, name=name, heartbeat_ms=heartbeat, mapping=mapping,
                      error=error)


def format_table(reports: Sequence[NodeReport]) -> str:
    """One block per node: identity line, then its PDOs."""
    lines = []
    for r in reports:
        if r.vendor_id is None:
            lines.append(f"node {r.node_id}: {r.error}")
            continue
        lines.append(f"node {r.node_id}: {r.name or '-'} vendor 0x{r.vendor_id:08X} product 0x{r.product_code:08X} "
                     f"revision 0x{r.revision:08X} serial 0x{r.serial:08X} device type 0x{r.device_type:08X} "
                     f"heartbeat {r.heartbeat_ms} ms")
        for what, tx in (("rpdo", False), ("tpdo", True)):
            for cob, entries in r.pdos(tx):
                lines.append(f"  {what} 0x{cob:03X}: " + ", ".join(f"0x{i:04X}:{s} ({b} bits)" for i, s, b in entries))
        if r.error:
            lines.append(f"  error: {r.error}")
    return "\n".join(lines)
