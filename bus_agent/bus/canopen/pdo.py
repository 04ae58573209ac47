"""PDO configuration by SDO (CiA 301 §7.2.2): read a node's layout, or write one.

The same three policies as the EtherCAT backend: ``node`` (use the mapping the node has, read
from 0x1400/0x1600/0x1800/0x1A00 + n), ``default`` (write
:func:`bus_agent.bus.canopen.mapping.default_layout`) and ``explicit`` (write the configured
layout). Writing follows CiA 301's order: COB-ID invalid (bit 31), mapping count 0, entries,
count, transmission type, COB-ID valid. Runs before the loop (start-up, recovery of a rebooted
node). Takes SDO functions bound to one node, so tests drive it against a simulated node.
"""

from __future__ import annotations

from bus_agent.bus.canopen import mapping as m
from bus_agent.bus.canopen.sdo import SdoRead, SdoWrite, read_uint, write_uint

POLICIES = ("node", "default", "explicit")


def read_layout(sdo_read: SdoRead) -> m.Layout:
    """The valid PDOs of a node as it has them now."""
    def side(comm: int, mp: int) -> tuple[m.PdoMap, ...]:
        pdos = []
        for n in range(m.MAX_PDOS):
            cob = read_uint(sdo_read, comm + n, 1)
            if cob & m.COB_ID_INVALID:
                continue
            count = read_uint(sdo_read, mp + n, 0)
            entries = tuple(m.entry_of(read_uint(sdo_read, mp + n, i)) for i in range(1, count + 1))
            if entries:
                pdos.append(m.PdoMap(cob & 0x7FF, entries))
        return tuple(pdos)

    return m.Layout(rpdos=side(m.RPDO_COMM, m.RPDO_MAP), tpdos=side(m.TPDO_COMM, m.TPDO_MAP))


def write_layout(sdo_write: SdoWrite, layout: m.Layout) -> None:
    """Write ``layout`` (PDO n = the n-th of the layout; the others invalid), synchronous."""
    for comm, mp, pdos in ((m.RPDO_COMM, m.RPDO_MAP, layout.rpdos), (m.TPDO_COMM, m.TPDO_MAP, layout.tpdos)):
        for n in range(m.MAX_PDOS):
            pdo = pdos[n] if n < len(pdos) else None
            cob = pdo.cob_id if pdo is not None else 0
            write_uint(sdo_write, comm + n, 1, cob | m.COB_ID_INVALID, 32)
            if pdo is None:
                continue
            write_uint(sdo_write, mp + n, 0, 0, 8)
            for i, entry in enumerate(pdo.entries, start=1):
                write_uint(sdo_write, mp + n, i, m.mapping_value(entry), 32)
            write_uint(sdo_write, mp + n, 0, len(pdo.entries), 8)
            write_uint(sdo_write, comm + n, 2, m.TRANSMISSION_SYNC, 8)
            write_uint(sdo_write, comm + n, 1, cob, 32)


def layout_for(policy: str, node_id: int, sdo_read: SdoRead, sdo_write: SdoWrite,
               explicit: m.Layout | None = None) -> m.Layout:
    """Apply ``policy`` to one node; returns the layout the codec is built from (checked).
    Raises LayoutError / SdoError."""
    if policy == "node":
        layout = read_layout(sdo_read)
    elif policy == "default":
        layout = m.default_layout(node_id)
        write_layout(sdo_write, layout)
    elif policy == "explicit":
        if explicit is None:
            raise m.LayoutError(f"node {node_id}: PDO policy explicit without a layout")
        m.check_layout(explicit, node_id)
        layout = explicit
        write_layout(sdo_write, layout)
    else:
        raise m.LayoutError(f"node {node_id}: PDO policy {policy!r} is not one of {', '.join(POLICIES)}")
    m.check_layout(layout, node_id)
    return layout
