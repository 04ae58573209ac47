"""An example cell script on the supervisor API: enable a group, run a sequence, react to a fault.

    python examples/cell/cell.py --connect tcp/127.0.0.1:7447     # e.g. against `drives-twin --fleet fleet.toml`

The cell (``fleet.toml``: a press with ``clamp`` and ``ram``, a conveyor ``belt``, group ``line``)
runs :data:`SEQUENCE` step by step, and ends with the ordered shutdown
(belt, ram, clamp). When a drive of the line faults or its agent disappears, the agents' group
reflex has already quick-stopped the other members; the cell stops its sequence, disables the
whole line and reports the drive and its 0x603F code. It resets a fault only when the code is in
:data:`RESETTABLE` and only once per run; anything else waits for a person (never reset blindly).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from dataclasses import dataclass, field
from typing import Callable, Sequence

from schemas.messages import DriveStatus
from supervisor.fleet import Fleet

GROUP = "line"
#: (step name, op, selectors): each must succeed on every addressed drive before the next.
SEQUENCE: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("clamp", "enable", ("press/clamp",)),
    ("press", "enable", ("press/ram",)),
    ("feed", "enable", ("conv/belt",)),
    ("pause-feed", "halt", ("conv/belt",)),
    ("resume-feed", "resume", ("conv/belt",)),
)
SHUTDOWN_STAGES = (("press/clamp",), ("press/ram",), ("conv/belt",))  # last stage first
#: Faults a cell may reset on its own, once per run (a transient following error, here).
RESETTABLE = frozenset({0x8611})
BAD_STATES = frozenset({"fault", "fault_reaction_active"})


@dataclass
class CellResult:
    """``state``: done (sequence and shutdown completed), faulted (a drive faulted or vanished:
    the line was disabled) or failed (a step did not reach its goal)."""

    state: str
    steps_done: list[str] = field(default_factory=list)
    fault: str = ""           # "press/ram 0x2310" or "conv lost"
    detail: str = ""


class Cell:
    """The cell on a connected :class:`Fleet`. ``between_steps(step)`` runs after each step (tests
    use it to make something happen at a known point of the sequence)."""

    def __init__(self, fleet: Fleet, between_steps: Callable[[str], None] | None = None) -> None:
        self.fleet = fleet
        self.between_steps = between_steps
        self._trouble = threading.Event()
        self._fault = ""
        members = fleet.groups().get(GROUP, [])
        self.members = set(members)
        fleet.on("status", self._on_status)
        fleet.on("departure", self._on_departure)

    def _on_status(self, st: DriveStatus) -> None:
        if f"{st.host}/{st.axis}" in self.members and (st.state in BAD_STATES or st.lost) and not self._fault:
            self._fault = f"{st.host}/{st.axis} {'lost' if st.lost else f'0x{st.error_code:04X}'}"
            self._trouble.set()

    def _on_departure(self, host: str) -> None:
        if any(m.split("/")[0] == host for m in self.members) and not self._fault:
            self._fault = f"{host} lost"
            self._trouble.set()

    def _troubled(self) -> bool:
        """The events seen so far, and the fleet's current view (an event may still be queued)."""
        for m in sorted(self.members):
            host = m.split("/")[0]
            st = self.fleet.status(m)
            if host not in self.fleet.hosts():
                self._on_departure(host)
            elif st is not None:
                self._on_status(st)
        return self._trouble.is_set()

    def _step(self, op: str, selectors: Sequence[str]) -> tuple[bool, str]:
        if op == "enable":
            r = self.fleet.enable(*selectors)
            return r.ok, r.reason
        res = self.fleet.halt(*selectors, on=(op == "halt"))
        return res.ok, "; ".join(f"{d.name} {d.outcome} {d.error}" for d in res.failures)

    def run(self) -> CellResult:
        """Run the sequence once; returns how it ended (never raises on a drive's behaviour)."""
        if not self.members:
            return CellResult("failed", detail=f"no group {GROUP!r} in the fleet")
        result = CellResult("done")
        for name, op, selectors in SEQUENCE:
            if self._troubled():
                break
            ok, why = self._step(op, selectors)
            # a step that failed because a drive faulted or vanished is that fault, not a failure
            if not ok and not self._trouble.wait(1.0):
                self.fleet.disable(*sorted(self.members))
                return CellResult("failed", result.steps_done, detail=f"step {name}: {why}")
            if ok:
                result.steps_done.append(name)
            if self.between_steps is not None:
                self.between_steps(name)
        if self._trouble.wait(0.2) or self._troubled():  # a fault during the last step counts too
            return self._react(result)
        report = self.fleet.shutdown(stages=[list(s) for s in SHUTDOWN_STAGES])
        if not report.ok:
            return CellResult("failed", result.steps_done, detail=f"shutdown: {report.reason}")
        return result

    def _react(self, result: CellResult) -> CellResult:
        """The line after a fault: everything disabled; a resettable fault reset once."""
        live = [m for m in sorted(self.members) if m.split("/")[0] in self.fleet.hosts()]
        if live:
            self.fleet.disable(*live)
        ref, _, code = self._fault.partition(" ")
        detail = "waiting for an operator"
        if code.startswith("0x") and int(code, 16) in RESETTABLE:
            detail = "reset once: " + ("ok" if self.fleet.fault_reset(ref).ok else "refused")
        return CellResult("faulted", result.steps_done, fault=self._fault, detail=detail)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="cell.py", description="run the example cell once")
    p.add_argument("--connect", action="append", default=[], metavar="EP")
    args = p.parse_args(argv)
    with Fleet(connect=args.connect or ["tcp/127.0.0.1:7447"], name="cell") as fleet:
        fleet.wait_for_agents(["press", "conv"], timeout_s=10, drives=3)
        result = Cell(fleet).run()
    print(json.dumps(result.__dict__))
    return 0 if result.state == "done" else 1


if __name__ == "__main__":
    sys.exit(main())
