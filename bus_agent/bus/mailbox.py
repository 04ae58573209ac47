"""What a slave's mailbox offers (its SII) and what a failed mailbox transfer means (pure).

SII words 0x18-0x1B give the standard mailbox's offsets and sizes, word 0x1C the mailbox
protocols (ETG.1000.6 Table 18); a slave whose mailbox sizes are 0 has no mailbox, so no CoE and
no SDO. A transfer fails in one of two ways: no answer in time (it may be made again: the answer
may have been lost), or a definite answer, made again it gets the same one: an SDO abort, a
mailbox error (ETG.1000.4 Table 30: "mailbox protocol not supported", ...), an unexpected frame.
"""

from __future__ import annotations

from dataclasses import dataclass

#: SII word 0x1C mailbox protocol bits (ETG.1000.6 Table 18).
MAILBOX_PROTOCOLS = ((0x01, "AoE"), (0x02, "EoE"), (0x04, "CoE"), (0x08, "FoE"), (0x10, "SoE"), (0x20, "VoE"))
COE = 0x04
#: SII word addresses of the standard mailbox: receive offset/size, send offset/size, protocols.
SII_MAILBOX_WORD = 0x18
SII_PROTOCOLS_WORD = 0x1C

#: Mailbox error reply codes (ETG.1000.4 Table 30).
MAILBOX_ERRORS = {
    0x01: "mailbox header syntax wrong",
    0x02: "mailbox protocol not supported",
    0x03: "mailbox channel field not zero",
    0x04: "service of the mailbox protocol not supported",
    0x05: "header of the mailbox protocol wrong",
    0x06: "mailbox data too short",
    0x07: "mailbox protocol cannot be handled: not enough memory",
    0x08: "mailbox data of inconsistent length",
}
#: SOEM's packet errors (pysoem PacketError): an answer that is not the one asked for.
PACKET_ERRORS = {1: "an unexpected frame came back", 3: "the answer does not fit the buffer given"}
NO_ANSWER = "no answer from the slave's mailbox"


def mailbox_protocols(word: int) -> tuple[str, ...]:
    return tuple(name for bit, name in MAILBOX_PROTOCOLS if word & bit)


@dataclass(frozen=True)
class SiiMailbox:
    """A slave's standard mailbox as its SII describes it."""

    receive_size: int   # word 0x19: master -> slave
    send_size: int      # word 0x1B: slave -> master
    protocols: int      # word 0x1C

    @property
    def present(self) -> bool:
        return self.receive_size > 0 and self.send_size > 0

    def coe_problem(self) -> str | None:
        """Why no SDO can be exchanged with this slave, or None when its mailbox offers CoE."""
        if not self.present:
            return (f"has no mailbox (its SII gives mailbox sizes {self.receive_size}/{self.send_size} bytes): "
                    "no CoE, so no SDO; not a CiA 402 drive over EtherCAT")
        if not self.protocols & COE:
            return (f"its mailbox does not offer CoE (SII mailbox protocols: "
                    f"{', '.join(mailbox_protocols(self.protocols)) or 'none'}): no SDO")
        return None


def transfer_failure(e: BaseException) -> tuple[str, bool]:
    """(what a failed pysoem mailbox transfer means, whether the answer was lost). Only a
    WkcError (no answer in time; pysoem's text says nothing by itself) is a lost answer."""
    kind = type(e).__name__
    if kind == "WkcError":
        return f"WkcError: {NO_ANSWER}", True
    if kind == "MailboxError":
        code = getattr(e, "error_code", 0)
        return f"mailbox error 0x{code:04X}: {MAILBOX_ERRORS.get(code, getattr(e, 'desc', 'unknown'))}", False
    if kind == "PacketError":
        code = getattr(e, "error_code", 0)
        return f"packet error {code}: {PACKET_ERRORS.get(code, 'unknown')}", False
    return str(e) or kind, False


def transfer_failure_text(e: BaseException) -> str:
    """What a failed pysoem mailbox transfer says (:func:`transfer_failure`)."""
    return transfer_failure(e)[0]
