"""The state every part of the cycle shares, and what the parts call of each other.

:class:`bus_agent.cycle.cycle.Cycle` is assembled from parts, each a mixin over
:class:`CycleBase` in its own module: start-up (:mod:`.startup`), commands and reflexes
(:mod:`.commands`), AL state and lost/found slaves (:mod:`.slaves`), NMT (:mod:`.nmt`), motion
(:mod:`.motion`), and the loop itself (:mod:`.cycle`). All of it runs in the cycle thread except
the documented thread-safe doors of ``Cycle``.
"""

from __future__ import annotations

import collections
import socket
import threading
import time
from array import array
from typing import TYPE_CHECKING, Callable, Sequence

from bus_agent.bus.base import ALState, Bus, SlaveALStatus, SlaveInfo
from bus_agent.bus.dc import DcSync
from bus_agent.config import AgentConfig
from bus_agent.cycle.drive import Drive, NmtRun
from bus_agent.cycle.found import FoundConfirmation
from bus_agent.cycle.groups import Groups
from bus_agent.cycle.management import AL_POLL_MIN_CYCLES, Management
from bus_agent.cycle.recorder import Recorder
from bus_agent.motion.axis import Finished
from bus_agent.runtime import (AgentCommand, CycleEvent, CycleSnapshot, CycleStats, DriveCommand, DriveSnapshot,
                               Outcome)

#: Periods kept for p50/p99/max (one statistics window), and how often they are recomputed.
STATS_WINDOW = 1000
STATS_EVERY = 250
#: Bounded inbox: submit() returns False beyond this many waiting commands.
INBOX_MAX = 256
#: Spin (busy-wait) at most this long before a deadline; sleep before that. time.sleep overshoots
#: by ~50-100 us on Linux with the default 50 us timer slack, so the spin absorbs it.
SPIN_NS = 150_000
#: The adaptive spin (``Cycle.spin_ns = None``): the SPIN_QUANTILE of the sleep's overshoot over
#: the last STATS_WINDOW sleeps plus SPIN_MARGIN_NS, at least SPIN_MIN_NS and at most SPIN_NS,
#: recomputed every STATS_EVERY cycles, and raised at once past a sleep that overshot it. The
#: quantile is that of the jitter figure kept (p99.9): about one cycle in a thousand may start
#: late, as with a fixed spin that the overshoot's tail exceeds. A quiet host wakes the thread
#: (1 ns timer slack) within tens of us, so part of the 150 us of spinning (15 % of a core at
#: 1 kHz) is saved; a loaded one keeps it at SPIN_NS. docs/agent-cycle.md, Timing.
SPIN_MIN_NS = 10_000
SPIN_MARGIN_NS = 10_000
SPIN_QUANTILE = 0.999


class CycleBase:
    """The cycle's state (created here) and the cross-part calls (declared for the type checker)."""

    def __init__(self, bus: Bus, config: AgentConfig, clock_ns: Callable[[], int] = time.monotonic_ns, *,
                 sleep: Callable[[float], None] = time.sleep, wall_ns: Callable[[], int] = time.time_ns,
                 manage_gc: bool = True, switch_interval_s: float | None = 0.0005,
                 record_periods: int = 0, rt_priority: int = 0) -> None:
        self.bus = bus
        self.config = config
        self.clock_ns = clock_ns
        self._sleep = sleep
        self._wall_ns = wall_ns
        self.period_ns = config.cycle_us * 1000
        self.manage_gc = manage_gc
        self.switch_interval_s = switch_interval_s
        #: SCHED_FIFO priority of the cycle thread (0: normal scheduling). Needs CAP_SYS_NICE.
        self.rt_priority = rt_priority
        #: Called with each CycleSnapshot from the cycle thread; must only enqueue.
        self.snapshot_sink: Callable[[CycleSnapshot], None] | None = None
        #: Called (group, reason) from the cycle thread when a local member triggers a group.
        self.group_sink: Callable[[str, str], None] | None = None
        self.latest: CycleSnapshot | None = None
        self._drive_snaps: tuple[DriveSnapshot, ...] = ()
        self._snap_list: list[DriveSnapshot | None] = []   # each drive's snapshot, by Drive.index
        self.state = "starting"            # schemas.messages.AGENT_STATES
        self.slaves: list[SlaveInfo] = []
        self.drives: list[Drive] = []
        self._by_axis: dict[str, Drive] = {}
        self.groups = Groups(config.host, config.groups, ())
        self._inbox: collections.deque[DriveCommand | AgentCommand] = collections.deque()
        self._inbox_lock = threading.Lock()
        self._triggers: collections.deque[tuple[str, str]] = collections.deque(maxlen=INBOX_MAX)
        #: Apply a remote group trigger at once in an express exchange (see ``Cycle._express``)
        #: rather than at the next deadline; False: the next cycle applies it, as before.
        self.express_reflex = True
        #: The sleep before this cycle found the trigger socket empty when it timed out.
        self._socket_watched = False
        #: eventfd the cycle thread's sleep waits on; ``trigger_group`` writes it (-1: plain sleep,
        #: e.g. with an injected clock, or before ``start``).
        self._wake_fd = -1
        self._wake_lock = threading.Lock()
        #: Group triggers as datagrams, read by the cycle thread (``Cycle.trigger_socket``).
        self._trigger_sock: socket.socket | None = None
        #: Events of express reflexes since the last cycle, for the flight recorder's triggers.
        self._express_events: list[CycleEvent] = []
        self.express_exchanges = 0
        self._events: list[CycleEvent] = []
        # Optional bus hooks (CANopen and pysoem, bus.emergency.EmergencyLog): emergencies as
        # (slave, error code, register, text), the text of the last one per slave as {slave: (error
        # code, text)}; a bus with mailboxes (pysoem) has the management thread read them.
        self._take_emergencies: Callable[[], list[tuple[int, int, int, str]]] | None = \
            getattr(bus, "take_emergencies", None)
        self._error_texts: dict[int, tuple[int, str]] = getattr(bus, "error_texts", {})
        self._reads_mailbox = getattr(bus, "poll_mailbox", None) is not None
        self._lost_origins: list[tuple[str, str]] = []
        self._ordered_stop = True
        self._desired_al: dict[int, ALState] = {}
        self._al_status: list[SlaveALStatus] = []
        self._nmt: NmtRun | None = None
        self._thread: threading.Thread | None = None
        self._stop_requested = threading.Event()
        self._stopped = threading.Event()
        self._stop_lock = threading.Lock()
        self._stopping_since_ns = 0
        self._stop_deadline_ns = 0
        self._opened = False
        self._closed = False
        self.error: BaseException | None = None
        # statistics
        self.cycles = 0
        #: Drive steps made in full so far (at most cycles x drives; the fast path skips the rest).
        self.drives_stepped = 0
        self.overruns = 0
        self.wkc_errors = 0
        self._last_wkc = 0
        self._periods = array("q", bytes(8 * STATS_WINDOW))
        self._period_max_ns = 0
        self._last_start_ns = 0
        self._stats = CycleStats(cycle_us=config.cycle_us)
        self._last_al_poll = -AL_POLL_MIN_CYCLES
        self._al_poll_ok = True
        self._al_ticket = 0
        self._wkc_was_bad = False
        self._no_answer_since: dict[int, int] = {}
        self._epoch: dict[int, int] = {}
        self._found = FoundConfirmation()
        self._mgmt = Management(bus, clock_ns, self.period_ns, config.host)
        self._dc: DcSync | None = None
        self._dc_time: Callable[[], int] = lambda: 0
        self._dc_ref: Drive | None = None  # the drive whose slave is the reference clock, if any
        self._dc_adjust_ns = 0
        #: How late the running cycle started after its deadline (ns; 0 for tick()).
        self._late_ns = 0
        self._dc_offsets = array("q", bytes(8 * STATS_WINDOW))
        self.dc_states: tuple[str, ...] = ()
        #: Spin before each deadline (ns): None adapts it to the sleep's overshoot (SPIN_MIN_NS ..
        #: SPIN_NS), a number fixes it (0: none). Default: a real-time cycle thread (rt_priority)
        #: spins the fixed SPIN_NS (jitter first), a normal one adapts (CPU first: the demo, a
        #: laptop); bench/bench_idle.py compares them (docs/agent-cycle.md, Timing).
        self.spin_ns: int | None = SPIN_NS if rt_priority else None
        #: False: the spin is made only while a period's jitter can matter (some drive in
        #: :data:`~bus_agent.cycle.drive.ARMED_STATES`, asked to go up, or moving; SYNC0 running);
        #: with every drive off the loop only sleeps (``[cycle] spin_at_rest``).
        self.spin_at_rest = False
        #: Indices of the drives that make the spin matter (maintained for the drives stepped).
        self._armed: set[int] = set()
        self._spin_auto_ns = SPIN_NS       # until the first sleeps are measured
        self._oversleep = array("q", bytes(8 * STATS_WINDOW))
        #: Optional full record of periods (ns) for benchmarks: ``record_periods`` slots.
        self.period_log = array("q", bytes(8 * record_periods)) if record_periods else None
        self.period_log_len = 0
        #: Optional record of frame-to-SYNC0 offsets (ns), beside period_log (benchmarks).
        self.dc_log: array | None = None
        #: The flight recorder (created in :meth:`open`; None when ``[recorder] seconds = 0``).
        self.recorder: Recorder | None = None
        #: Skip the per-drive work of drives at rest (docs/agent-cycle.md, "Fast paths"); False:
        #: every drive is stepped in full every cycle (tests compare both).
        self.fast_paths = True
        self._inputs_changed: Callable[[], Sequence[int] | None] | None = getattr(bus, "inputs_changed", None)
        #: Indices of the drives that are not at rest: stepped every cycle (see Cycle._at_rest).
        self._busy: set[int] = set()
        self._drives_of_slave: dict[int, tuple[int, ...]] = {}
        self._all_op_wanted: bool | None = None   # cached while no NMT command runs
        self._express_seen = 0                     # express_exchanges at the last cycle

    if TYPE_CHECKING:  # implemented by the parts (mixins) of Cycle
        def _event(self, axis: str, kind: str, detail: str = "", *, from_state: str = "unknown",
                   to_state: str = "unknown", error_code: int = 0, request_id: str = "") -> None: ...

        def _reply(self, d: Drive, cmd: DriveCommand, outcome: str, reason: str, now_ns: int, start_ns: int,
                   start_cycle: int | None = None, duration_s: float = 0.0) -> None: ...

        def _resolve(self, d: Drive, outcome: str, reason: str, now_ns: int) -> None: ...

        @staticmethod
        def _outcome(cmd: DriveCommand | AgentCommand, outcome: Outcome) -> None: ...

        def _refusal(self, d: Drive) -> str: ...

        def _motion_abort(self, d: Drive, reason: str, now_ns: int, *, drop: bool = False) -> None: ...

        def _motion_command(self, d: Drive, cmd: DriveCommand, now_ns: int) -> None: ...

        def _motion_finished(self, d: Drive, ended: Sequence[Finished], now_ns: int) -> None: ...

        def _group_move(self, cmd: DriveCommand, now_ns: int) -> None: ...

        def _update_recover_set(self) -> None: ...

        def _confirm_found(self, wkc: int, now_ns: int) -> bool: ...

        def _finish_nmt(self, outcome: str, reason: str, now_ns: int) -> None: ...

        def _close_bus(self) -> None: ...

        def _drive_snapshots(self, work: Sequence[Drive] | None = None) -> tuple[DriveSnapshot, ...]: ...

        def _take_trigger_datagrams(self) -> None: ...

        def _apply_agent(self, cmd: AgentCommand, now_ns: int) -> None: ...
