"""The bridge's wire format, pure: message tags, snapshot/event/command/outcome tuples, the forward filter.

Shared by both ends of the bridge (:mod:`bus_agent.gateway.bridge` in the cycle process,
:mod:`bus_agent.gateway.child` in the gateway process). Length-prefixed pickled tuples; see
docs/agent-gateway.md for the measured choice of pickle over msgpack.
"""

from __future__ import annotations

import dataclasses
import operator
import pickle
from enum import IntEnum
from typing import Any, Callable, Iterable, Sequence

from bus_agent import runtime as rt

#: Drive snapshot fields whose change is forwarded at once (the gateway's ``CHANGE_FIELDS``:
#: each change is a status publication within one cycle).
FORWARD_NOW_FIELDS = ("state", "statusword", "controlword", "goal", "halt", "mode", "mode_display",
                      "error_code", "error_text", "al_state", "lost", "axis_state", "homed", "motion_request_id")
#: Otherwise (position, velocity, torque, statistics) the latest snapshot goes at this rate; it
#: must be at least the gateway's motion rate (``motion_period_s`` 0.1 s) and heartbeat.
FORWARD_PERIOD_S = 0.05
#: How long the child may take to open its session and declare everything.
READY_TIMEOUT_S = 30.0
#: How long ``CycleProxy.submit`` waits for the cycle process's answer.
SUBMIT_TIMEOUT_S = 5.0
#: A recording's round trip may take this much longer than its own timeout (copy, pickling).
RECORD_MARGIN_S = 10.0
#: Events kept while the bridge thread is behind (as the in-process gateway).
EVENT_BACKLOG = 8192

_DRIVE_FIELDS = tuple(f.name for f in dataclasses.fields(rt.DriveSnapshot))
_STATS_FIELDS = tuple(f.name for f in dataclasses.fields(rt.CycleStats))
_EVENT_FIELDS = tuple(f.name for f in dataclasses.fields(rt.CycleEvent))
_OUTCOME_FIELDS = tuple(f.name for f in dataclasses.fields(rt.Outcome))
_drive_tuple = operator.attrgetter(*_DRIVE_FIELDS)
_stats_tuple = operator.attrgetter(*_STATS_FIELDS)
_event_tuple = operator.attrgetter(*_EVENT_FIELDS)
_outcome_tuple = operator.attrgetter(*_OUTCOME_FIELDS)
_change_key = operator.attrgetter(*FORWARD_NOW_FIELDS)


class Msg(IntEnum):
    """First element of every message tuple."""

    # cycle process -> gateway process
    INIT = 1        # (settings kwargs, ZenohConfig, sim: (segment, n_slaves, actions) | None)
    UPDATE = 2      # (snapshot | None, events, outcomes)
    SUBMITTED = 3   # (cid, accepted, cycle state)
    SIM_RESULT = 4  # (call id, ok, detail or error text)
    STOPPING = 5    # stop taking commands; agent state "stopping"
    CLOSE = 6       # the cycle stopped: publish the last status, undeclare, close, exit
    RECORD_RESULT = 7  # (call id, ok, RecordingData or error text)
    # gateway process -> cycle process
    READY = 10      # ()
    FAILED = 11     # (what: "zenoh" | "gateway", text)
    SUBMIT = 12     # (cid, command fields)
    TRIGGER = 13    # (group, reason)
    SIM = 14        # (call id, action, position, args)
    RECORD = 15     # (call id, what, last_s, timeout_s): a flight recording (Cycle.recording)


class BridgeError(RuntimeError):
    """The gateway process could not be started. ``what``: "zenoh" (session) or "gateway"."""

    def __init__(self, what: str, text: str) -> None:
        super().__init__(text)
        self.what = what


# ---- pure encoding ------------------------------------------------------------------------------


def dumps(msg: tuple) -> bytes:
    return pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)


def loads(data: bytes) -> tuple:
    msg = pickle.loads(data)
    if not isinstance(msg, tuple) or not msg:
        raise ValueError(f"bridge message is not a tagged tuple: {msg!r:.80}")
    return (Msg(msg[0]), *msg[1:])


def encode_snapshot(snap: rt.CycleSnapshot) -> tuple:
    """A snapshot without its events (those travel with their own cycle, see encode_event)."""
    return (snap.cycle, snap.time_ns, snap.agent_state, _stats_tuple(snap.stats),
            tuple(map(_drive_tuple, snap.drives)))


def _drive_snapshot(fields: Sequence[Any]) -> rt.DriveSnapshot:
    """A DriveSnapshot of all its field values in order (what ``encode_snapshot`` sent), built
    without the frozen dataclass's ``__init__``, which sets each of the 26 fields through
    ``object.__setattr__``: 1.4 instead of 3.5 us, per drive of every snapshot the gateway
    process reads. The class defines no ``__post_init__``, so the objects are equal."""
    if len(fields) != len(_DRIVE_FIELDS):
        raise ValueError(f"drive snapshot of {len(fields)} fields, expected {len(_DRIVE_FIELDS)}")
    d = object.__new__(rt.DriveSnapshot)
    d.__dict__.update(zip(_DRIVE_FIELDS, fields))
    return d


def decode_snapshot(t: Sequence[Any], events: tuple[rt.CycleEvent, ...] = (),
                    previous: tuple[Sequence[Any], rt.CycleSnapshot] | None = None) -> rt.CycleSnapshot:
    """The snapshot of ``encode_snapshot``'s tuple ``t``. ``previous``: the last tuple and its
    snapshot; a drive whose fields did not change keeps the previous DriveSnapshot object (a
    tuple comparison instead of a new object), so readers can tell an unchanged drive by identity."""
    cycle, time_ns, agent_state, stats, drives = t
    if previous is not None and len(previous[0][4]) == len(drives):
        old_t, old = previous[0][4], previous[1].drives
        built = tuple(old[i] if d == old_t[i] else _drive_snapshot(d) for i, d in enumerate(drives))
    else:
        built = tuple(map(_drive_snapshot, drives))
    return rt.CycleSnapshot(cycle=cycle, time_ns=time_ns, drives=built,
                            events=events, stats=rt.CycleStats(*stats), agent_state=agent_state)


def encode_event(ev: rt.CycleEvent, cycle: int, time_ns: int) -> tuple:
    return (_event_tuple(ev), cycle, time_ns)


def decode_event(t: Sequence[Any]) -> tuple[rt.CycleEvent, int, int]:
    fields, cycle, time_ns = t
    return rt.CycleEvent(*fields), cycle, time_ns


def encode_update(snap: rt.CycleSnapshot | None, events: Iterable[tuple[rt.CycleEvent, int, int]],
                  outcomes: Iterable[tuple[int, rt.Outcome]]) -> bytes:
    return dumps((Msg.UPDATE.value, encode_snapshot(snap) if snap is not None else None,
                  tuple(encode_event(*e) for e in events), tuple((cid, _outcome_tuple(o)) for cid, o in outcomes)))


def encode_command(cid: int, cmd: rt.DriveCommand | rt.AgentCommand) -> bytes:
    """A command without its callback; the cycle process attaches one that routes by ``cid``."""
    axes = cmd.axes if isinstance(cmd, rt.DriveCommand) else None
    return dumps((Msg.SUBMIT.value, cid, (cmd.request_id, cmd.op, axes, dict(cmd.args), cmd.timeout_s,
                                          cmd.supervisor, cmd.received_ns)))


def decode_command(fields: Sequence[Any], on_outcome: Callable[[rt.Outcome], None]) -> rt.DriveCommand | rt.AgentCommand:
    request_id, op, axes, args, timeout_s, supervisor, received_ns = fields
    if axes is None:
        return rt.AgentCommand(request_id=request_id, op=op, args=args, timeout_s=timeout_s, supervisor=supervisor,
                               received_ns=received_ns, on_outcome=on_outcome)
    return rt.DriveCommand(request_id=request_id, op=op, axes=tuple(axes), args=args, timeout_s=timeout_s,
                           supervisor=supervisor, received_ns=received_ns, on_outcome=on_outcome)


def decode_outcome(t: Sequence[Any]) -> rt.Outcome:
    return rt.Outcome(*t)


class ForwardFilter:
    """Decides which snapshots cross to the gateway (functional core of ``bridge-out``).

    ``due(snap, now_s, pending)`` is True when ``pending`` (events or outcomes wait), when a
    :data:`FORWARD_NOW_FIELDS` field of any drive or the agent state differs from the last
    forwarded snapshot, or when ``period_s`` passed since the last forward. A True answer
    counts as forwarded.
    """

    def __init__(self, period_s: float = FORWARD_PERIOD_S) -> None:
        self.period_s = period_s
        self._key: tuple | None = None
        self._due_s = 0.0

    def due(self, snap: rt.CycleSnapshot, now_s: float, pending: bool = False) -> bool:
        key = (snap.agent_state, tuple(map(_change_key, snap.drives)))
        if pending or now_s >= self._due_s or key != self._key:
            self._key = key
            self._due_s = now_s + self.period_s
            return True
        return False
