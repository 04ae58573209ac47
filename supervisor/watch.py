"""Tables of the fleet (status and a live view) with rich.

The live view is driven by the status subscription: every received ``DriveStatus`` (and every
agent arrival or departure) sets an event; the loop redraws when it is set, coalescing bursts to
at most :data:`MAX_REDRAW_HZ` redraws per second. Nothing polls the agents.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Iterable, Sequence

from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from schemas.messages import DriveStatus

from .fleet import Fleet
from .results import CommandResult, DriveResult, Report
from .selectors import DriveRef, parse_selector

MAX_REDRAW_HZ = 20.0

_STATE_STYLE = {
    "operation_enabled": "bold green",
    "switched_on": "green",
    "ready_to_switch_on": "cyan",
    "switch_on_disabled": "white",
    "not_ready_to_switch_on": "dim",
    "quick_stop_active": "bold yellow",
    "fault_reaction_active": "bold red",
    "fault": "bold red",
    "unknown": "dim",
}
_MODE_ABBR = {1: "pp", 3: "pv", 4: "pt", 6: "hm", 7: "ip", 8: "csp", 9: "csv", 10: "cst"}


def status_rows(fleet: Fleet, selectors: Sequence[str] = ()) -> list[dict[str, Any]]:
    """One row per known drive (filtered by ``selectors``), with its agent's liveliness."""
    parsed = [parse_selector(s) for s in selectors]
    groups = fleet.groups() if any(p.group for p in parsed) else {}
    alive = set(fleet.hosts())
    rows = []
    known = fleet.drives()
    for ref in sorted(set(known) | set(fleet.roster())):
        if parsed and not any(
            (p.group and str(ref) in groups.get(p.group, ())) or (not p.group and p.matches(ref)) for p in parsed
        ):
            continue
        st = known.get(ref)
        row: dict[str, Any] = {"host": ref.host, "axis": ref.axis, "agent_alive": ref.host in alive}
        if st is not None:
            row.update(
                state=st.state, goal=st.goal, mode=st.mode_display, position=st.position,
                velocity=st.velocity, error_code=st.error_code, error_text=st.error_text,
                lease_holder=st.lease_holder, lost=st.lost, al_state=st.al_state, seq=st.seq,
                statusword=st.statusword, halt=st.halt,
            )
        else:
            row.update(state="unknown")
        rows.append(row)
    return rows


def status_table(rows: Iterable[dict[str, Any]], title: str = "drives") -> Table:
    """A table of status rows: host, axis, state, mode, position, error code and text, lease."""
    t = Table(title=title, expand=False)
    for col in ("host", "axis", "state", "mode", "position", "error", "lease", "agent"):
        t.add_column(col, justify="right" if col == "position" else "left")
    for r in rows:
        state = r.get("state", "unknown")
        if r.get("lost"):
            state_text = Text("lost", style="bold red")
        else:
            state_text = Text(state, style=_STATE_STYLE.get(state, ""))
        mode = r.get("mode")
        code = r.get("error_code") or 0
        err = f"0x{code:04X} {r.get('error_text', '')}".strip() if code else r.get("error_text", "")
        t.add_row(
            r["host"], r["axis"], state_text,
            "" if mode is None else _MODE_ABBR.get(mode, str(mode)),
            "" if r.get("position") is None else str(r["position"]),
            Text(err, style="red" if code else ""),
            r.get("lease_holder", "") or "",
            Text("up", style="green") if r["agent_alive"] else Text("gone", style="bold red"),
        )
    return t


def result_table(results: Iterable[DriveResult], title: str) -> Table:
    """Per-drive command results."""
    t = Table(title=title)
    for col in ("drive", "outcome", "state", "error", "elapsed s"):
        t.add_column(col, justify="right" if col == "elapsed s" else "left")
    for r in results:
        err = " ".join(x for x in (f"0x{r.error_code:04X}" if r.error_code else "", r.error,
                                   f"(leased by {r.lease_holder})" if r.outcome == "busy" and r.lease_holder else "") if x)
        t.add_row(r.name, Text(r.outcome, style="green" if r.ok else "bold red"), r.state, err, f"{r.elapsed_s:.3f}")
    return t


def print_report(console: Console, report: Report | CommandResult) -> None:
    """Print a command result or an orchestration report as a table plus a clear failure list."""
    if isinstance(report, CommandResult):
        results = [*report.results, *report.unexpected]
        ok, reason, action, errors = report.ok, "", report.op, list(report.errors)
    else:
        results = list(report.final)
        ok, reason, action = report.ok, report.reason, report.action
        errors = [e for _, res in report.steps for e in res.errors]
    console.print(result_table(results, f"{action}: {len(results)} drive(s)"))
    for e in errors:
        console.print(f"agent error: {e}", style="red")
    if ok:
        console.print(f"{action}: all {len(results)} drive(s) reached the goal", style="green")
        return
    if reason:
        console.print(f"{action} FAILED: {reason}", style="bold red")
    for r in results:
        if not r.ok:
            console.print(f"  {r.name}: {r.outcome} ({r.state}) {r.error}".rstrip(), style="red")


def run_watch(fleet: Fleet, selectors: Sequence[str] = (), *, console: Console | None = None,
              duration_s: float | None = None) -> int:
    """Show the live table until Ctrl-C (or ``duration_s``); redraw on every status change."""
    console = console or Console()
    changed = threading.Event()
    for ev in ("status", "arrival", "departure", "agent"):
        fleet.on(ev, lambda *_: changed.set())
    end = None if duration_s is None else time.monotonic() + duration_s
    min_gap = 1.0 / MAX_REDRAW_HZ

    def render() -> Table:
        rows = status_rows(fleet, selectors)
        title = f"{len(fleet.hosts())} agent(s), {len(rows)} drive(s) - {time.strftime('%H:%M:%S')}"
        return status_table(rows, title)

    try:
        with Live(render(), console=console, auto_refresh=False, transient=False) as live:
            while True:
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    break
                if not changed.wait(timeout=left):
                    continue
                changed.clear()
                live.update(render(), refresh=True)
                time.sleep(min_gap)  # coalesce a burst of changes into one redraw
    except KeyboardInterrupt:
        pass
    return 0


__all__ = ["status_rows", "status_table", "result_table", "print_report", "run_watch", "DriveRef", "DriveStatus"]
