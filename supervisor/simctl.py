"""Fault injection into simulated drives by axis name (test beds, demos, users' integration tests).

Both simulators serve ``drives/@sim/<segment>/<slave>/<action>`` (``bus_agent.sim.control``):
``bus-agent --sim N`` under its host name, ``ecat-sim`` under its ``--name``. This module turns
``host/axis`` selectors into (segment, slave position) through the fleet's status (each
``DriveStatus`` carries its ``slave``; else the agent's axis order) and sends the action.
The resolution (:func:`sim_targets`) is pure given the fleet's view; :func:`inject` does the I/O.

    with Fleet(connect=[ep]) as fleet:
        inject(fleet, "fault", "h1/axis1", error_code=0x2310)
        inject(fleet, "unplug", "h2/x", segment="seg0")     # an ecat-sim named seg0 behind h2
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

from bus_agent.sim.control import SimControlError, sim_inject
from schemas import keys

from .fleet import Fleet
from .selectors import DriveRef, SelectorError

#: Actions both simulators serve, and the arguments each takes.
SIM_ACTIONS: Mapping[str, tuple[str, ...]] = {"fault": ("error_code",), "unplug": (), "plug": (),
                                              "wkc_fault": ("on",)}


@dataclass(frozen=True)
class SimTarget:
    """Where one drive lives in its simulator."""

    drive: DriveRef
    segment: str
    slave: int


def slave_of(fleet: Fleet, ref: DriveRef) -> int:
    """The slave position of ``ref``: its status' ``slave``, else its index in the agent's axes."""
    st = fleet.status(ref)
    if st is not None:
        return st.slave
    info = fleet.agents().get(ref.host)
    axes = list(info.status.axes) if info and info.status else []
    if ref.axis in axes:
        return axes.index(ref.axis)
    raise SelectorError(f"{ref}: slave position unknown (no status, and {ref.host} does not list the axis)")


def sim_targets(fleet: Fleet, selectors: Sequence[str], segment: str | None = None) -> list[SimTarget]:
    """The (segment, slave) of every selected live drive. ``segment``: the simulator's segment
    name when it is not the host name (``ecat-sim --name``); only with drives of one host."""
    refs = [r for r in fleet.select(*selectors).drives if r in set(fleet.roster())]
    if not refs:
        raise SelectorError(f"{' '.join(selectors)}: no live drive selected")
    if segment is not None:
        keys.validate_name(segment, "segment")
        if len({r.host for r in refs}) > 1:
            raise SelectorError("--segment names one simulator: select drives of one host")
    return [SimTarget(r, segment or r.host, slave_of(fleet, r)) for r in refs]


def inject(fleet: Fleet, action: str, *selectors: str, segment: str | None = None, timeout_s: float = 2.0,
           **args: Any) -> list[tuple[SimTarget, str]]:
    """Perform ``action`` (:data:`SIM_ACTIONS`) on every selected drive's simulated slave; return
    each target with the simulator's detail. Raises :class:`SelectorError` (nothing sent) or
    :class:`SimControlError` (a simulator refused or none answered; earlier targets were done)."""
    if action not in SIM_ACTIONS:
        raise ValueError(f"sim action {action!r}: use one of {', '.join(SIM_ACTIONS)}")
    if set(args) != set(SIM_ACTIONS[action]):
        raise ValueError(f"sim {action} takes {', '.join(SIM_ACTIONS[action]) or 'no arguments'}, got {sorted(args)}")
    out = []
    for t in sim_targets(fleet, selectors, segment):
        try:
            details = sim_inject(fleet.session, t.segment, t.slave, action, timeout_s=timeout_s, **args)
        except SimControlError as exc:
            hint = "" if segment else " (an ecat-sim segment is named by its --name: give segment=/--segment)"
            raise SimControlError(f"{t.drive} (segment {t.segment}, slave {t.slave}): {exc}{hint}") from None
        out.append((t, "; ".join(details)))
    return out


__all__ = ["SIM_ACTIONS", "SimTarget", "SimControlError", "inject", "sim_targets", "slave_of"]
