"""The events of the running cycle: what every part of the cycle reports into one list.

One :class:`EventLog` per :class:`bus_agent.cycle.cycle.Cycle`, given to each part that reports;
the cycle starts a new list per cycle (and per express reflex) and publishes it in the snapshot.
Cycle thread only.
"""

from __future__ import annotations

from bus_agent.runtime import CycleEvent


class EventLog:
    """The :class:`CycleEvent` list of the running cycle."""

    __slots__ = ("items",)

    def __init__(self) -> None:
        self.items: list[CycleEvent] = []

    def begin(self) -> list[CycleEvent]:
        """A new, empty list for the cycle (or express reflex) that starts; returned."""
        items = self.items = []
        return items

    def append(self, event: CycleEvent) -> None:
        self.items.append(event)

    def event(self, axis: str, kind: str, detail: str = "", *, from_state: str = "unknown",
              to_state: str = "unknown", error_code: int = 0, request_id: str = "") -> None:
        """Report one event of ``axis`` ('' for the agent) in this cycle."""
        self.items.append(CycleEvent(axis=axis, kind=kind, detail=detail, from_state=from_state,
                                     to_state=to_state, error_code=error_code, request_id=request_id))
