"""``--self-test``: every monitor shown able to fail, and able to pass.

For each monitor, :data:`CASES` holds two synthetic traces built by hand: one that breaks the
monitor's promise exactly once in the way the soak could meet it, and the same situation with
the promise kept. A monitor passes its self-test when it reports a violation on the first and
none on the second. No process, no network: this runs in a fraction of a second.
"""

from __future__ import annotations

from array import array
from typing import Callable

from .limits import check_limits
from .monitors import (MONITORS, final_down, group_reflex, lost_is_unknown, malformed_refused, no_stale_found,
                       no_unexpected_death, no_unrequested_enable, one_reply, seq_rising)
from .trace import Command, ErrReply, Event, Injection, Limits, Recording, Reply, Result, Status, Trace

MS = 1_000_000
T0 = 1_700_000_000_000_000_000  # an epoch time in ns, so every time is positive and realistic


def _t(ms: float) -> int:
    return T0 + int(ms * MS)


def _trace() -> Trace:
    return Trace(hosts={"h1": ("a", "b"), "h2": ("a",)}, groups={"g": ("h1/a", "h1/b", "h2/a")},
                 limits={r: Limits(100_000.0, 1_000_000.0) for r in ("h1/a", "h1/b", "h2/a")})


def _st(ms: float, ref: str, seq: int, state: str, lost: bool = False, goal: str = "disabled", cycle: int = 0,
        mode: int = 8) -> Status:
    h, a = ref.split("/")
    return Status(_t(ms) + 100_000, h, a, seq, _t(ms), cycle or int(ms), state, lost, goal, mode)


def _ev(ms: float, ref: str, kind: str, cycle: int = 0, rid: str = "", detail: str = "") -> Event:
    h, a = ref.split("/")
    return Event(_t(ms) + 100_000, h, a, 0, _t(ms), cycle or int(ms), kind, detail, request_id=rid)


def _cmd(rid: str, op: str, refs: tuple[str, ...], sent: float, done: float, replies: list[tuple[str, str]],
         flaw: str = "", errors: tuple[tuple[str, str], ...] = ()) -> Command:
    c = Command(rid, op, f"drives/@v1/{refs[0].split('/')[0]}/drive/*/cmd/{op}", refs, _t(sent), _t(done),
                malformed=flaw)
    c.replies = [Reply(_t(done), ref.split("/")[0], ref.split("/")[1], rid, op, outcome,
                       reason="why" if outcome != "done" else "") for ref, outcome in replies]
    c.errors = [ErrReply(_t(done), h, f"{h}: {text}") for h, text in errors]
    return c


# ---- one case per monitor: (broken, kept) -----------------------------------------------------------


def _one_reply(broken: bool) -> Trace:
    tr = _trace()
    replies = [("h1/a", "done")] + ([("h1/a", "done")] if broken else [("h1/b", "done")])
    tr.commands = [_cmd("r1", "enable", ("h1/a", "h1/b"), 0, 20, replies)]
    return tr


def _unrequested(broken: bool) -> Trace:
    tr = _trace()
    tr.statuses = [_st(0, "h1/a", 1, "switch_on_disabled"), _st(50, "h1/a", 2, "operation_enabled", goal="enabled"),
                   _st(100, "h1/a", 3, "unknown", lost=True), _st(150, "h1/a", 4, "operation_enabled")]
    tr.commands = [_cmd("e1", "enable", ("h1/a",), 10, 60, [("h1/a", "done")])]
    if not broken:  # the stale "found" case is kept honest: an enable after the loss
        tr.commands.append(_cmd("e2", "enable", ("h1/a",), 120, 160, [("h1/a", "done")]))
    return tr


def _reflex(broken: bool) -> Trace:
    tr = _trace()
    tr.statuses = [_st(0, r, 1, "operation_enabled", goal="enabled") for r in ("h1/a", "h1/b", "h2/a")]
    tr.events = [_ev(100, "h1/a", "fault", cycle=100), _ev(100, "h1/b", "reflex", cycle=100),
                 _ev(300 if broken else 104, "h2/a", "reflex", cycle=900)]
    return tr


def _seq(broken: bool) -> Trace:
    tr = _trace()
    tr.statuses = [_st(0, "h1/a", 5, "switch_on_disabled"), _st(10, "h1/a", 6, "switch_on_disabled"),
                   _st(20, "h1/a", 6 if broken else 7, "switch_on_disabled"),
                   # after a kill and restart the new instance numbers from 0 again: kept
                   _st(300, "h1/a", 0, "switch_on_disabled")]
    tr.injections = [Injection("agent_restart", "h1", _t(100), _t(100), _t(250))]
    return tr


def _malformed(broken: bool) -> Trace:
    tr = _trace()
    c = _cmd("m1", "enable", ("h1/a", "h1/b"), 0, 10, [], flaw="unknown_argument",
             errors=(("h1", "invalid command_request: args: unknown argument 'force'"),))
    c.before = {"h1/a": _st(-1, "h1/a", 1, "switch_on_disabled")}
    c.after = {"h1/a": _st(11, "h1/a", 2, "switch_on_disabled", goal="enabled" if broken else "disabled")}
    tr.commands = [c]
    return tr


def _limits(broken: bool) -> Trace:
    tr = _trace()
    # 1 ms cycles: 100 counts per cycle at most, the step changes by 1 count per cycle at most
    tp = [0, 1, 3, 6, 10, 15, 21, 28, 36, 45, 55] + ([555] if broken else [66])
    n = len(tp)
    tr.recordings = [Recording(_t(0), "h2", 1000, n, ("a",), {
        "time_ns": array("q", [i * MS for i in range(n)]), "statusword": array("q", [0x0237] * n),
        "controlword": array("q", [0x000F] * n), "mode_display": array("q", [8] * n),
        "target_position": array("q", tp), "target_velocity": array("q", [0] * n)})]
    return tr


def _death(broken: bool) -> Trace:
    tr = _trace()
    tr.processes = 3
    tr.unexpected_exits = ["twin: bus-agent h1 exited unexpectedly (exit code -11)"] if broken else []
    return tr


def _final(broken: bool) -> Trace:
    tr = _trace()
    tr.final = {r: _st(0, r, 1, "switch_on_disabled") for r in tr.refs()}
    if broken:
        tr.final["h2/a"] = _st(0, "h2/a", 1, "operation_enabled", goal="enabled")
    return tr


def _lost_unknown(broken: bool) -> Trace:
    tr = _trace()
    tr.statuses = [_st(0, "h1/a", 1, "operation_enabled" if broken else "unknown", lost=True)]
    return tr


def _stale_found(broken: bool) -> Trace:
    tr = _trace()
    tr.injections = [Injection("wkc_fault", "h1/a", _t(0), _t(0), _t(1000))]
    tr.statuses = [_st(5, "h1/a", 1, "operation_enabled", goal="enabled"),  # before the fault reached it
                   _st(40, "h1/a", 2, "unknown", lost=True),
                   _st(45, "h1/a", 3, "operation_enabled" if broken else "unknown", lost=not broken),
                   _st(1100, "h1/a", 4, "fault")]
    return tr


CASES: dict[str, tuple[Callable[[Trace], Result], Callable[[bool], Trace]]] = {
    "one_terminal_reply": (one_reply, _one_reply),
    "no_unrequested_enable": (no_unrequested_enable, _unrequested),
    "group_reflex": (group_reflex, _reflex),
    "status_seq_rising": (seq_rising, _seq),
    "malformed_refused": (malformed_refused, _malformed),
    "wire_limits": (check_limits, _limits),
    "no_unexpected_death": (no_unexpected_death, _death),
    "final_disable_down": (final_down, _final),
    "lost_state_unknown": (lost_is_unknown, _lost_unknown),
    "faulted_never_enabled": (no_stale_found, _stale_found),
}


def self_test() -> dict:
    """Each monitor on its broken and its kept trace: ``{"ok": bool, "monitors": {name: {...}}}``."""
    out: dict = {"monitors": {}}
    assert set(CASES) == set(MONITORS), "every monitor has a self-test case"
    for name, (monitor, build) in CASES.items():
        broken, kept = monitor(build(True)), monitor(build(False))
        out["monitors"][name] = {
            "fails_when_broken": bool(broken.violations), "passes_when_kept": not kept.violations,
            "broken_reports": [v.what for v in broken.violations],
            "kept_reports": [v.what for v in kept.violations]}
    out["ok"] = all(m["fails_when_broken"] and m["passes_when_kept"] for m in out["monitors"].values())
    return out
