"""``[can]``: the configuration of the CANopen backend (``bus-agent --can CHANNEL``; docs/canopen.md),
its validation, and its reading from TOML (:class:`bus_agent.toml_table.Table`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from bus_agent.bus.mapping import POLICIES
from bus_agent.toml_table import ConfigError, Table

log = logging.getLogger("bus_agent.config")

#: CAN backend: python-can interfaces and PDO policies (bus_agent/bus/canopen, docs/canopen.md):
#: the EtherCAT backend's policy names (bus_agent.bus.mapping.POLICIES) but ``predefined``, and
#: ``eds`` (the default mapping of the node's EDS).
CAN_INTERFACES = ("socketcan", "udp_multicast")
CAN_PDO_POLICIES = tuple(p for p in POLICIES if p not in ("predefined", "eds")) + ("eds",)
#: Earlier words for a policy, still read with a deprecation warning.
CAN_PDO_ALIASES = {"node": "drive"}


@dataclass(frozen=True)
class CanNode:
    """``[[can.nodes]]``: one CANopen node (slave position = its place in the list)."""

    node_id: int
    pdo: str = "default"                       # CAN_PDO_POLICIES ("node": alias of "drive")
    eds: str | None = None                     # EDS file: object names and types, identity check, pdo "eds"
    rpdo: tuple[tuple[int, ...], ...] = ()      # explicit: mapping u32 entries per RPDO 1..4
    tpdo: tuple[tuple[int, ...], ...] = ()      # explicit: mapping u32 entries per TPDO 1..4
    startup_sdos: tuple[tuple[int, int, int, int], ...] = ()  # (index, subindex, value, bytes)


@dataclass(frozen=True)
class CanConfig:
    """``[can]``: the CANopen backend (``bus-agent --can CHANNEL``)."""

    channel: str
    interface: str = "socketcan"
    nodes: tuple[CanNode, ...] = ()
    heartbeat_ms: int = 200
    #: 0x1019: 0 = SYNC without data; 2..240 = SYNC carries a counter 1..N (written to every node)
    sync_counter: int = 0


def validate_can(c: CanConfig) -> None:
    if not c.channel:
        raise ConfigError("can.channel: required (a SocketCAN interface, or a udp_multicast group)")
    if c.interface not in CAN_INTERFACES:
        raise ConfigError(f"can.interface: {c.interface!r} is not one of {', '.join(CAN_INTERFACES)}")
    if not c.nodes:
        raise ConfigError("can.nodes: at least one node id")
    if not 1 <= c.heartbeat_ms <= 0xFFFF:
        raise ConfigError(f"can.heartbeat_ms: {c.heartbeat_ms} must be 1..65535")
    if isinstance(c.sync_counter, bool) or c.sync_counter != 0 and not 2 <= c.sync_counter <= 240:
        raise ConfigError(f"can.sync_counter: {c.sync_counter} must be 0 (SYNC without counter) or 2..240 "
                          "(0x1019: the counter runs 1..N; 1 and 241..255 are reserved)")
    seen: set[int] = set()
    for i, n in enumerate(c.nodes):
        key = f"can.nodes[{i}]"
        if isinstance(n.node_id, bool) or not isinstance(n.node_id, int) or not 1 <= n.node_id <= 127:
            raise ConfigError(f"{key}.id: {n.node_id!r} must be a node id 1..127")
        if n.node_id in seen:
            raise ConfigError(f"{key}.id: node {n.node_id} listed twice")
        seen.add(n.node_id)
        if n.pdo not in CAN_PDO_POLICIES:
            why = (": 'predefined' assigns fixed EtherCAT PDOs, a CANopen node has no PDO assignment; use 'drive' "
                   "(its own mapping)" if n.pdo == "predefined" else "")
            raise ConfigError(f"{key}.pdo: {n.pdo!r} is not one of {', '.join(CAN_PDO_POLICIES)}{why}")
        if n.pdo == "eds" and not n.eds:
            raise ConfigError(f"{key}.pdo: 'eds' uses the default mapping of the node's EDS: give eds = \"FILE\"")
        if (n.pdo == "explicit") != bool(n.rpdo or n.tpdo):
            raise ConfigError(f"{key}: rpdo/tpdo are given exactly when pdo = \"explicit\"")
        for side, pdos in (("rpdo", n.rpdo), ("tpdo", n.tpdo)):
            if len(pdos) > 4 or any(not isinstance(v, int) or not 0 < v <= 0xFFFFFFFF for p in pdos for v in p):
                raise ConfigError(f"{key}.{side}: up to 4 PDOs, each a list of mapping entries "
                                  "(index << 16 | subindex << 8 | bits)")
        for j, (index, sub, _value, size) in enumerate(n.startup_sdos):
            if not (0 <= index <= 0xFFFF and 0 <= sub <= 0xFF and size in (1, 2, 4)):
                raise ConfigError(f"{key}.sdo[{j}]: index 0..0xFFFF, subindex 0..255, size 1, 2 or 4")


def can_config(channel: str, interface: str | None, node_ids: tuple[int, ...], sync_counter: int = 0) -> CanConfig:
    """``--can CHANNEL --can-interface IF --nodes 1,2,3 [--sync-counter N]`` as a CanConfig
    (defaults for the rest)."""
    return CanConfig(channel=channel, interface=interface or "socketcan",
                     nodes=tuple(CanNode(node_id=n) for n in node_ids), sync_counter=sync_counter)


def can_from_table(t: Table) -> CanConfig:
    nodes = []
    for i, raw in enumerate(t.get("nodes", list, [])):
        if isinstance(raw, int) and not isinstance(raw, bool):
            nodes.append(CanNode(node_id=raw))
            continue
        n = Table(raw, f"can.nodes[{i}]")
        sdos = []
        for j, s in enumerate(n.get("sdo", list, [])):
            st = Table(s, f"can.nodes[{i}].sdo[{j}]")
            sdos.append((st.get("index", int), st.get("subindex", int, 0), st.get("value", int), st.get("size", int)))
            st.done()
        pdo = n.get("pdo", str, "default")
        if pdo in CAN_PDO_ALIASES:
            log.warning("can.nodes[%d].pdo: %r is deprecated, say %r (the same policy, as for EtherCAT drives)",
                        i, pdo, CAN_PDO_ALIASES[pdo])
            pdo = CAN_PDO_ALIASES[pdo]
        nodes.append(CanNode(node_id=n.get("id", int), pdo=pdo, eds=n.get("eds", str, None),
                             rpdo=tuple(tuple(p) for p in n.get("rpdo", list, [])),
                             tpdo=tuple(tuple(p) for p in n.get("tpdo", list, [])), startup_sdos=tuple(sdos)))
        n.done()
    cfg = CanConfig(channel=t.get("channel", str), interface=t.get("interface", str, "socketcan"),
                    nodes=tuple(nodes), heartbeat_ms=t.get("heartbeat_ms", int, 200),
                    sync_counter=t.get("sync_counter", int, 0))
    t.done()
    return cfg
