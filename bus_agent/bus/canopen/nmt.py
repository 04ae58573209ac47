"""NMT: network management commands and states (CiA 301 §7.2.8.3; seed 001).

An NMT command is one CAN frame on COB-ID 0x000, two bytes: the command specifier and the node
id (0 = every node). The node states and the transitions a command causes are a table
(:data:`TRANSITIONS`), used by the simulator's NMT slave; the master side sends the frames
(:func:`nmt_frame`). The bus interface speaks EtherCAT AL states, so :data:`AL_OF_NMT` and
:data:`NMT_FOR_AL` say how one maps onto the other (docs/canopen.md). Pure.
"""

from __future__ import annotations

from enum import IntEnum

from bus_agent.bus.base import ALState

NMT_COB_ID = 0x000
HEARTBEAT_COB_BASE = 0x700  # + node id; also the boot-up message (one byte 0x00)
BROADCAST = 0


class NmtCommand(IntEnum):
    """NMT command specifiers (byte 0 of the 0x000 frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as a heartbeat reports them (byte 0, toggle bit 7 masked). ``UNKNOWN``: a
    value no state has (decoded, not raised)."""

    INITIALISING = 0x00  # the boot-up message
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F
    UNKNOWN = 0xFF

    @property
    def wire_name(self) -> str:
        return self.name.lower().replace("_", "-")


#: (state, command) -> next state, CiA 301 Figure 48 (seed 001). A reset passes through
#: initialisation (boot-up message) to pre-operational by itself: see :func:`after_command`.
TRANSITIONS: dict[tuple[NmtState, NmtCommand], NmtState] = {
    **{(s, NmtCommand.START): NmtState.OPERATIONAL
       for s in (NmtState.PRE_OPERATIONAL, NmtState.STOPPED, NmtState.OPERATIONAL)},
    **{(s, NmtCommand.STOP): NmtState.STOPPED
       for s in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL, NmtState.STOPPED)},
    **{(s, NmtCommand.ENTER_PRE_OPERATIONAL): NmtState.PRE_OPERATIONAL
       for s in (NmtState.OPERATIONAL, NmtState.STOPPED, NmtState.PRE_OPERATIONAL)},
    **{(s, c): NmtState.INITIALISING
       for s in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL, NmtState.STOPPED)
       for c in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION)},
}


def after_command(state: NmtState, command: NmtCommand) -> NmtState:
    """The state a node is in after ``command`` (unchanged when the table has no entry)."""
    return TRANSITIONS.get((state, command), state)


def decode_command(data: bytes | bytearray) -> tuple[NmtCommand | None, int]:
    """(command or None when unknown, node id) of an NMT frame; ValueError when not 2 bytes."""
    if len(data) != 2:
        raise ValueError(f"NMT frame must be 2 bytes, got {len(data)}")
    try:
        return NmtCommand(data[0]), data[1]
    except ValueError:
        return None, data[1]


def nmt_frame(command: NmtCommand, node_id: int) -> bytes:
    """The two data bytes of an NMT command to ``node_id`` (0 = all)."""
    if not 0 <= node_id <= 127:
        raise ValueError(f"node id {node_id} outside 0..127")
    return bytes((int(command), node_id))


def decode_heartbeat(data: bytes | bytearray) -> NmtState:
    """The state in a heartbeat (or boot-up) frame; UNKNOWN for anything else."""
    if len(data) < 1:
        return NmtState.UNKNOWN
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        return NmtState.UNKNOWN


#: What the cycle reads: a node's NMT state as the bus interface's AL state. Stopped is the
#: state of EtherCAT's SAFE-OP in the cycle's NMT commands (process data no longer applied).
AL_OF_NMT: dict[NmtState, ALState] = {
    NmtState.OPERATIONAL: ALState.OP,
    NmtState.STOPPED: ALState.SAFEOP,
    NmtState.PRE_OPERATIONAL: ALState.PREOP,
    NmtState.INITIALISING: ALState.INIT,
    NmtState.UNKNOWN: ALState.NONE,
}

#: What the cycle asks for (an AL state) as the NMT command sent. INIT = reset communication:
#: the node reboots its communication (boot-up message) and is reported INIT until configured.
NMT_FOR_AL: dict[ALState, NmtCommand] = {
    ALState.OP: NmtCommand.START,
    ALState.SAFEOP: NmtCommand.STOP,
    ALState.PREOP: NmtCommand.ENTER_PRE_OPERATIONAL,
    ALState.INIT: NmtCommand.RESET_COMMUNICATION,
}
