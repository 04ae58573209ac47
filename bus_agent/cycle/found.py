"""When a returned slave counts as found: valid process data, proven by the working counter.

A slave that the management thread brought back to OP is not found yet: its AL state can read
OP while its process data does not arrive (a datagram lost on its way, a slave that answers the
AL registers but not the process image). Its drives stay lost, with their state ``unknown``,
until the working counter has proven the slave's process data for :data:`FOUND_CONFIRM_CYCLES`
cycles in a row. Pure: the cycle calls :meth:`FoundConfirmation.step` once per cycle with what
it needs.

The working counter is one sum for the whole segment, so it proves a single slave only when
the others' shares are known: a slave in OP counts ``WKC_PER_SLAVE_OP`` (3 for a drive: read
+1, write +2, ETG.1000.4), a slave below SAFE-OP counts nothing. The counter is taken as proof
when it equals the expected count less the full share of every slave still lost, and every such
slave last read below SAFE-OP (so it cannot have made up for a returned slave's missing share).
While a lost slave sits in SAFE-OP, or reads OP, nothing is found: a slave stays lost rather
than be found on data that may be stale.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

from bus_agent.bus.base import ALState, SlaveALStatus

#: Cycles in a row with a working counter that proves the returned slave's process data.
FOUND_CONFIRM_CYCLES = 10
#: A drive slave's share of the working counter in OP (LRW: +1 read, +2 write).
WKC_PER_SLAVE_OP = 3
#: AL states in which a slave adds nothing to the working counter of the process data.
SILENT_AL_STATES = frozenset((ALState.NONE, ALState.INIT, ALState.PREOP, ALState.BOOT))


@dataclass
class FoundConfirmation:
    """The returned slaves waiting for proof of their process data, by slave position."""

    confirm_cycles: int = FOUND_CONFIRM_CYCLES
    #: slave -> (epoch of its recovery, cycles in a row with a proving working counter)
    _waiting: dict[int, list[int]] = field(default_factory=dict)

    def returned(self, slave: int, epoch: int) -> None:
        """The management thread reports ``slave`` back in OP (recovery ``epoch``)."""
        self._waiting[slave] = [epoch, 0]

    def cancel(self, slave: int) -> None:
        """``slave`` was lost again before it was found."""
        self._waiting.pop(slave, None)

    def waiting(self, slave: int) -> bool:
        return slave in self._waiting

    def __bool__(self) -> bool:
        return bool(self._waiting)

    def step(self, wkc: int, expected_wkc: int, lost_slaves: Iterable[int],
             al_status: Mapping[int, SlaveALStatus] | list[SlaveALStatus]) -> list[int]:
        """One cycle's working counter ``wkc``. ``lost_slaves``: every slave whose drives are
        lost (the waiting ones included); ``al_status``: the last AL status read per slave.
        Returns the slaves found this cycle (each once)."""
        others = [s for s in set(lost_slaves) if s not in self._waiting]
        proven = (wkc == expected_wkc - WKC_PER_SLAVE_OP * len(others)
                  and all(_silent(al_status, s) for s in others))
        found = []
        for slave, rec in list(self._waiting.items()):
            st = al_status[slave]
            if not proven or st.state != ALState.OP or st.error:
                rec[1] = 0
                continue
            rec[1] += 1
            if rec[1] >= self.confirm_cycles:
                del self._waiting[slave]
                found.append(slave)
        return found


def _silent(al_status: Mapping[int, SlaveALStatus] | list[SlaveALStatus], slave: int) -> bool:
    return al_status[slave].state in SILENT_AL_STATES
