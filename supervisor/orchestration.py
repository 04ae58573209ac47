"""Coordination across drives and hosts: two-phase enable, ordered shutdown.

CiA 402 transitions (cia402.md): 2 shutdown (-> Ready to switch on), 3 switch on (-> Switched
on), 4 enable operation (-> Operation enabled), 5 disable operation, 6 shutdown, 7/9/10/12
disable voltage (-> Switch on disabled), 11 quick stop, 15 fault reset.

Two-phase enable: every selected drive first goes to Switched on (transitions 2, 3), where it
has power but produces no torque; only if all of them got there does any drive get Enable
operation (transition 4). If one fails, the drives that moved are returned (shutdown or
disable voltage, to where they were) and the report says which drive failed and why.
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence

from schemas.error_codes import describe

from .results import MISSING, CommandResult, DriveResult, Report, final_results
from .selectors import DriveRef, SelectorError


class Selection(Protocol):
    """What orchestration needs of a selection (``supervisor.selectors.Selection``)."""

    @property
    def drives(self) -> Sequence[DriveRef]: ...


class Fleet(Protocol):
    """What orchestration needs of a fleet (``supervisor.fleet.Fleet``); a protocol, so this module
    does not import the fleet and the fleet can import it (no import circle)."""

    def select(self, *selectors: str, allow_empty: bool = False) -> Any: ...
    def selection_of(self, refs: Iterable[DriveRef], *, per_host: bool = False) -> Any: ...
    def roster(self) -> list[DriveRef]: ...
    def conflicts(self) -> Mapping[str, str]: ...
    def hosts(self) -> list[str]: ...
    def drives(self) -> Mapping[DriveRef, Any]: ...
    def fetch_status(self, target: Any, timeout_s: float = 2.0) -> Mapping[DriveRef, Any]: ...
    def command(self, op: str, target: Any = "**", args: Mapping[str, Any] | None = None,
                timeout_s: float = 5.0) -> CommandResult: ...
    def send(self, op: str, sel: Any, args: Mapping[str, Any] | None = None,
             timeout_s: float = 5.0) -> CommandResult: ...

log = logging.getLogger(__name__)

#: States a drive must not be in for enable to start (nothing is sent if one is).
_BLOCKING_STATES = ("fault", "fault_reaction_active")
#: States from which switch_on would take an enabled drive *down* (transition 5): skip phase 1.
_ALREADY_UP = ("operation_enabled",)


def _describe(results: Sequence) -> str:
    parts = []
    for r in results:
        bits = [r.outcome]
        if r.state and r.state != "unknown":
            bits.append(f"in {r.state}")
        if r.error_code:
            bits.append(f"error 0x{r.error_code:04X} {describe(r.error_code)}")
        if r.error:
            bits.append(r.error)
        if r.lease_holder and r.outcome == "busy":
            bits.append(f"leased by {r.lease_holder}")
        parts.append(f"{r.name}: {', '.join(bits)}")
    return "; ".join(parts)


def _stage_selections(fleet: "Fleet", stages: Sequence[Sequence[str] | str]) -> list["Selection"]:
    """One selection per stage; a drive belongs to the first stage that names it."""
    seen: set[DriveRef] = set()
    out = []
    for stage in stages:
        sel = fleet.select(*([stage] if isinstance(stage, str) else list(stage)))
        own = [d for d in sel.drives if d not in seen]
        seen.update(own)
        out.append(sel if len(own) == len(sel.drives) else fleet.selection_of(own))
    return out


def enable_blockers(selected: Sequence[DriveRef], roster: Iterable[DriveRef],
                    statuses: Mapping[DriveRef, Any], conflicts: Mapping[str, str] | None = None) -> list[DriveResult]:
    """The selected drives that stop an enable before anything is sent, each as a result:
    ``missing`` (not present: agent gone or unknown drive) or ``rejected`` (in Fault, in Fault
    reaction active, or lost: faults are never reset implicitly; or its host name is used by two
    agents)."""
    present = set(roster)
    conflicts = conflicts or {}
    out = []
    for ref in selected:
        st = statuses.get(ref)
        if ref.host in conflicts:
            out.append(DriveResult(ref.host, ref.axis, "rejected", error=f"not enabling: {conflicts[ref.host]}"))
        elif ref not in present:
            out.append(DriveResult(ref.host, ref.axis, MISSING, error="not present (agent gone or unknown drive)"))
        elif st is not None and (st.state in _BLOCKING_STATES or st.lost):
            why = "slave lost" if st.lost else f"in {st.state}: fault_reset first (never implicit)"
            out.append(DriveResult(ref.host, ref.axis, "rejected", st.state, st.error_code,
                                   f"not enabling: {why}"))
    return out


def two_phase_enable(fleet: "Fleet", selectors: Sequence[str], *, timeout_s: float = 5.0,
                     stages: Sequence[Sequence[str] | str] | None = None,
                     before_phase: Callable[[str], None] | None = None) -> Report:
    """Enable the selected drives all together or not at all.

    Phase 1 sends ``switch_on`` (transitions 2+3) to every selected drive not already in
    Operation enabled. If any does not reach Switched on, the drives that did are returned to
    their previous state (``shutdown`` to Ready to switch on, else ``disable`` to Switch on
    disabled) and the report names the failures. Phase 2 sends ``enable`` (transition 4), in
    ``stages`` order when given (each stage a list of selectors), else as one fan-out query.

    A selected drive known to be in Fault, lost, or whose agent is gone stops the operation
    before anything is sent: faults are never reset implicitly. ``before_phase(name)`` is called
    just before each phase's query goes out (``switch_on``, ``enable``): for logging and tests.
    """
    if stages:
        stage_sels = _stage_selections(fleet, stages)
        everything = fleet.selection_of([d for s in stage_sels for d in s.drives])
    else:
        everything = fleet.select(*selectors)
        stage_sels = [everything]
    roster = set(fleet.roster())
    # The agents' current answer, not the snapshot alone: a published status may lag (or have
    # been dropped), and skipping phase 1 for a drive wrongly believed enabled would enable it
    # straight from Switch on disabled.
    statuses = {**fleet.drives(), **fleet.fetch_status(everything)}
    blockers = enable_blockers(everything.drives, roster, statuses, fleet.conflicts())
    if blockers:
        reason = "not enabling, nothing sent: " + _describe(blockers)
        log.warning("enable: %s", reason)
        # The blocking drives are the failures: a caller looping over report.failures sees them.
        return Report("enable", False, (), reason, tuple(blockers))

    before = {ref: (statuses[ref].state if ref in statuses else "unknown") for ref in everything.drives}
    # A drive whose state is unknown gets phase 1 too: switch_on never enables.
    to_switch_on = [r for r in everything.drives if before[r] not in _ALREADY_UP]
    steps: list[tuple[str, CommandResult]] = []
    if to_switch_on:
        sel1 = everything if len(to_switch_on) == len(everything.drives) else fleet.selection_of(to_switch_on)
        if before_phase is not None:
            before_phase("switch_on")
        phase1 = fleet.command("switch_on", sel1, timeout_s=timeout_s)
        steps.append(("switch_on", phase1))
        if not phase1.ok:
            reason = "switch_on failed: " + _describe(phase1.failures)
            # Return every drive that may have moved (done, or timed out half-way) to where it was.
            moved = [r for r in phase1.results
                     if r.outcome in ("done", "timeout") or (r.outcome == "missing" and r.host in fleet.hosts())]
            back_shutdown = [DriveRef(r.host, r.axis) for r in moved
                             if before.get(DriveRef(r.host, r.axis)) == "ready_to_switch_on"]
            back_disable = [DriveRef(r.host, r.axis) for r in moved
                            if before.get(DriveRef(r.host, r.axis)) != "ready_to_switch_on"]
            for op, refs in (("shutdown", back_shutdown), ("disable", back_disable)):
                if refs:
                    rb = fleet.command(op, fleet.selection_of(refs), timeout_s=timeout_s)
                    steps.append((f"rollback:{op}", rb))
                    if not rb.ok:
                        reason += f"; rollback {op} incomplete: " + _describe(rb.failures)
            log.warning("enable: %s", reason)
            # The final per-drive view: phase-1 failures stay visible next to the rollbacks.
            last = {DriveRef(r.host, r.axis): r for r in final_results(steps)}
            for r in phase1.failures:
                last[DriveRef(r.host, r.axis)] = r
            return Report("enable", False, tuple(steps), reason, tuple(last[k] for k in sorted(last)))

    failures = []
    if before_phase is not None:
        before_phase("enable")
    for i, sel in enumerate(stage_sels):
        res = fleet.command("enable", sel, timeout_s=timeout_s)
        steps.append(("enable" if len(stage_sels) == 1 else f"enable:stage{i + 1}", res))
        failures.extend(res.failures)
        if not res.ok:
            break  # later stages depend on earlier ones: do not enable them
    final = final_results(steps)
    if failures:
        reason = "enable failed: " + _describe(failures)
        skipped = [d for d in everything.drives if d not in {DriveRef(r.host, r.axis) for r in final}]
        if skipped:
            reason += f"; not enabled (later stages, left in Switched on): {', '.join(map(str, skipped))}"
        return Report("enable", False, tuple(steps), reason, final)
    return Report("enable", True, tuple(steps), "", final)


def ordered_shutdown(fleet: "Fleet", stages: Sequence[Sequence[str] | str], *, op: str = "disable",
                     timeout_s: float = 5.0) -> Report:
    """Take drives down stage by stage, **last stage first** (``stages`` are in enable order).

    ``op`` is ``disable`` (disable operation, shutdown, disable voltage: transitions 5, 6, 7/9)
    or ``shutdown`` / ``quick_stop``. Every stage is attempted even if an earlier one failed
    (leaving drives powered because one refused would be worse); failures are reported.
    """
    if op not in ("disable", "shutdown", "quick_stop"):
        raise SelectorError(f"shutdown op {op!r}: use disable, shutdown or quick_stop")
    sels = _stage_selections(fleet, stages)
    steps: list[tuple[str, CommandResult]] = []
    for i in reversed(range(len(sels))):
        res = fleet.command(op, sels[i], timeout_s=timeout_s)
        steps.append((f"{op}:stage{i + 1}", res))
    final = final_results(steps)
    failures = [r for r in final if not r.ok]
    reason = f"{op} failed: " + _describe(failures) if failures else ""
    return Report(op, not failures, tuple(steps), reason, final)
