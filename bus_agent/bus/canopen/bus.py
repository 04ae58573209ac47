"""CanopenBus: CiA 402 drives on a CAN bus behind the Bus protocol (backend "canopen").

Built on python-can (the bus: SocketCAN, or ``udp_multicast`` between processes) and
python-canopen (``Network`` and its receive thread, the SDO client, NMT frames). Nothing above
the Bus protocol knows it is CAN: node i of ``node_ids`` is slave position i, and the NMT state
is reported as an AL state (:data:`bus_agent.bus.canopen.nmt.AL_OF_NMT`).

Start-up (not cycle-safe): ``open`` identifies every node by SDO (0x1018, 0x1008, retried until
``boot_timeout_s``) and sends it to pre-operational; ``start`` writes the heartbeat time (0x1017),
applies the PDO policy per node (:mod:`bus_agent.bus.canopen.pdo`), builds one codec per node (the
EtherCAT backend's :class:`~bus_agent.bus.codec.DriveCodec`, sliced into frames) and starts the nodes (NMT start), waiting for their heartbeats to say operational.

Cycle-safe: ``exchange`` takes the TPDOs received since the previous call (the answers to the
previous SYNC; the working counter counts the nodes whose every TPDO came), then sends every
node's RPDOs and one SYNC. ``inputs``/``set_outputs`` are per-node records.

Management (management thread): ``read_al_status`` is the heartbeat consumer's view (no bus
traffic); ``request_al_state`` sends NMT frames (broadcast for all); ``recover`` reconfigures a
node that booted (boot-up message seen) and starts it, never enabling its drive.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from bus_agent.bus.base import ALState, BusError, SlaveALStatus, SlaveIdentity, SlaveInfo
from bus_agent.bus.canopen import emcy as emcy_mod, pdo as pdo_mod, sdo as sdo_mod
from bus_agent.bus.canopen.cob import EMCY_COB_BASE, SYNC_COB_ID, SYNC_COUNTER_RANGE
from bus_agent.bus.canopen.heartbeat import HeartbeatConsumer
from bus_agent.bus.canopen.nmt import (AL_OF_NMT, BROADCAST, HEARTBEAT_COB_BASE, NMT_COB_ID, NMT_FOR_AL,
                                       NmtCommand, NmtState, nmt_frame)
from bus_agent.bus.codec import DriveCodec
from bus_agent.bus.emergency import EmergencyLog
from bus_agent.bus.mapping import MappingError, SlaveMapping, describe
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.startup_guard import StartupSteps
from bus_agent.can_config import CanConfig
from bus_agent.devices.eds import EdsDevice, EdsError, load as load_eds

log = logging.getLogger(__name__)

INTERFACES = ("socketcan", "udp_multicast")
DEFAULT_HEARTBEAT_MS = 200
#: Consumer time as a multiple of the producer time (CiA 301 leaves it to the integrator).
HEARTBEAT_TIMEOUT_FACTOR = 3.0
BOOT_TIMEOUT_S = 5.0
START_TIMEOUT_S = 5.0
SDO_TIMEOUT_S = 0.5
#: Deadline of configuring one node in start (about 10 to 40 SDO transfers of up to SDO_TIMEOUT_S each).
CONFIGURE_NODE_S = 30.0


@dataclass(frozen=True)
class NodeConfig:
    """One drive on the bus: node id, PDO policy (``default``/``drive``/``explicit``/``eds``) and
    the mapping of ``explicit``/``eds``, start-up SDOs ((index, subindex, bytes) written before NMT
    start), its EDS (``device``: read for this node id; names and types its objects, and its
    identity must match the node's)."""

    node_id: int
    pdo: str = "default"
    mapping: SlaveMapping | None = None
    startup_sdos: tuple[tuple[int, int, bytes], ...] = ()
    eds: str | None = None
    device: EdsDevice | None = None


@dataclass
class _Node:
    cfg: NodeConfig
    remote: Any = None                 # canopen.RemoteNode
    frames: pdo_mod.PdoFrames | None = None
    inputs: DriveInputs = field(default_factory=DriveInputs)
    outputs: DriveOutputs = field(default_factory=DriveOutputs)
    tpdo_seq: dict[int, int] = field(default_factory=dict)   # COB-ID -> frames received
    tpdo_seen: dict[int, int] = field(default_factory=dict)  # COB-ID -> seq at the last exchange
    tpdo_data: dict[int, bytes] = field(default_factory=dict)
    missed_tpdos: int = 0
    last_emcy: emcy_mod.Emergency | None = None
    objects: Any = None  # names and types of its objects from the node's EDS (codec, ``objects``)

    def __post_init__(self) -> None:
        if self.cfg.device is not None:
            self.objects = pdo_mod.eds_dictionary(self.cfg.device)


def open_can(channel: str, interface: str) -> Any:
    """A python-can bus (``udp_multicast``: classic CAN frames, no FD)."""
    import can

    if interface not in INTERFACES:
        raise BusError(f"CAN interface {interface!r} is not one of {', '.join(INTERFACES)}")
    kwargs: dict[str, Any] = {"fd": False} if interface == "udp_multicast" else {}
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, OSError, ValueError) as e:
        raise BusError(f"cannot open CAN {interface} channel {channel}: {e}") from None


def open_network(channel: str, interface: str) -> Any:
    """A python-canopen ``Network`` on :func:`open_can`, its receive thread running (python-can's
    ``Notifier``): callbacks subscribed on it run in that thread."""
    import can
    import canopen

    bus = open_can(channel, interface)
    net = canopen.Network(bus)
    net.notifier = can.Notifier(bus, net.listeners, 0.5)
    return net


class CanopenBus:
    """The Bus protocol over one CAN bus of CANopen CiA 402 nodes (backend "canopen")."""

    backend = "canopen"
    express_exchange = False  # an exchange sends a SYNC: every node would run a cycle

    def __init__(self, channel: str, nodes: Sequence[NodeConfig | int], interface: str = "socketcan",
                 heartbeat_ms: int = DEFAULT_HEARTBEAT_MS, boot_timeout_s: float = BOOT_TIMEOUT_S,
                 sdo_timeout_s: float = SDO_TIMEOUT_S, sync_counter: int = 0) -> None:
        cfgs = [n if isinstance(n, NodeConfig) else NodeConfig(int(n)) for n in nodes]
        ids = [c.node_id for c in cfgs]
        if not cfgs or len(set(ids)) != len(ids) or not all(1 <= i <= 127 for i in ids):
            raise BusError(f"CAN node ids must be distinct, 1..127, at least one: {ids}")
        if not 1 <= heartbeat_ms <= 0xFFFF:
            raise BusError(f"heartbeat time {heartbeat_ms} ms outside 1..65535")
        if sync_counter and sync_counter not in SYNC_COUNTER_RANGE:
            raise BusError(f"SYNC counter overflow value {sync_counter} is neither 0 nor 2..240 (0x1019)")
        self.channel = channel
        self.interface = interface
        self.heartbeat_ms = heartbeat_ms
        self.boot_timeout_s = boot_timeout_s
        self.sdo_timeout_s = sdo_timeout_s
        self.sync_counter = sync_counter
        # the SYNC frames' data, one per counter value (none: SYNC without data), made once
        self._sync_data = tuple(bytes((k,)) for k in range(1, sync_counter + 1)) or (b"",)
        self._sync_index = -1
        self._nodes = [_Node(c) for c in cfgs]
        self._by_id = {c.node_id: i for i, c in enumerate(cfgs)}
        self.heartbeats = HeartbeatConsumer(tuple(ids), heartbeat_ms / 1000.0 * HEARTBEAT_TIMEOUT_FACTOR)
        self.emergencies: collections.deque[emcy_mod.Emergency] = collections.deque(maxlen=256)
        self._emcy = EmergencyLog()
        #: Deadlines only, until the agent sets its guarded steps (stop signal, guard process)
        self.startup_steps = StartupSteps()
        #: position -> (error code, text) of its last EMCY (read by the cycle for error_text)
        self.error_texts = self._emcy.error_texts
        self.frames_sent = 0
        self.exchanges = 0
        self._changed: list[int] = []
        self._network: Any = None
        self._tpdo_owner: dict[int, _Node] = {}
        self._lock = threading.Lock()  # NMT/SDO configuration of a node (management vs start-up)
        self._opened = False

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(n.cfg.node_id for n in self._nodes)

    def _node(self, position: int) -> _Node:
        if not isinstance(position, int) or not 0 <= position < len(self._nodes):
            raise BusError(f"CAN {self.channel}: no node at position {position!r} (0..{len(self._nodes) - 1})")
        return self._nodes[position]

    # ---- receive callbacks (python-canopen's receive thread) -----------------------------------

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.heartbeats.on_frame(can_id - HEARTBEAT_COB_BASE, data, time.monotonic())

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        e = emcy_mod.decode(can_id - EMCY_COB_BASE, data)
        pos = self._by_id.get(e.node_id)
        if pos is not None:
            self._nodes[pos].last_emcy = e
            self._emcy.record(pos, e.error_code, e.error_register)
        self.emergencies.append(e)
        log.warning("CAN %s node %d: EMCY 0x%04X (%s), error register 0x%02X", self.channel, e.node_id,
                    e.error_code, e.text, e.error_register)

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node = self._tpdo_owner.get(can_id)
        if node is not None:
            node.tpdo_data[can_id] = bytes(data)
            node.tpdo_seq[can_id] = node.tpdo_seq.get(can_id, 0) + 1

    # ---- start-up --------------------------------------------------------------------------------

    def open(self) -> list[SlaveInfo]:
        """Open the CAN bus, identify every node by SDO, send it to pre-operational. Raises BusError."""
        import canopen

        net = open_network(self.channel, self.interface)
        self._network = net
        self._tpdo_owner.clear()
        infos = []
        try:
            for pos, node in enumerate(self._nodes):
                nid = node.cfg.node_id
                device = node.cfg.device
                od = device.od if device is not None else canopen.ObjectDictionary()
                node.remote = canopen.RemoteNode(nid, od)
                node.remote.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
                net.add_node(node.remote)
                net.subscribe(HEARTBEAT_COB_BASE + nid, self._on_heartbeat)
                net.subscribe(EMCY_COB_BASE + nid, self._on_emcy)
            for pos, node in enumerate(self._nodes):
                with self.startup_steps.step(f"CAN {self.channel}: node {node.cfg.node_id}: identification "
                                             "(0x1018, 0x1008)", self.boot_timeout_s + 2 * self.sdo_timeout_s + 1.0):
                    infos.append(self._identify(pos, node))
                self.send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, node.cfg.node_id)
        except BaseException:
            self._disconnect()
            raise
        self._opened = True
        return infos

    def _identify(self, pos: int, node: _Node) -> SlaveInfo:
        nid = node.cfg.node_id
        deadline = time.monotonic() + self.boot_timeout_s
        while True:
            try:
                ident = sdo_mod.read_identity(self._reader(node))
                break
            except sdo_mod.SDO_FAILURES as e:
                if e.abort_code or time.monotonic() >= deadline:
                    raise BusError(f"CAN {self.channel}: node {nid} (position {pos}) not identified within "
                                   f"{self.boot_timeout_s:g} s: {e}") from None
        try:
            name = self._reader(node)(0x1008, 0).decode(errors="replace")
        except sdo_mod.SDO_FAILURES:
            name = f"node{nid}"
        log.info("CAN %s: node %d %r vendor 0x%08X product 0x%08X revision 0x%08X serial 0x%08X",
                 self.channel, nid, name, *ident)
        device = node.cfg.device
        if device is not None:
            wrong = device.identity_mismatch(*ident[:3])
            if wrong:
                raise BusError(f"CAN {self.channel}: node {nid} (position {pos}, {name!r}) is not the device of its "
                               f"EDS {device.path} ({device.product_name or 'no ProductName'}): {wrong}")
        return SlaveInfo(pos, name, SlaveIdentity(*ident))

    def _reader(self, node: _Node) -> sdo_mod.SdoRead:
        def read(index: int, sub: int) -> bytes:
            self.startup_steps.check()  # during start-up: a stop signal or a deadline between transfers
            return sdo_mod.read(node.remote.sdo, node.cfg.node_id, index, sub)
        return read

    def _writer(self, node: _Node) -> sdo_mod.SdoWrite:
        def write(index: int, sub: int, data: bytes) -> None:
            self.startup_steps.check()
            sdo_mod.write(node.remote.sdo, node.cfg.node_id, index, sub, data)
        return write

    def _configure(self, node: _Node) -> None:
        """Heartbeat time, PDO policy, start-up SDOs; codec and TPDO subscriptions (pre-operational)."""
        nid = node.cfg.node_id
        write = self._writer(node)
        sdo_mod.write_uint(write, 0x1017, 0, self.heartbeat_ms, 16)
        if self.sync_counter:
            sdo_mod.write_uint(write, 0x1019, 0, self.sync_counter, 8)
        try:
            mapping = pdo_mod.mapping_for(node.cfg.pdo, nid, self._reader(node), write, node.cfg.mapping)
            frames = pdo_mod.PdoFrames(mapping, node.objects)
        except MappingError as e:
            raise BusError(f"CAN {self.channel}: {e}") from None
        except sdo_mod.SDO_FAILURES as e:  # the node refused the mapping (an object it cannot map, ...) or did not answer
            raise BusError(f"CAN {self.channel}: PDO policy {node.cfg.pdo!r}: {e}") from None
        if node.frames is not None and node.frames.mapping != mapping:
            raise BusError(f"CAN {self.channel}: node {nid}: its PDO mapping is not the one of start-up "
                           f"({describe(mapping)}, was {describe(node.frames.mapping)}): not brought back")
        for index, sub, data in node.cfg.startup_sdos:
            write(index, sub, data)
        if node.frames is not None:
            for cob in node.frames.tpdo_cob_ids:
                self._network.unsubscribe(cob, self._on_tpdo)
                self._tpdo_owner.pop(cob, None)
        node.frames = frames
        for cob in frames.tpdo_cob_ids:
            self._tpdo_owner[cob] = node
            self._network.subscribe(cob, self._on_tpdo)
        self.heartbeats.configured(nid)
        log.info("CAN %s node %d: configured, PDO policy %s: %s", self.channel, nid, node.cfg.pdo, describe(mapping))

    def start(self, mapping_override: Mapping[int, object] | None = None) -> int:
        """Configure every node and start it (NMT start); wait until every heartbeat says
        operational. Returns the expected working counter (one per node). Raises BusError."""
        if mapping_override:
            raise BusError(f"CAN {self.channel}: PDO mappings are configured per node ([[can.nodes]] pdo = "
                           "default|drive|explicit), not through [[drives]] mapping or sdo")
        if not self._opened:
            raise BusError(f"CAN {self.channel}: start() before open()")
        with self._lock:
            for node in self._nodes:
                with self.startup_steps.step(f"CAN {self.channel}: node {node.cfg.node_id}: heartbeat, PDO "
                                             "policy and start-up SDOs", CONFIGURE_NODE_S):
                    self._configure(node)
            for node in self._nodes:
                self.send_nmt(NmtCommand.START, node.cfg.node_id)
        with self.startup_steps.step(f"CAN {self.channel}: nodes to operational", START_TIMEOUT_S + 1.0):
            self._wait_operational()
        log.info("CAN %s: %d node(s) operational", self.channel, len(self._nodes))
        return self.expected_wkc

    def _wait_operational(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            self.startup_steps.check()
            now = time.monotonic()
            waiting = [n.cfg.node_id for n in self._nodes
                       if self.heartbeats.state(n.cfg.node_id, now) is not NmtState.OPERATIONAL]
            if not waiting:
                break
            if now >= deadline:
                raise BusError(f"CAN {self.channel}: node(s) {waiting} not operational within {START_TIMEOUT_S:g} s "
                               "(no heartbeat saying so)")
            time.sleep(0.01)

    @property
    def expected_wkc(self) -> int:
        return len(self._nodes)

    # ---- cycle -----------------------------------------------------------------------------------

    def exchange(self) -> int:
        """TPDOs of the previous SYNC in; RPDOs and one SYNC (carrying the next counter value
        1..``sync_counter`` when set) out. Returns the number of nodes whose every TPDO arrived.
        Cycle-safe."""
        wkc = 0
        changed = self._changed = []
        for position, node in enumerate(self._nodes):
            frames = node.frames
            if frames is None:
                continue
            complete, fresh = True, False
            for cob in frames.tpdo_cob_ids:
                seq = node.tpdo_seq.get(cob, 0)
                if seq != node.tpdo_seen.get(cob, 0):
                    node.tpdo_seen[cob] = seq
                    fresh = frames.store_tpdo(cob, node.tpdo_data[cob]) or fresh
                else:
                    complete = False
                    node.missed_tpdos += 1
            if fresh:
                frames.decode_into(node.inputs)
                changed.append(position)
            wkc += complete
        send = self._network.send_message
        for node in self._nodes:
            if node.frames is not None:
                for cob, data in node.frames.rpdo_frames(node.outputs):
                    send(cob, data)
                    self.frames_sent += 1
        self._sync_index = (self._sync_index + 1) % len(self._sync_data)
        send(SYNC_COB_ID, self._sync_data[self._sync_index])
        self.frames_sent += 1
        self.exchanges += 1
        return wkc

    def inputs(self, position: int) -> DriveInputs:
        return self._nodes[position].inputs

    def inputs_changed(self) -> list[int]:
        """Positions of the nodes whose TPDO data changed at the last :meth:`exchange` (the
        others' inputs are as before: a missing TPDO changes nothing). Optional hook of the Bus
        protocol, as on EtherCAT: the cycle skips drives at rest. Cycle-safe."""
        return self._changed

    def codec(self, position: int) -> DriveCodec:
        """The process-data codec of the node at ``position`` (after start()): which objects
        its PDOs carry, as for an EtherCAT slave (the cycle serves the others by SDO)."""
        frames = self._node(position).frames
        if frames is None:
            raise BusError(f"CAN {self.channel}: node at position {position} has no PDO mapping before start()")
        return frames.codec

    def set_outputs(self, position: int, outputs: DriveOutputs) -> None:
        self._nodes[position].outputs = outputs

    @property
    def missed_tpdos(self) -> int:
        return sum(n.missed_tpdos for n in self._nodes)

    # ---- management ------------------------------------------------------------------------------

    def send_nmt(self, command: NmtCommand, node_id: int) -> None:
        """One NMT frame on 0x000 (``node_id`` 0: every node)."""
        self._network.send_message(NMT_COB_ID, nmt_frame(command, node_id))
        log.info("CAN %s: NMT 0x%02X (%s) to %s", self.channel, command, command.name.lower(),
                 "all nodes" if node_id == BROADCAST else f"node {node_id}")

    def read_al_status(self) -> list[SlaveALStatus]:
        """Every node's NMT state from its heartbeats, as an AL state (no bus traffic)."""
        now = time.monotonic()
        return [SlaveALStatus(AL_OF_NMT[self.heartbeats.state(n.cfg.node_id, now)], False, 0) for n in self._nodes]

    def request_al_state(self, position: int | None, state: ALState) -> None:
        """The NMT command for ``state`` (:data:`NMT_FOR_AL`) to one node or, broadcast, to all.
        A node that booted since it was configured is configured again first (but for a reset)."""
        command = NMT_FOR_AL.get(ALState(state))
        if command is None:
            raise BusError(f"CAN {self.channel}: no NMT command reaches AL state {ALState(state).wire_name}")
        targets = list(range(len(self._nodes))) if position is None else [position]
        with self._lock:
            if command not in (NmtCommand.RESET_COMMUNICATION, NmtCommand.RESET_NODE):
                for pos in targets:
                    node = self._node(pos)
                    if self.heartbeats.booted(node.cfg.node_id):
                        self._configure(node)
            if position is None:
                self.send_nmt(command, BROADCAST)
            else:
                self.send_nmt(command, self._node(position).cfg.node_id)

    def request_nmt(self, position: int | None, command: str) -> None:
        """The agent's NMT command (cia402.md §5) as the CANopen one: ``reset_node`` is NMT reset
        node (0x81), the rest as :meth:`request_al_state` (reset_comm: reset communication)."""
        if command == "reset_node":
            with self._lock:
                self.send_nmt(NmtCommand.RESET_NODE,
                              BROADCAST if position is None else self._node(position).cfg.node_id)
            return
        state = {"start": ALState.OP, "stop": ALState.SAFEOP, "preop": ALState.PREOP,
                 "reset_comm": ALState.INIT}.get(command)
        if state is None:
            raise BusError(f"CAN {self.channel}: unknown NMT command {command!r}")
        self.request_al_state(position, state)

    def recover(self, position: int) -> bool:
        """One step: a silent node -> nothing; a node that booted -> configure it again; not
        operational -> NMT start. True once its heartbeat says operational. Its drive stays
        as the cycle leaves it (goal disabled): nothing here enables."""
        node = self._node(position)
        nid = node.cfg.node_id
        now = time.monotonic()
        state = self.heartbeats.state(nid, now)
        if state is NmtState.OPERATIONAL:
            return True
        if not self.heartbeats.heard(nid, now) and not self.heartbeats.booted(nid):
            return False  # silent; a node that booted may stay so (0x1017 defaults to 0): configure it
        with self._lock:
            if self.heartbeats.booted(nid):
                try:
                    self._configure(node)
                except BusError as e:
                    log.warning("CAN %s node %d: reconfiguration after boot-up failed: %s", self.channel, nid, e)
                    return False
            self.send_nmt(NmtCommand.START, nid)
        return False

    def sdo_read(self, position: int, index: int, subindex: int, size: int) -> bytes:
        node = self._node(position)
        data = sdo_mod.read(node.remote.sdo, node.cfg.node_id, index, subindex)
        if size and len(data) > size:
            raise BusError(f"node {node.cfg.node_id}: SDO 0x{index:04X}:{subindex} is {len(data)} bytes, "
                           f"buffer is {size}")
        return data

    def sdo_write(self, position: int, index: int, subindex: int, data: bytes) -> None:
        node = self._node(position)
        sdo_mod.write(node.remote.sdo, node.cfg.node_id, index, subindex, data)

    def take_emergencies(self) -> list[tuple[int, int, int, str]]:
        """EMCY frames since the last call as (position, error code, register, text). Cycle-safe."""
        return self._emcy.take()

    def last_emergency(self, position: int) -> emcy_mod.Emergency | None:
        return self._node(position).last_emcy

    def close(self) -> None:
        """Every node to pre-operational (PDOs stop), then release the bus. Idempotent."""
        if self._network is None:
            return
        try:
            self.send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, BROADCAST)
        except Exception as e:
            log.warning("CAN %s: NMT pre-operational at close failed: %s", self.channel, e)
        self._disconnect()

    def _disconnect(self) -> None:
        net, self._network = self._network, None
        self._opened = False
        if net is not None:
            try:
                net.disconnect()
            except Exception as e:
                log.warning("CAN %s: disconnect: %s", self.channel, e)


def canopen_bus(cfg: CanConfig) -> CanopenBus:
    """The backend of a ``[can]`` configuration (an explicit mapping gets the pre-defined COB-IDs)."""
    nodes = []
    for n in cfg.nodes:
        device = None
        if n.eds:
            try:
                device = load_eds(n.eds, n.node_id)
            except EdsError as e:
                raise BusError(f"CAN {cfg.channel}: node {n.node_id}: {e}") from None
        mapping = pdo_mod.pdos_mapping(n.node_id, n.rpdo, n.tpdo) if n.pdo == "explicit" else None
        if n.pdo == "eds" and device is not None:
            mapping = pdo_mod.eds_mapping(device)
        sdos = tuple((index, sub, value.to_bytes(size, "little", signed=value < 0))
                     for index, sub, value, size in n.startup_sdos)
        nodes.append(NodeConfig(n.node_id, pdo=n.pdo, mapping=mapping, startup_sdos=sdos, eds=n.eds, device=device))
    return CanopenBus(cfg.channel, nodes, interface=cfg.interface, heartbeat_ms=cfg.heartbeat_ms,
                      sync_counter=cfg.sync_counter)
