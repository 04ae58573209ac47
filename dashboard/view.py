"""What the dashboard shows, kept from the supervisor API's callbacks; read by the web handlers.

:class:`FleetView` is fed by ``supervisor.Fleet`` listeners (status, agent, arrival, departure)
and the drive event subscriber, on their threads; the web side reads JSON-ready copies. Every
change bumps a version; each drive row, host row and event carries the version it changed at,
so a live page gets only what changed since the version it has (:meth:`FleetView.changes_since`).
No I/O here.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Iterable

from schemas.messages import DRIVE_STATES, AgentStatus, DriveStatus, Event

#: Motion samples kept per drive for the live plots (status publications: about 10 per second
#: in motion, one per heartbeat at rest).
MOTION_SAMPLES = 600
#: Recent events kept for the page.
EVENTS_KEPT = 200
#: How the page colours a drive, by CiA 402 state (the contract's names). ``unknown`` is what a
#: lost drive reports (its last known state, where published, goes in another field): lost.
DISPLAY_OF_STATE = {
    "not_ready_to_switch_on": "disabled",
    "switch_on_disabled": "disabled",
    "ready_to_switch_on": "disabled",
    "switched_on": "disabled",
    "operation_enabled": "enabled",
    "quick_stop_active": "quick_stop",
    "fault_reaction_active": "fault",
    "fault": "fault",
    "unknown": "lost",
}
#: Every colour class of a drive row: the above, ``lost`` (not answering) and ``offline`` (no live
#: agent reports it).
DISPLAYS = ("enabled", "disabled", "quick_stop", "fault", "lost", "offline")
#: Displays that need an operator's attention (the page's banner).
ATTENTION_DISPLAYS = ("fault", "lost", "offline")
#: 0x60F4 following error actual value, by its CiA 402 name in ``DriveStatus.objects`` (present
#: when the drive maps it).
FOLLOWING_ERROR_OBJECT = "following_error_actual_value"
#: Cyclic synchronous position (0x6060/0x6061 = 8): the only mode where the agent's own following
#: error (target written last minus 0x6064) means something.
MODE_CSP = 8


def following_error(st: DriveStatus) -> tuple[int, str] | None:
    """The drive's following error and where it comes from, or None when unknown. Pure.

    ``0x60F4`` when the drive maps it (its own measurement); else ``agent`` (0x607A written last
    minus 0x6064) while the drive runs cyclic synchronous position in Operation enabled with its
    position mapped; else unknown (the agent's field then reads 0 and means nothing)."""
    v = st.objects.get(FOLLOWING_ERROR_OBJECT)
    if v is not None:
        return int(v), "0x60F4"
    if st.state == "operation_enabled" and st.mode_display == MODE_CSP and "position" not in st.absent:
        return st.following_error, "agent"
    return None


def dc_offset_us(st: AgentStatus) -> tuple[float, float] | None:
    """(p50, p99) of the frame-to-SYNC0 offset while any of the agent's slaves runs SYNC0, else
    None (the fields then read 0 and mean nothing). Pure."""
    if "sync0" not in st.dc.values():
        return None
    return st.dc_offset_p50_us, st.dc_offset_p99_us


def is_lost(st: DriveStatus) -> bool:
    """Not answering: flagged lost, or its state unknown (what a lost drive reports). Pure."""
    return st.lost or st.state == "unknown"


def display_of(state: str, lost: bool, online: bool) -> str:
    """The colour class of a drive (:data:`DISPLAYS`): offline before lost before its state. Pure."""
    if not online:
        return "offline"
    return "lost" if lost else DISPLAY_OF_STATE.get(state, "disabled")


def drive_row(st: DriveStatus, agent_alive: bool, last_state: str = "") -> dict[str, Any]:
    """One table row (JSON-ready); ``last_state``: the last state seen before it was lost, used
    when the status does not carry ``last_known_state`` (an older agent). Pure."""
    fe = following_error(st)
    lost = is_lost(st)
    display = display_of(st.state, lost, agent_alive)
    return {"host": st.host, "axis": st.axis, "state": st.state, "display": display,
            "last_state": (st.last_known_state or last_state) if lost else "", "mode": st.mode_display,
            "position": st.position, "velocity": st.velocity, "torque": st.torque,
            "following_error": None if fe is None else fe[0],
            "error_code": st.error_code, "error_text": st.error_text, "al_state": st.al_state,
            "lost": lost, "lease_holder": st.lease_holder, "statusword": st.statusword,
            "goal": st.goal, "online": agent_alive, "time_ns": st.time_ns,
            "alarm": display in ATTENTION_DISPLAYS}


def offline_row(host: str, axis: str) -> dict[str, Any]:
    """Row of an expected drive that no live agent reports. Pure."""
    return {"host": host, "axis": axis, "state": "offline", "display": "offline", "last_state": "", "mode": None, "position": None, "velocity": None,
            "torque": None, "error_code": 0, "error_text": "", "al_state": "none", "lost": False,
            "lease_holder": "", "statusword": None, "goal": None, "online": False, "alarm": True, "time_ns": 0,
            "following_error": None}


def agent_row(host: str, alive: bool, st: AgentStatus | None, expected: bool, conflict: str = "") -> dict[str, Any]:
    """One agent health row (JSON-ready); ``conflict``: why its host name is in conflict ('' if
    not). Pure."""
    row: dict[str, Any] = {"host": host, "alive": alive, "expected": expected, "state": "offline",
                           "conflict": conflict}
    if st is not None:
        row.update(state=st.state if alive else "offline", backend=st.backend, cycle_us=st.cycle_us,
                   cycles=st.cycles, period_p50_us=st.period_p50_us, period_p99_us=st.period_p99_us,
                   period_max_us=st.period_max_us, overruns=st.overruns, wkc_errors=st.wkc_errors,
                   axes=list(st.axes), commands=dict(getattr(st, "commands", {}) or {}))
        dc = dc_offset_us(st)
        row.update(dc_offset_p50_us=None if dc is None else dc[0], dc_offset_p99_us=None if dc is None else dc[1])
    return row


def event_row(ev: Event) -> dict[str, Any]:
    """One event line (JSON-ready). Pure."""
    return {"host": ev.host, "axis": ev.axis, "time_ns": ev.time_ns, "kind": ev.kind, "detail": ev.detail,
            "from_state": ev.from_state, "to_state": ev.to_state, "error_code": ev.error_code,
            "alarm": ev.kind in ("fault", "lost", "reflex")}


class FleetView:
    """The dashboard's state. ``expected``: host -> axes of the expected fleet (may be empty)."""

    def __init__(self, expected: dict[str, list[str]] | None = None) -> None:
        self.expected = {h: list(a) for h, a in (expected or {}).items()}
        self._lock = threading.Lock()
        self.version = 0
        self._status: dict[tuple[str, str], DriveStatus] = {}
        self._rows: dict[tuple[str, str], tuple[int, dict[str, Any]]] = {}
        self._agents: dict[str, tuple[bool, AgentStatus | None]] = {}
        self._hosts: dict[str, tuple[int, dict[str, Any]]] = {}
        self._conflicts: dict[str, str] = {}
        self._last_state: dict[tuple[str, str], str] = {}
        self._events: collections.deque[tuple[int, dict[str, Any]]] = collections.deque(maxlen=EVENTS_KEPT)
        self._motion: dict[tuple[str, str], collections.deque[tuple[float, int, int, int]]] = {}
        self.started_s = time.time()
        for h, axes in self.expected.items():
            self._agents[h] = (False, None)
            self._touch_host(h)
            for a in axes:
                self._set_row((h, a))

    # ---- feeding (any thread) --------------------------------------------------------------

    def on_status(self, st: DriveStatus) -> None:
        ref = (st.host, st.axis)
        with self._lock:
            self._status[ref] = st
            if not is_lost(st):
                self._last_state[ref] = st.state
            m = self._motion.get(ref)
            if m is None:
                m = self._motion[ref] = collections.deque(maxlen=MOTION_SAMPLES)
            m.append((st.time_ns / 1e9, st.position, st.velocity, st.torque))
            self._set_row(ref)

    def on_agent(self, st: AgentStatus) -> None:
        with self._lock:
            alive = self._agents.get(st.host, (True, None))[0]
            self._agents[st.host] = (alive or st.state == "running", st)
            self._touch_host(st.host)

    def on_alive(self, host: str, alive: bool) -> None:
        with self._lock:
            st = self._agents.get(host, (False, None))[1]
            self._agents[host] = (alive, st)
            self._touch_host(host)
            for ref in [r for r in set(self._status) | set(self._rows) if r[0] == host]:
                self._set_row(ref)

    def on_conflicts(self, conflicts: dict[str, str]) -> None:
        """Hosts whose name two agents use now, with why (``Fleet.conflicts()``, polled)."""
        with self._lock:
            changed = set(conflicts.items()) ^ set(self._conflicts.items())
            self._conflicts = dict(conflicts)
            for host in {h for h, _ in changed}:
                self._touch_host(host)

    def on_event(self, ev: Event) -> None:
        with self._lock:
            self.version += 1
            self._events.append((self.version, event_row(ev)))

    def _touch_host(self, host: str) -> None:
        self.version += 1
        alive, st = self._agents.get(host, (False, None))
        self._hosts[host] = (self.version, agent_row(host, alive, st, host in self.expected,
                                                     self._conflicts.get(host, "")))

    def _set_row(self, ref: tuple[str, str]) -> None:
        st = self._status.get(ref)
        alive = self._agents.get(ref[0], (False, None))[0]
        row = drive_row(st, alive, self._last_state.get(ref, "")) if st is not None else offline_row(*ref)
        old = self._rows.get(ref)
        if old is not None and _same_row(old[1], row):
            return  # a heartbeat: nothing the page shows changed, nothing to send
        self.version += 1
        self._rows[ref] = (self.version, row)

    # ---- reading (any thread) -------------------------------------------------------------------

    def changes_since(self, version: int) -> dict[str, Any]:
        """Rows, hosts and events changed after ``version`` (everything for 0), and the version now."""
        with self._lock:
            return {"version": self.version,
                    "full": version == 0,
                    "drives": [r for v, r in self._rows.values() if v > version],
                    "hosts": [r for v, r in self._hosts.values() if v > version],
                    "events": [e for v, e in self._events if v > version]}

    def snapshot(self) -> dict[str, Any]:
        """Everything, sorted (``/api/fleet``)."""
        with self._lock:
            drives = [r for _, (_, r) in sorted(self._rows.items())]
            hosts = [r for _, (_, r) in sorted(self._hosts.items())]
            events = [e for _, e in self._events]
            version = self.version
        return {"version": version, "drives": drives, "hosts": hosts, "events": events,
                "summary": summary(drives, hosts)}

    def drive(self, host: str, axis: str) -> dict[str, Any] | None:
        """One drive: its row, motion history and events (``/api/drive/<host>/<axis>``)."""
        with self._lock:
            row = self._rows.get((host, axis))
            if row is None:
                return None
            motion = list(self._motion.get((host, axis), ()))
            events = [e for _, e in self._events if e["host"] == host and e["axis"] == axis]
        return {"drive": row[1], "motion": {"t": [m[0] for m in motion], "position": [m[1] for m in motion],
                                            "velocity": [m[2] for m in motion], "torque": [m[3] for m in motion]},
                "events": events}

    def statuses(self) -> dict[tuple[str, str], DriveStatus]:
        with self._lock:
            return dict(self._status)

    def agents(self) -> dict[str, tuple[bool, AgentStatus | None]]:
        with self._lock:
            return dict(self._agents)


def _same_row(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Equal but for the status time (heartbeats carry a new one)."""
    return all(a.get(k) == v for k, v in b.items() if k != "time_ns")


def summary(drives: Iterable[dict[str, Any]], hosts: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """Counts for the page header and the fleet metrics. Pure."""
    by_state = {s: 0 for s in (*DRIVE_STATES, "offline")}
    alarms = 0
    n = 0
    for r in drives:
        n += 1
        by_state[r["state"]] = by_state.get(r["state"], 0) + 1
        alarms += bool(r["alarm"])
    hs = list(hosts)
    return {"drives": n, "by_state": by_state, "alarms": alarms, "agents_up": sum(1 for h in hs if h["alive"]),
            "agents_expected_offline": sum(1 for h in hs if h["expected"] and not h["alive"])}
