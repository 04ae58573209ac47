"""COB-IDs of the pre-defined connection set and the PDO communication objects (CiA 301 §7.3.5,
§7.5.2.35-38). Pure data: who sends what on which CAN identifier.

PDO n (1..4) of node id: TPDO 0x180 + 0x100 (n-1) + id, RPDO 0x200 + 0x100 (n-1) + id. The
communication parameter of PDO n is 0x1400 + n-1 (RPDO) / 0x1800 + n-1 (TPDO), sub 1 the COB-ID
(bit 31: not valid), sub 2 the transmission type; the mapping 0x1600 + n-1 / 0x1A00 + n-1.
NMT (0x000) and heartbeat (0x700 + id) are in :mod:`bus_agent.bus.canopen.nmt`.
"""

from __future__ import annotations

SYNC_COB_ID = 0x080
EMCY_COB_BASE = 0x080       # + node id
SDO_TX_BASE, SDO_RX_BASE = 0x580, 0x600   # server -> client, client -> server (+ node id)
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
MAX_PDOS = 4                # the pre-defined connection set has COB-IDs for PDO 1..4
MAX_PDO_BITS = 64           # one classic CAN frame
COB_ID_INVALID = 0x80000000  # bit 31 of sub 1: PDO does not exist / is not valid
COB_ID_MASK = 0x7FF         # 11-bit identifiers
TRANSMISSION_SYNC = 1       # synchronous, every SYNC (TPDO: sampled at the SYNC; RPDO: applied at the next)
#: 0x1019 synchronous counter overflow value: 0 = SYNC without data, 2..240 = SYNC carries a
#: counter 1..value (1 and 241..255 are reserved).
SYNC_COUNTER_RANGE = range(2, 241)


def default_cob_id(tx: bool, pdo: int, node_id: int) -> int:
    """Pre-defined connection set: TPDO n 0x180 + 0x100 (n-1) + id, RPDO n 0x200 + 0x100 (n-1) + id."""
    if not 1 <= pdo <= MAX_PDOS:
        raise ValueError(f"PDO number {pdo} outside 1..{MAX_PDOS}")
    return (0x180 if tx else 0x200) + 0x100 * (pdo - 1) + node_id
