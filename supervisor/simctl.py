"""Fault injection addressed by drive name: ``host/axis`` -> simulator segment and slave position.

Simulators take requests on ``drives/@sim/<segment>/<slave>/<action>`` (``bus_agent.sim.control``)
by slave *position*; people and tests name drives. :func:`sim_target` resolves a name through
what the drive's own agent published (``DriveStatus.slave``), so the position is the agent's, not
a guess. The segment is the host name: ``bus-agent --sim`` serves its host's name, and a test bed
that runs ``ecat-sim`` for a host names the segment after the host (``ecat-sim --name <host>``).

Actions: ``fault {error_code}``, ``unplug``, ``plug``, ``wkc_fault {on}`` on both simulators;
``drop_frames``, ``delay_frames`` on ``ecat-sim`` only (see docs/simulator.md and
docs/virtual-ethercat.md).
"""

from __future__ import annotations

from typing import Any, Mapping

import zenoh

from bus_agent.sim.control import DEFAULT_TIMEOUT_S, sim_inject
from schemas.messages import DriveStatus

from .selectors import DriveRef, SelectorError


def sim_target(statuses: Mapping[DriveRef, DriveStatus], ref: DriveRef | str) -> tuple[str, int]:
    """``(segment, slave)`` of drive ``ref`` from the last known status of every drive (pure).

    Raises :class:`SelectorError` when ``ref`` is malformed or no status of it is known."""
    r = ref if isinstance(ref, DriveRef) else DriveRef.parse(ref)
    st = statuses.get(r)
    if st is None:
        known = sorted(str(d) for d in statuses if d.host == r.host)
        hint = f"known on {r.host}: {', '.join(known)}" if known else f"no drive of host {r.host} is known"
        raise SelectorError(f"drive {r}: no status seen, so its slave position is unknown ({hint})")
    return r.host, st.slave


def inject(session: zenoh.Session, statuses: Mapping[DriveRef, DriveStatus], ref: DriveRef | str, action: str,
           *, timeout_s: float = DEFAULT_TIMEOUT_S, **args: Any) -> str:
    """Ask the simulator of drive ``ref`` to perform ``action``; returns its reply's detail.

    Raises :class:`SelectorError` (unknown drive, nothing sent) or
    ``bus_agent.sim.control.SimControlError`` (refused, or no simulator answered)."""
    segment, slave = sim_target(statuses, ref)
    return "; ".join(sim_inject(session, segment, slave, action, timeout_s=timeout_s, **args))
