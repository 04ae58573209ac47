"""Find the CANopen nodes on a bus and describe them: identity (0x1018), device type (0x1000),
name (0x1008), heartbeat time (0x1017) and PDO mappings (0x1400..0x1A03), all read by SDO.

Nodes are found with python-canopen's ``NodeScanner``: an SDO upload of 0x1000 to every node id
(or the ids given), plus any heartbeat, EMCY or PDO heard meanwhile. Read-only: nothing is
written and no NMT command is sent. Not for a running agent's bus while it cycles (it would only
add SDO traffic, but a scan is a commissioning tool).

With EDS files (``--eds PATH``, a file or a directory of ``*.eds``), each node is matched to the
EDS whose identity is its own (vendor id, product code, revision when the EDS gives one; read
for the node's id), named by it, and the PDOs where its mapping differs from that EDS's default
are listed (:func:`eds_differences`).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from typing import Any, Sequence

from bus_agent.bus.base import BusError
from bus_agent.bus.canopen import pdo as pdo_mod, sdo as sdo_mod
from bus_agent.bus.canopen.bus import open_network
from bus_agent.bus.canopen.cob import MAX_PDOS, RPDO_MAP, SDO_RX_BASE, TPDO_MAP
from bus_agent.bus.mapping import SlaveMapping, split_entry
from bus_agent.devices.eds import EdsDevice, EdsError, load as load_eds

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
    eds: str = ""                      # the matching EDS file ("" none given or none matches)
    device: str = ""                   # its ProductName
    eds_checked: int = 0               # how many EDS files were compared
    differences: tuple[str, ...] = ()  # PDOs whose mapping is not the EDS default

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
                "rpdo": pdos(False), "tpdo": pdos(True), "error": self.error,
                "eds": self.eds, "device": self.device, "differences": list(self.differences)}


def eds_files(path: str) -> list[str]:
    """``path`` itself, or the ``*.eds`` files of a directory (sorted). Raises EdsError."""
    if os.path.isdir(path):
        files = sorted(os.path.join(path, f) for f in os.listdir(path) if f.lower().endswith(".eds"))
        if not files:
            raise EdsError(f"EDS directory {path}: no *.eds file")
        return files
    if not os.path.isfile(path):
        raise EdsError(f"EDS {path}: no such file or directory")
    return [path]


def _pdo_text(cob: int | None, entries: Sequence[int]) -> str:
    if cob is None:
        return "not valid"
    return f"0x{cob:03X} [" + " ".join(f"{i:04X}" + (f":{s:02X}" if s else "") for i, s, _b in map(split_entry, entries)) + "]"


def eds_differences(mapping: SlaveMapping, device: EdsDevice) -> tuple[str, ...]:
    """The PDOs (1..4) whose COB-ID, validity or entries differ between a node's ``mapping`` and
    its EDS's default, e.g. ``RPDO1: node 0x204 [6040 2100], EDS not valid``."""
    eds = pdo_mod.eds_mapping(device)
    out = []
    for name, base in (("RPDO", RPDO_MAP), ("TPDO", TPDO_MAP)):
        for n in range(MAX_PDOS):
            sides = []
            for m in (mapping, eds):
                cobs = dict(m.cob_ids)
                sides.append((cobs.get(base + n), pdo_mod.pdo_entries(m, base + n)))
            if sides[0] != sides[1]:
                out.append(f"{name}{n + 1}: node {_pdo_text(*sides[0])}, EDS {_pdo_text(*sides[1])}")
    return tuple(out)


def match_eds(report: NodeReport, files: Sequence[str]) -> NodeReport:
    """``report`` with the EDS of ``files`` whose identity is the node's (the first), and where its
    mapping differs from that EDS's default. A file that cannot be read is skipped."""
    if report.vendor_id is None or not files:
        return report
    for path in files:
        try:
            device = load_eds(path, report.node_id)
        except EdsError:
            continue
        if device.identity_mismatch(report.vendor_id, report.product_code or 0, report.revision or 0) is None:
            differences = eds_differences(report.mapping, device) if report.mapping is not None else ()
            return dataclasses.replace(report, eds=path, device=device.product_name, eds_checked=len(files),
                                       differences=differences)
    return dataclasses.replace(report, eds_checked=len(files))


def scan(channel: str, interface: str, node_ids: Sequence[int] = (), listen_s: float = LISTEN_S,
         sdo_timeout_s: float = 0.3, eds: Sequence[str] = ()) -> list[NodeReport]:
    """Search the bus and read every node found, each matched to one of the EDS files ``eds``.
    Raises BusError when the bus cannot be opened."""
    net = open_network(channel, interface)
    try:
        ids = sorted(set(node_ids)) or list(range(1, 128))
        for nid in ids:
            net.send_message(SDO_RX_BASE + nid, b"\x40\x00\x10\x00\x00\x00\x00\x00")  # upload 0x1000:0
        time.sleep(listen_s)
        found = sorted(n for n in net.scanner.nodes if not node_ids or n in ids)
        return [match_eds(_describe(net, nid, sdo_timeout_s), eds) for nid in found]
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
        ident = sdo_mod.read_identity(read)
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
        if r.eds:
            lines.append(f"  EDS: {r.eds} ({r.device or 'no ProductName'}): "
                         + ("mapping as its default" if not r.differences else "mapping differs from its default"))
            lines += [f"    {d}" for d in r.differences]
        elif r.eds_checked:
            lines.append(f"  EDS: none of {r.eds_checked} file(s) has its identity")
        if r.error:
            lines.append(f"  error: {r.error}")
    return "\n".join(lines)
