"""What the chaos soak observed, as plain records (pure data; no I/O).

Every record carries wall-clock times in ns since the epoch: ``t_ns`` when the soak's client saw
it, ``time_ns`` where the agent stamped it (status and events: the snapshot's time). All
processes run on one machine, so both clocks are the same clock. The monitors
(:mod:`bench.chaos.monitors`) are pure functions of a :class:`Trace`; the self-test builds traces
by hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

#: CiA 402 states a drive is "down" in (not powered for motion).
UP = "operation_enabled"
#: States that trigger a group reflex (with ``lost``).
BAD_STATES = frozenset({"fault", "fault_reaction_active"})
#: States a drive may be in after a final disable.
DOWN_STATES = frozenset({"switch_on_disabled", "not_ready_to_switch_on", "fault"})
#: Goals that keep a drive in a down state (a group reflex may set quick_stop on a disabled drive).
DOWN_GOALS = frozenset({"disabled", "quick_stop"})
#: Outcomes that mean a command was not taken up at all.
REFUSED = frozenset({"rejected", "busy"})


@dataclass(frozen=True)
class Violation:
    """A promise broken: which monitor, what, and the details to find it again."""

    monitor: str
    what: str
    detail: dict[str, Any]


@dataclass
class Result:
    """One monitor's verdict: cases checked, cases it could not judge, violations."""

    monitor: str
    checked: int = 0
    skipped: int = 0
    violations: list[Violation] = field(default_factory=list)
    #: What the monitor measured on the way (e.g. reflex latencies), for the result.
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Status:
    """One ``drive_status`` put seen on ``drives/@v1/<host>/drive/<axis>/status``."""

    t_ns: int
    host: str
    axis: str
    seq: int
    time_ns: int
    cycle: int
    state: str
    lost: bool = False
    goal: str = "disabled"
    mode: int = 8
    halt: bool = False
    lease_holder: str = ""
    error_code: int = 0

    @property
    def ref(self) -> str:
        return f"{self.host}/{self.axis}"


@dataclass(frozen=True)
class AgentInfo:
    """One ``agent_status`` put seen on ``drives/@v1/<host>/agent``."""

    t_ns: int
    host: str
    seq: int
    instance: str
    state: str = "running"
    #: The longest cycle period of the agent's last statistics window (1000 cycles): a stall.
    period_max_us: float = 0.0


@dataclass(frozen=True)
class Event:
    """One ``event`` put seen on ``drives/@v1/<host>/drive/<axis>/event``."""

    t_ns: int
    host: str
    axis: str
    seq: int
    time_ns: int
    cycle: int
    kind: str
    detail: str = ""
    from_state: str = "unknown"
    to_state: str = "unknown"
    request_id: str = ""

    @property
    def ref(self) -> str:
        return f"{self.host}/{self.axis}"


@dataclass(frozen=True)
class Reply:
    """One ``command_reply`` (ok) of a command query."""

    t_ns: int
    host: str
    axis: str
    request_id: str
    op: str
    outcome: str
    state: str = "unknown"
    reason: str = ""

    @property
    def ref(self) -> str:
        return f"{self.host}/{self.axis}"


@dataclass(frozen=True)
class ErrReply:
    """One ``reply_err`` of a command query: the agent refused the query as a whole. ``host`` is
    taken from the text's ``"<host>: "`` prefix ('' when the text has none)."""

    t_ns: int
    host: str
    text: str


@dataclass
class Command:
    """One command query the soak sent: ``addressed`` the drives (``host/axis``) its key names;
    ``malformed`` the flaw it was built with ('' for a well-formed command). ``before``/``after``:
    the addressed drives' status fetched right before sending and right after the query finished
    (malformed commands only)."""

    request_id: str
    op: str
    key: str
    addressed: tuple[str, ...]
    sent_ns: int
    done_ns: int = 0
    args: dict[str, Any] = field(default_factory=dict)
    malformed: str = ""
    replies: list[Reply] = field(default_factory=list)
    errors: list[ErrReply] = field(default_factory=list)
    before: dict[str, Status] = field(default_factory=dict)
    after: dict[str, Status] = field(default_factory=dict)

    def replies_of(self, ref: str) -> list[Reply]:
        return [r for r in self.replies if r.ref == ref]


@dataclass(frozen=True)
class Injection:
    """One fault-injection episode: ``kind`` one of ``fault``, ``unplug`` (to ``end_ns``: plugged
    again), ``wkc_fault`` (on until ``end_ns``), ``cut`` (link down until ``end_ns``: restored and
    answering), ``agent_restart`` (SIGKILL at ``start_ns``, answering again at ``end_ns``),
    ``router_restart`` (likewise for the router); ``target`` a drive ``host/axis``, a host or ''
    (the router). ``applied_ns``: when the injection itself took effect (the simulator's reply)."""

    kind: str
    target: str
    start_ns: int
    applied_ns: int
    end_ns: int
    ok: bool = True
    detail: str = ""

    @property
    def host(self) -> str:
        return self.target.split("/")[0]


@dataclass(frozen=True)
class Recording:
    """A flight recording fetched on ``drives/@v1/<host>/agent/recording`` (the reply's fields)."""

    t_ns: int
    host: str
    cycle_us: int
    n_cycles: int
    axes: tuple[str, ...]
    channels: dict[str, Sequence[int]]


@dataclass(frozen=True)
class Limits:
    """One axis's motion limits in counts: velocity (counts/s) and acceleration (counts/s^2)."""

    max_velocity: float
    max_acceleration: float


@dataclass
class Trace:
    """Everything one soak saw, and what it knows of the fleet it ran (hosts, groups, limits)."""

    hosts: dict[str, tuple[str, ...]]
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    limits: dict[str, Limits] = field(default_factory=dict)
    statuses: list[Status] = field(default_factory=list)
    agents: list[AgentInfo] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    commands: list[Command] = field(default_factory=list)
    injections: list[Injection] = field(default_factory=list)
    recordings: list[Recording] = field(default_factory=list)
    #: Processes that exited without the schedule killing them: one text each.
    unexpected_exits: list[str] = field(default_factory=list)
    #: Processes watched by the no-death monitor.
    processes: int = 0
    #: The simulated drives live in the agent's process (the sim backend): a killed agent takes
    #: its drives' faults with it, and the restarted one starts with fresh drives.
    sim_in_agent: bool = True
    #: Every drive's status after the final disable (None: no answer).
    final: dict[str, Status | None] = field(default_factory=dict)
    final_ns: int = 0

    def refs(self) -> list[str]:
        return [f"{h}/{a}" for h, axes in self.hosts.items() for a in axes]


def trace_from_json(d: dict[str, Any]) -> Trace:
    """A trace written by ``python -m bench.chaos`` (``*.trace.json``), to judge it again
    (``--judge``); it has no flight recordings."""
    def command(c: dict[str, Any]) -> Command:
        return Command(**{**c, "addressed": tuple(c["addressed"]), "replies": [Reply(**x) for x in c["replies"]],
                          "errors": [ErrReply(**x) for x in c["errors"]],
                          "before": {k: Status(**v) for k, v in c["before"].items()},
                          "after": {k: Status(**v) for k, v in c["after"].items()}})
    return Trace(hosts={h: tuple(a) for h, a in d["hosts"].items()}, groups={g: tuple(m) for g, m in d["groups"].items()},
                 statuses=[Status(**x) for x in d["statuses"]], agents=[AgentInfo(**x) for x in d["agents"]],
                 events=[Event(**x) for x in d["events"]], commands=[command(c) for c in d["commands"]],
                 injections=[Injection(**x) for x in d["injections"]], unexpected_exits=list(d["unexpected_exits"]),
                 processes=d.get("processes", 0), sim_in_agent=d.get("sim_in_agent", True),
                 final={r: Status(**s) if s else None for r, s in d["final"].items()}, final_ns=d["final_ns"])
