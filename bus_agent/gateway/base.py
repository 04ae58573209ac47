"""The gateway's shared state and settings, and what its parts call of each other.

:class:`bus_agent.gateway.gateway.Gateway` is assembled from parts, each a mixin over
:class:`GatewayBase`: the publisher (:mod:`.publisher`: status, events, agent status), leases
and remote group members (:mod:`.peers`), and the command path with the life cycle
(:mod:`.gateway`). Command parsing is pure and lives in :mod:`.requests`.
"""

from __future__ import annotations

import collections
import queue
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Mapping, Protocol, Sequence

import zenoh

from bus_agent import runtime as rt
from bus_agent.gateway.hostclaim import ClaimLink, ConflictTracker, new_instance
from bus_agent.gateway.leases import LeaseTable
from bus_agent.gateway.requests import RECORDING_QUEUE, Request
from schemas import messages as m

#: Lease loss reactions (``DrivePolicy.lease_reaction``) -> drive ops run one after the other.
LEASE_REACTION_OPS: dict[str, tuple[str, ...]] = {
    "quick_stop_then_disable": ("quick_stop", "disable"),
    "quick_stop": ("quick_stop",),
    "disable": ("disable",),
    "none": (),
}
#: Drive status fields whose change is news and is published within one cycle. Position,
#: velocity and torque change every cycle in motion: they go out at most every
#: ``motion_period_s`` and with every heartbeat.
CHANGE_FIELDS = ("state", "statusword", "controlword", "goal", "halt", "mode", "mode_display",
                 "error_code", "error_text", "al_state", "lost", "axis_state", "homed", "motion_request_id")
MOTION_FIELDS = ("position", "velocity", "torque", "target_position", "following_error", "objects", "target_clamps")
#: What the agent asks of a drive (0x6040, the goal, the halt bit, 0x6060): a change of these
#: alone is answered by the drive within a cycle or two (0x6041, 0x6061), and the status waits
#: for that answer to go out with it, at most :data:`HOLD_CYCLES` cycles (docs/agent-gateway.md).
ASKED_FIELDS = ("controlword", "goal", "halt", "mode")
#: Positions of ASKED_FIELDS in the change tuple the publisher compares (CHANGE_FIELDS + holder).
ASKED_INDEX = frozenset(CHANGE_FIELDS.index(f) for f in ASKED_FIELDS)
#: The longest a change of ASKED_FIELDS alone waits for the drive's answer, in agent cycles.
HOLD_CYCLES = 3
#: Remote group member states that trigger the group here.
BAD_STATES = ("fault", "fault_reaction_active")

#: Ops an agent refuses while another agent uses its host name: whatever raises power, clears a
#: fault, changes the mode or moves (the other agent may obey the same command); lowering ops
#: (disable, shutdown, quick_stop, halt, stop) and leases still work.
CONFLICT_REFUSED_OPS = frozenset({"enable", "switch_on", "fault_reset", "set_mode", "nmt", "move", "jog", "home"})
#: Request-id memory: size and time to live of finished requests.
DEDUP_SIZE = 1024
DEDUP_TTL_S = 300.0
#: Identity of commands the agent issues itself (lease loss reactions).
AGENT_SUPERVISOR = ""
#: How long one publish pass may wait, in all, for the command thread to finish its work (see
#: ``Gateway._commands_first``).
COMMANDS_FIRST_MAX_S = 0.005


class CycleLike(Protocol):
    """What the gateway needs from the cycle (``bus_agent.cycle.cycle.Cycle``)."""

    snapshot_sink: Callable[[rt.CycleSnapshot], None] | None

    @property
    def latest(self) -> rt.CycleSnapshot | None: ...

    def submit(self, cmd: rt.DriveCommand | rt.AgentCommand) -> bool: ...

    def trigger_group(self, group: str, reason: str) -> None: ...


@dataclass(frozen=True)
class GatewaySettings:
    host: str
    axes: tuple[str, ...]                      # in slave order
    heartbeat_s: float = 1.0
    agent_period_s: float = 1.0
    motion_period_s: float = 0.1
    backend: str = "sim"
    cycle_us: int = 1000
    groups: Mapping[str, Sequence[str]] = field(default_factory=dict)   # name -> "host/axis"
    lease_reaction: Mapping[str, str] = field(default_factory=dict)     # axis -> LEASE_REACTION_OPS key
    lease_ttl_s: Mapping[str, float] = field(default_factory=dict)      # axis -> default ttl
    instance: str = ""              # this agent process' id ('' = a new random one)
    check_host: bool = True         # refuse to start while another agent holds the host name
    has_connect: bool = False       # the session has connect endpoints (wait for a link first)
    secure: bool = False  # --pki: serve only authenticated command keys (requester from the key)
    #: SCHED_FIFO of gw-publish and gw-command (0: off). Set only for the gateway process (its own
    #: GIL); threads of the cycle process keep ``realtime.helper_priority``.
    rt_priority: int = 0


@dataclass
class RemoteMember:
    """A group member on another host, as seen through its status and its agent's token."""

    group: str
    host: str
    axis: str
    bad: bool = False
    seen: bool = False


class GatewayBase:
    """The gateway's state (created here) and the cross-part calls (declared for the type checker)."""

    def __init__(self, session: zenoh.Session, cycle: CycleLike, settings: GatewaySettings,
                 claim_config: Any = None) -> None:
        """``claim_config``: the ``zenoh.Config`` of the host claim's client session
        (:func:`~bus_agent.gateway.hostclaim.claim_config`), None when this session serves."""
        self.session = session
        self.cycle = cycle
        self.s = settings
        self.host = settings.host
        self.axes = tuple(settings.axes)
        self.agent_state_override: str | None = None
        self.instance = settings.instance or new_instance()
        # Other agents under our host name; a conflict ends after three silent status periods.
        self._conflicts = ConflictTracker(self.host, self.instance, max(1.0, 3 * settings.agent_period_s))
        self._conflict_text = ""
        self._claim_config = claim_config
        self._claim: ClaimLink | None = None
        # cycle -> publisher
        self._latest: rt.CycleSnapshot | None = None
        self._events: collections.deque[tuple[rt.CycleEvent, int, int]] = collections.deque(maxlen=8192)
        self._wake = threading.Event()
        # command thread state
        self._inbox: queue.SimpleQueue[tuple[Callable[..., None], tuple]] = queue.SimpleQueue()
        self._cycle_outcomes: collections.deque[tuple[Request, rt.Outcome]] = collections.deque()
        self._drain_queued = False   # a drain of _cycle_outcomes is queued on gw-command
        self._requests: collections.OrderedDict[str, Request] = collections.OrderedDict()
        self._pending: set[Request] = set()
        self.leases = LeaseTable()
        self._lease_holders: dict[str, str] = {}   # published copy, replaced whole
        self._remotes: list[RemoteMember] = []
        # Remote members change on zenoh's callback threads (status) and the command thread (tokens).
        self._remotes_lock = threading.Lock()
        for group, members in settings.groups.items():
            for member in members:
                host, _, axis = member.partition("/")
                if host != self.host:
                    self._remotes.append(RemoteMember(group, host, axis))
        self._internal_seq = 0
        # publisher thread state
        self._status_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._event_seq: dict[str, int] = {a: 0 for a in self.axes}
        self._agent_seq = 0
        self._last_fields: dict[str, tuple] = {}
        self._last_motion: dict[str, tuple] = {}
        self._last_motion_pub_s: dict[str, float] = {}
        self._status_keys: dict[str, str] = {}  # axis -> its status key, built once
        self._held_until: dict[str, float] = {}  # axis -> when its held change goes out at the latest
        # axis -> (drive snapshot, lease holder) last seen with nothing left to publish
        self._settled: dict[str, tuple[rt.DriveSnapshot, str]] = {}
        self._hold_s = HOLD_CYCLES * settings.cycle_us / 1e6
        self._published: dict[str, m.DriveStatus] = {}
        self._next_heartbeat_s = 0.0
        self._next_agent_s = 0.0
        # zenoh entities
        self._status_pubs: dict[str, zenoh.Publisher] = {}
        self._event_pubs: dict[str, zenoh.Publisher] = {}
        self._agent_pub: zenoh.Publisher | None = None
        self._cmd_queryables: list[Any] = []
        self._other_decls: list[Any] = []
        self._token: Any = None
        self._stop = threading.Event()
        self._accepting = False
        self._threads: list[threading.Thread] = []
        self._pub_lock = threading.Lock()  # publish_once from close() vs the thread
        self._publish_fifo = False    # gw-publish waits and starts each pass under SCHED_FIFO
        self._publish_normal = False  # ... and is under SCHED_OTHER for the rest of this pass
        # Set while the command thread has nothing to do; the publish thread waits for it (bounded).
        self._commands_idle = threading.Event()
        self._commands_idle.set()
        # Flight recorder queries: served one at a time on their own thread (copies take a while).
        self._recordings: queue.Queue[zenoh.Query] = queue.Queue(maxsize=RECORDING_QUEUE)
        #: 'op.outcome' -> replies given (published in AgentStatus.commands, for metrics).
        self._command_counts: dict[str, int] = {}

    if TYPE_CHECKING:  # implemented by the parts (mixins) of Gateway
        def _emit(self, ev: rt.CycleEvent) -> None: ...

        def _state(self, axis: str) -> str: ...

        def _submit(self, req: Request, parsed: Any) -> None: ...

        def _outcome(self, req: Request, outcome: rt.Outcome, event: bool = True) -> None: ...

        def _commands_first(self, until_s: float) -> None: ...
