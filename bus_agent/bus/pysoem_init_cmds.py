"""The SAFE-OP -> OP part of the slaves' start-up SDOs over pysoem (the ESI's ``SO`` InitCmds).

Called by :mod:`bus_agent.bus.pysoem_startup` in SAFE-OP, just before OP is requested; the
PRE-OP ones (``IP``, ``PS``) travel with the other start-up SDOs (:class:`SlaveSetup.sdos`).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, Sequence

from bus_agent.bus.mapping import SlaveSetup

log = logging.getLogger(__name__)


def apply_safeop_sdos(slaves: Sequence[Any], setups: Mapping[int, SlaveSetup],
                      sdo: Callable[[int, Callable[[], Any], str], Any], exchange: Callable[[], Any]) -> None:
    """Each slave's ``safeop_sdos`` in order, process data exchanged between them (outputs must
    keep flowing in SAFE-OP: SM watchdog). ``sdo(position, transfer, what)`` raises BusError
    naming what."""
    for pos, setup in sorted(setups.items()):
        s = slaves[pos]
        for item in setup.safeop_sdos:
            sdo(pos, lambda: s.sdo_write(item.index, item.subindex, item.data, release_gil=True),
                f"slave {pos} ({s.name!r}): SAFE-OP start-up SDO {item}")
            exchange()
        if setup.safeop_sdos:
            log.info("slave %d (%r): %d SAFE-OP start-up SDO(s) applied", pos, s.name, len(setup.safeop_sdos))
