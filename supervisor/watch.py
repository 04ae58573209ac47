"""Tables of the fleet (status and a live view) with rich.

The live view is driven by the status subscription: every received ``DriveStatus`` (and every
agent arrival or departure) sets an event; the loop redraws when it is set, coalescing bursts to
at most :data:`MAX_REDRAW_HZ` redraws per second. Nothing polls the agents.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from typing import Any, Callable, Iterable, Sequence

from rich.console import Console
from rich.live import Live
from rich.table import Table
from rich.text import Text

from schemas.error_codes import describe
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
    """One row per known or expected drive (filtered by ``selectors``), with its agent's
    liveliness: ``agent`` is ``up``, ``gone`` (seen, then left), ``offline`` (expected, never
    seen by this Fleet) or ``conflict``; ``expected`` is False for a drive outside the expected
    fleet (always True without one)."""
    parsed = [parse_selector(s) for s in selectors]
    groups = fleet.groups() if any(p.group for p in parsed) else {}
    alive = set(fleet.hosts())
    seen = set(fleet.agents())
    conflicts = fleet.conflicts()
    exp = fleet.expected
    rows = []
    known = fleet.drives()
    for ref in sorted(set(known) | set(fleet.roster()) | set(fleet.expected_drives())):
        if parsed and not any(
            (p.group and str(ref) in groups.get(p.group, ())) or (not p.group and p.matches(ref)) for p in parsed
        ):
            continue
        st = known.get(ref)
        agent = ("conflict" if ref.host in conflicts else "up" if ref.host in alive
                 else "gone" if ref.host in seen else "offline")
        row: dict[str, Any] = {"host": ref.host, "axis": ref.axis, "agent_alive": ref.host in alive,
                               "agent": agent, "expected": exp is None or exp.expects(ref.host, ref.axis)}
        if st is not None:
            row.update(
                state=st.state, goal=st.goal, mode=st.mode_display, position=st.position,
                velocity=st.velocity, error_code=st.error_code, error_text=st.error_text,
                lease_holder=st.lease_holder, lost=st.lost, al_state=st.al_state, seq=st.seq,
                statusword=st.statusword, halt=st.halt, axis_state=st.axis_state, homed=st.homed,
                target_position=st.target_position, following_error=st.following_error,
                motion_request_id=st.motion_request_id,
            )
        else:
            row.update(state="offline" if ref.host not in alive else "unknown")
        rows.append(row)
    return rows


_AGENT_STYLE = {"up": "green", "gone": "bold red", "offline": "bold red", "conflict": "bold red reverse"}


def _motion_text(r: dict[str, Any]) -> Text:
    """The PLCopen axis state, '(homed)', and the running motion command's request id."""
    st = r.get("axis_state")
    if st is None:
        return Text("")
    text = st + (" homed" if r.get("homed") else "")
    if r.get("motion_request_id"):
        text += f" {r['motion_request_id']}"
    return Text(text, style="red" if st == "error_stop" else "yellow" if st == "stopping" else "")


def status_table(rows: Iterable[dict[str, Any]], title: str = "drives") -> Table:
    """A table of status rows: host, axis, state, mode, motion (axis state, homed, running command),
    position and target position, error code and text, the
    EtherCAT AL state when it is not OP (and ``lost``), lease, agent liveliness."""
    t = Table(title=title, expand=False)
    for col in ("host", "axis", "state", "mode", "motion", "position", "target", "error", "AL", "lease", "agent"):
        t.add_column(col, justify="right" if col in ("position", "target") else "left")
    for r in rows:
        state = r.get("state", "unknown")
        mode = r.get("mode")
        code = r.get("error_code") or 0
        err = f"0x{code:04X} {r.get('error_text', '')}".strip() if code else r.get("error_text", "")
        al = r.get("al_state", "op")
        al_text = " ".join(x for x in ("" if al == "op" else al.upper(), "lost" if r.get("lost") else "") if x)
        agent = r.get("agent", "up" if r["agent_alive"] else "gone")
        if not r.get("expected", True):
            agent += " unexpected"
        t.add_row(
            r["host"], r["axis"], Text(state, style=_STATE_STYLE.get(state, "bold red")),
            "" if mode is None else _MODE_ABBR.get(mode, str(mode)),
            _motion_text(r),
            "" if r.get("position") is None else str(r["position"]),
            "" if r.get("target_position") is None else str(r["target_position"]),
            Text(err, style="red" if code else ""),
            Text(al_text, style="bold red" if al_text else ""),
            r.get("lease_holder", "") or "",
            Text(agent, style=_AGENT_STYLE.get(agent, "bold yellow")),
        )
    return t


def agent_rows(fleet: Fleet) -> dict[str, dict[str, Any]]:
    """One JSON-ready entry per known or expected agent: liveliness, state, cycle figures."""
    out: dict[str, dict[str, Any]] = {}
    exp = fleet.expected
    conflicts = fleet.conflicts()
    infos = fleet.agents()
    for h in sorted(set(infos) | set(exp.hosts if exp else ())):
        a = infos.get(h)
        st = a.status if a else None
        out[h] = {"alive": bool(a and a.alive), "expected": exp is None or exp.expects(h),
                  "conflict": conflicts.get(h, ""),
                  "state": st.state if st else ("offline" if a is None else None),
                  "backend": st.backend if st else None, "axes": list(st.axes) if st else None,
                  "groups": dict(st.groups) if st else {}, "leases": dict(st.leases) if st else {},
                  "cycle_us": st.cycle_us if st else None, "period_p99_us": st.period_p99_us if st else None,
                  "period_max_us": st.period_max_us if st else None, "overruns": st.overruns if st else None,
                  "wkc_errors": st.wkc_errors if st else None, "cycles": st.cycles if st else None}
    return out


def agent_table(agents: dict[str, dict[str, Any]]) -> Table:
    """Agents and their cycle figures (``drivectl -v``)."""
    t = Table(title="agents")
    for col in ("host", "agent", "state", "backend", "cycle us", "period p99 us", "max us", "overruns",
                "WKC errors"):
        t.add_column(col, justify="left" if col in ("host", "agent", "state", "backend") else "right")
    for h, a in agents.items():
        live = "conflict" if a["conflict"] else "up" if a["alive"] else "offline" if a["state"] == "offline" else "gone"
        if not a["expected"]:
            live += " unexpected"

        def num(v: Any, fmt: str = "{}") -> str:
            return "" if v is None else fmt.format(v)
        t.add_row(h, Text(live, style=_AGENT_STYLE.get(live, "bold yellow")), a["state"] or "", a["backend"] or "",
                  num(a["cycle_us"]), num(a["period_p99_us"], "{:.1f}"), num(a["period_max_us"], "{:.1f}"),
                  num(a["overruns"]), num(a["wkc_errors"]))
    return t


def result_table(results: Iterable[DriveResult], title: str) -> Table:
    """Per-drive command results."""
    t = Table(title=title)
    for col in ("drive", "outcome", "state", "error", "elapsed s"):
        t.add_column(col, justify="right" if col == "elapsed s" else "left")
    for r in results:
        err = " ".join(x for x in (f"0x{r.error_code:04X} {describe(r.error_code)}" if r.error_code else "", r.error,
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


#: Status fields whose change makes a ``watch --json`` line.
JSON_FIELDS = ("state", "goal", "error_code", "error_text", "lost", "al_state", "lease_holder", "mode_display",
               "axis_state", "homed", "motion_request_id")


def _json_line(st: DriveStatus) -> dict[str, Any]:
    return {"event": "status", "host": st.host, "axis": st.axis, "time_ns": st.time_ns,
            **{f: getattr(st, f) for f in JSON_FIELDS}}


def run_watch_json(fleet: Fleet, selectors: Sequence[str] = (), *, duration_s: float | None = None,
                   out: Callable[[str], None] = print) -> int:
    """``watch --json``: one JSON object per line, first the current status of each selected
    drive, then one line per change of :data:`JSON_FIELDS` and per agent arrival, departure or
    host name conflict, until Ctrl-C (or ``duration_s``)."""
    parsed = [parse_selector(s) for s in selectors]

    def wanted(host: str, axis: str) -> bool:
        if not parsed:
            return True
        groups = fleet.groups()
        ref = DriveRef(host, axis)
        return any((p.group and str(ref) in groups.get(p.group, ())) or (not p.group and p.matches(ref))
                   for p in parsed)

    items: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
    fleet.on("status", lambda st: items.put(("status", st)))
    fleet.on("arrival", lambda h: items.put(("arrival", h)))
    fleet.on("departure", lambda h: items.put(("departure", h)))
    fleet.on("agent", lambda a: items.put(("agent", a)))
    last: dict[DriveRef, tuple] = {}
    conflicts: dict[str, str] = {}

    def status(st: DriveStatus) -> None:
        key = tuple(getattr(st, f) for f in JSON_FIELDS)
        ref = DriveRef(st.host, st.axis)
        if wanted(st.host, st.axis) and last.get(ref) != key:
            last[ref] = key
            out(json.dumps(_json_line(st)))

    for st in sorted(fleet.drives().values(), key=lambda st: (st.host, st.axis)):
        status(st)
    for ref in fleet.absent():
        if wanted(ref.host, ref.axis):
            out(json.dumps({"event": "offline", "host": ref.host, "axis": ref.axis}))
    end = None if duration_s is None else time.monotonic() + duration_s
    try:
        while True:
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                break
            try:
                kind, item = items.get(timeout=left)
            except queue.Empty:
                continue
            if kind == "status":
                status(item)
            elif kind in ("arrival", "departure"):
                out(json.dumps({"event": kind, "host": item}))
            now = fleet.conflicts()
            if now != conflicts:
                for h in sorted(set(now) | set(conflicts)):
                    if now.get(h) != conflicts.get(h):
                        out(json.dumps({"event": "conflict", "host": h, "conflict": now.get(h, "")}))
                conflicts = now
    except KeyboardInterrupt:
        pass
    return 0


__all__ = ["run_watch_json", "status_rows", "status_table", "agent_rows", "agent_table", "result_table", "print_report", "run_watch", "DriveRef", "DriveStatus"]
