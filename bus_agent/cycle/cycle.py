"""The agent's cyclic loop: process data, CiA 402 controllers, group reflexes, commands, snapshots.

Only this module (its thread) touches the bus and the drive controllers. The gateway talks to it
through three thread-safe doors and one callback:

- :meth:`Cycle.submit` -- a validated ``DriveCommand``/``AgentCommand`` into a bounded inbox;
  applied at the next cycle start; every addressed axis later gets exactly one ``Outcome``.
- :meth:`Cycle.trigger_group` -- a group triggered on another host; local members react.
- :attr:`Cycle.snapshot_sink` -- called with one immutable ``CycleSnapshot`` per cycle (must only
  enqueue); :attr:`Cycle.latest` holds the last one for pulls.
- :attr:`Cycle.group_sink` -- called ``(group, reason)`` when a *local* member faults or is lost,
  so the gateway can carry the trigger to the other hosts (must only enqueue).

One cycle (``_cycle``): exchange -> working counter check -> management reports (AL status,
lost/found) -> commands and remote triggers -> group reflexes -> step every controller -> write
outputs -> pending-command deadlines -> snapshot. Everything that can block on a slave (AL status
reads, AL state requests, recovery of a lost slave with its SDOs) runs in a separate management
thread (:class:`bus_agent.cycle.management.Management`) while the cycle keeps exchanging process data; the cycle only posts
requests to it and reads its reports. Timing: drift-free deadlines ``t0 + k * period`` from a
monotonic clock; sleep coarse, spin the last :data:`SPIN_NS`; a cycle that starts more than one
period late counts as an overrun and the schedule skips the missed slots (no burst of catch-up
cycles). See docs/agent-cycle.md for the decisions (outcomes, NMT, shutdown, GC).
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import logging
import sys
import threading
import time
from array import array
from dataclasses import dataclass, field
from typing import Callable, Sequence

from bus_agent.bus.base import ALState, Bus, BusError, SlaveALStatus, SlaveInfo, al_status_text
from bus_agent.bus.dc import DcSync
from bus_agent.bus.mapping import SlaveSetup
from bus_agent.cia402.controller import (DISABLED_IN_FAULT, ControllerConfig, ControllerEvent, DriveController, EventKind,
                                         Goal)
from bus_agent.cia402.states import Mode, State, decode_statusword
from bus_agent.config import AgentConfig, ConfigError, DriveConfig
from bus_agent.cycle.groups import Groups
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.cycle.management import AL_POLL_MIN_CYCLES, RECOVER_EVERY_CYCLES, Management, SdoJob
from bus_agent.cycle.motion import MotionMixin, following_error
from bus_agent.motion.axis import MOTION_OPS, AxisMotion
from bus_agent.cycle.realtime import helper_priority, set_thread_fifo
from bus_agent.cycle.recorder import Recorder, RecordingData, RecordingUnavailable
from bus_agent.runtime import (AgentCommand, CycleEvent, CycleSnapshot, CycleStats, DriveCommand,
                               DriveSnapshot, Outcome)

log = logging.getLogger(__name__)

#: Spin (busy-wait) this long before a deadline; sleep before that. time.sleep overshoots by
#: ~50-100 us on Linux, so the spin absorbs it.
SPIN_NS = 150_000
#: Bounded inbox: submit() returns False beyond this many waiting commands.
INBOX_MAX = 256
#: Periods kept for p50/p99/max (one statistics window), and how often they are recomputed.
STATS_WINDOW = 1000
STATS_EVERY = 250
#: A slave that does not answer the AL status read is lost only when it still does not answer
#: this many cycles later (a later poll): a few dropped or late frames are not a lost slave.
NO_ANSWER_CONFIRM_CYCLES = 8

#: (pending command kind, controller event) -> (terminal outcome, reason when the event has none).
OUTCOME_OF_EVENT: dict[tuple[str, EventKind], tuple[str, str]] = {
    ("goal", EventKind.GOAL_REACHED): ("done", ""),
    ("goal", EventKind.GOAL_FAILED): ("failed", "goal failed"),
    ("goal", EventKind.GOAL_TIMEOUT): ("timeout", "transition deadline passed"),
    ("mode", EventKind.MODE_CONFIRMED): ("done", ""),
    ("mode", EventKind.MODE_REJECTED): ("rejected", "mode not supported (0x6502)"),
    ("mode", EventKind.MODE_TIMEOUT): ("timeout", "0x6061 did not echo the mode"),
    ("fault_reset", EventKind.FAULT_RESET_DONE): ("done", ""),
    ("fault_reset", EventKind.FAULT_RESET_FAILED): ("failed", "fault reset retries exhausted"),
}

GOAL_OF_OP = {
    "enable": Goal.ENABLED,
    "switch_on": Goal.SWITCHED_ON,
    "shutdown": Goal.READY,
    "disable": Goal.DISABLED,
    "quick_stop": Goal.QUICK_STOP,
}
#: Goals that move a drive towards torque; withdrawn when nobody waits for them any more.
_UPWARD_GOALS = (Goal.READY, Goal.SWITCHED_ON, Goal.ENABLED)
_FAULT_STATES = (State.FAULT, State.FAULT_REACTION_ACTIVE)
#: States in which a drive counts as down for the ordered shutdown.
_DOWN_STATES = (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT)
NMT_TARGET = {"start": ALState.OP, "stop": ALState.SAFEOP, "preop": ALState.PREOP,
              "reset_comm": ALState.PREOP, "reset_node": ALState.OP}
_VALID_MODES = frozenset(int(m) for m in Mode)
SUPPORTED_DRIVE_MODES = 0x6502
_MODE_UNWRITTEN = -129  # no i8: the first cycle writes 0x6060 by SDO
_CSX_MODES = (int(Mode.CYCLIC_SYNC_POSITION), int(Mode.CYCLIC_SYNC_VELOCITY), int(Mode.CYCLIC_SYNC_TORQUE))


def decode_supported_modes(bits: int) -> frozenset[int]:
    """The modes of operation set in a 0x6502 (supported drive modes) value."""
    return frozenset(int(m) for m in Mode if bits >> m.supported_bit & 1)


class IdentityMismatch(BusError):
    """A slave's 0x1018 identity is not the configured one; start-up stops."""


@dataclass(slots=True)
class _Pending:
    cmd: DriveCommand
    kind: str                 # "goal" | "mode" | "fault_reset"
    start_cycle: int
    start_ns: int
    deadline_ns: int


@dataclass(slots=True)
class _Drive:
    cfg: DriveConfig
    axis: str
    slave: int
    ctrl: DriveController
    motion: AxisMotion
    out: DriveOutputs = field(default_factory=DriveOutputs)
    inputs: DriveInputs = field(default_factory=DriveInputs)
    state: State = State.UNKNOWN
    controlword: int = 0
    lost: bool = False
    al: SlaveALStatus = SlaveALStatus(ALState.NONE, False, 0)
    pending: _Pending | None = None
    target_position: int = 0
    target_velocity: int = 0
    target_torque: int = 0
    # auto reset bookkeeping
    fault_since_ns: int = 0
    last_fault_ns: int = 0
    auto_attempts: int = 0
    auto_exhausted: bool = False
    # objects the drive does not map (see docs/agent-cycle.md, "Real drives")
    absent: tuple[str, ...] = ()        # actual values not mapped: reported absent
    object_names: tuple[str, ...] = ()  # other mapped input objects
    sdo_mode: bool = False              # 0x6060 not in the RxPDO: written by SDO
    sdo_mode_display: bool = False      # 0x6061 not in the TxPDO: read by SDO
    sdo_error_code: bool = False        # 0x603F not in the TxPDO: read by SDO on a fault
    mode_written: int = 0
    mode_display_sdo: int = 0
    error_code_sdo: int = 0
    dc: str = "none"                    # DC state of the slave (bus dc_states)


@dataclass(slots=True)
class _Nmt:
    cmd: AgentCommand
    command: str
    slaves: tuple[int, ...]
    phase: str                # "bring_down" | "to_init" | "to_target" | "recover"
    start_cycle: int
    start_ns: int
    deadline_ns: int
    down_deadline_ns: int
    note: str = ""
    ticket: int = 0           # AL status must be read after this management request


class Cycle(MotionMixin):
    """The cyclic process-data loop of one bus agent.

    ``Cycle(bus, config, clock_ns=time.monotonic_ns)``; :meth:`open` brings the segment to OP
    (identity checked), :meth:`start` runs the loop in its own thread, :meth:`stop` performs the
    ordered shutdown. :meth:`tick` runs one cycle synchronously (tests, tools; not while the
    thread runs). Not re-startable after stop.
    """

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
        self.state = "starting"            # schemas.messages.AGENT_STATES
        self.slaves: list[SlaveInfo] = []
        self.drives: list[_Drive] = []
        self._by_axis: dict[str, _Drive] = {}
        self.groups = Groups(config.host, config.groups, ())
        self._inbox: collections.deque[DriveCommand | AgentCommand] = collections.deque()
        self._inbox_lock = threading.Lock()
        self._triggers: collections.deque[tuple[str, str]] = collections.deque(maxlen=INBOX_MAX)
        self._events: list[CycleEvent] = []
        # Optional bus hooks (the CANopen backend): EMCY frames as (slave, error code, register,
        # text), and the text of the last emergency per slave as {slave: (error code, text)}.
        self._take_emergencies: Callable[[], list[tuple[int, int, int, str]]] | None = \
            getattr(bus, "take_emergencies", None)
        self._error_texts: dict[int, tuple[int, str]] = getattr(bus, "error_texts", {})
        self._lost_origins: list[tuple[str, str]] = []
        self._ordered_stop = True
        self._desired_al: dict[int, ALState] = {}
        self._al_status: list[SlaveALStatus] = []
        self._nmt: _Nmt | None = None
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
        self._mgmt = Management(bus, clock_ns, self.period_ns, config.host)
        self._dc: DcSync | None = None
        self._dc_time: Callable[[], int] = lambda: 0
        self._dc_adjust_ns = 0
        self._dc_offsets = array("q", bytes(8 * STATS_WINDOW))
        self.dc_states: tuple[str, ...] = ()
        #: Optional full record of periods (ns) for benchmarks: ``record_periods`` slots.
        self.period_log = array("q", bytes(8 * record_periods)) if record_periods else None
        self.period_log_len = 0
        #: Optional record of frame-to-SYNC0 offsets (ns), beside period_log (benchmarks).
        self.dc_log: array | None = None
        #: The flight recorder (created in :meth:`open`; None when ``[recorder] seconds = 0``).
        self.recorder: Recorder | None = None

    # ---- lifecycle --------------------------------------------------------------------------

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(d.axis for d in self.drives)

    def open(self) -> list[SlaveInfo]:
        """Open the bus, check every configured identity (0x1018), map PDOs and reach OP.

        Raises IdentityMismatch / BusError / ConfigError; on error the bus is closed. Not cycle-safe
        (blocking, seconds)."""
        if self._opened:
            return self.slaves
        try:
            self.slaves = list(self.bus.open())
            configs = self.config.drive_configs(len(self.slaves))
            for dc in configs:
                info = self.slaves[dc.slave]
                ident = info.identity
                if dc.identity is not None and not dc.identity.matches(ident.vendor_id, ident.product_code,
                                                                     ident.revision):
                    raise IdentityMismatch(
                        f"slave {dc.slave} ({info.name!r}, axis {dc.axis!r}): identity vendor 0x{ident.vendor_id:08X} "
                        f"product 0x{ident.product_code:08X} revision 0x{ident.revision:08X} does not match the "
                        f"configured {dc.identity}")
                if dc.identity is None:
                    log.info("slave %d (%s) axis %s: identity not configured, accepting vendor 0x%08X product 0x%08X",
                             dc.slave, info.name, dc.axis, ident.vendor_id, ident.product_code)
            overrides = {k: v for k, v in self._slave_setups(configs).items() if v != SlaveSetup()}
            self.bus.start(overrides or None)
            supported = {dc.slave: self._read_supported_modes(dc) for dc in configs}
            for dc in configs:
                pol = dc.policy
                cc = ControllerConfig(transition_timeout_s=pol.transition_timeout_s,
                                      fault_reset_retries=pol.fault_reset_retries, mode_timeout_s=pol.transition_timeout_s)
                d = _Drive(cfg=dc, axis=dc.axis, slave=dc.slave,
                           ctrl=DriveController(cc, mode=dc.mode, supported_modes=supported[dc.slave]),
                           motion=AxisMotion(dc.motion, self.period_ns / 1e9))
                self._unmapped_objects(d)
                self.drives.append(d)
        except BaseException:
            self.state = "error"
            self._close_bus()
            raise
        self._by_axis = {d.axis: d for d in self.drives}
        self._start_dc()
        self._desired_al = {i: ALState.OP for i in range(len(self.slaves))}
        self._al_status = [SlaveALStatus(ALState.OP, False, 0)] * len(self.slaves)
        for d in self.drives:
            d.al = self._al_status[d.slave]
        self.groups = Groups(self.config.host, self.config.groups, self.axes)
        rc = self.config.recorder
        if rc.seconds:
            self.recorder = Recorder(self.axes, self.config.cycle_us, rc.seconds, rc.pre_s, rc.post_s,
                                     wall_ns=self._wall_ns, mono_ns=self.clock_ns)
        self._stats = CycleStats(cycle_us=self.config.cycle_us, expected_wkc=self.bus.expected_wkc)
        self._opened = True
        self.state = "running"
        log.info("host %s: %d slave(s) in OP, %d drive(s) %s, expected working counter %d",
                 self.config.host, len(self.slaves), len(self.drives), ",".join(self.axes), self.bus.expected_wkc)
        return self.slaves

    def _slave_setups(self, configs: Sequence[DriveConfig]) -> dict[int, SlaveSetup]:
        """Mapping policy, start-up SDOs and SYNC0 per slave. ``[dc] mode = "auto"``: SYNC0 at the
        cycle time for DC-capable slaves whose mode is cyclic synchronous (8/9/10)."""
        dcc = self.config.dc
        capable = getattr(self.bus, "dc_capable", None)
        out = {}
        for dc in configs:
            s0 = None
            if dcc.mode == "auto" and capable is not None and dc.mode in _CSX_MODES and capable(dc.slave):
                s0 = (dcc.sync0_cycle_ns or self.period_ns, dcc.sync0_shift_ns)
            out[dc.slave] = dataclasses.replace(dc.setup, sync0=s0, sync0_before_safeop=dcc.before_safeop and s0 is not None)
        return out

    def _start_dc(self) -> None:
        """After start(): the PI that keeps the cycle in step with SYNC0, per-slave DC states."""
        states = getattr(self.bus, "dc_states", None)
        if states is None:
            return
        st = states()
        self.dc_states = tuple(st)
        for d in self.drives:
            d.dc = st[d.slave]
        if getattr(self.bus, "dc_active", False):
            dcc = self.config.dc
            self._dc = DcSync(dcc.sync0_cycle_ns or self.period_ns, dcc.sync0_shift_ns, dcc.target_fraction)
            self._dc_time = self.bus.dc_time_ns  # type: ignore[attr-defined]

    def _unmapped_objects(self, d: _Drive) -> None:
        """From the drive's codec: which objects are served by SDO and which are absent."""
        codec_of = getattr(self.bus, "codec", None)
        if codec_of is None:
            return  # a backend with the fixed default layout (sim)
        codec = codec_of(d.slave)
        d.absent = tuple(f for f in codec.absent_inputs if f in ("position", "velocity", "torque"))
        d.object_names = codec.extra_names
        d.sdo_mode = (0x6060, 0) not in codec.mapped_outputs
        d.sdo_mode_display = (0x6061, 0) not in codec.mapped_inputs
        d.sdo_error_code = (0x603F, 0) not in codec.mapped_inputs
        # No SDO here: the slaves are in OP and the loop does not run yet (SM watchdog). The
        # first cycle writes the configured mode (0x6060) by SDO and reads 0x6061 back.
        d.mode_written = _MODE_UNWRITTEN
        served = [n for n, f in (("0x6060", d.sdo_mode), ("0x6061", d.sdo_mode_display), ("0x603F", d.sdo_error_code)) if f]
        if served or d.absent:
            log.info("axis %s (slave %d): not mapped, served by SDO: %s; absent: %s", d.axis, d.slave,
                     ", ".join(served) or "none", ", ".join(d.absent) or "none")

    def _read_supported_modes(self, d: DriveConfig) -> frozenset[int] | None:
        """0x6502 (supported drive modes) by SDO; None (any mode tried) when the drive has no
        0x6502 or the read fails. Raises ConfigError when the configured mode is not supported."""
        sdo_read = getattr(self.bus, "sdo_read", None)
        if sdo_read is None:
            return None
        # read in PRE-OP by a bus that can (no SDO between OP and the first cycle: SM watchdog)
        sdo_read = getattr(self.bus, "preop_sdo_read", sdo_read)
        try:
            raw = sdo_read(d.slave, SUPPORTED_DRIVE_MODES, 0, 4)
            if len(raw) < 1:
                raise BusError(f"slave {d.slave}: 0x6502 is empty")
            bits = int.from_bytes(bytes(raw)[:4], "little")
        except BusError as e:
            log.info("axis %s (slave %d): supported drive modes (0x6502) not available, any mode is tried: %s",
                     d.axis, d.slave, e)
            return None
        modes = decode_supported_modes(bits)
        log.info("axis %s (slave %d): 0x6502 = 0x%08X, modes %s", d.axis, d.slave, bits, sorted(modes))
        if d.mode not in modes:
            raise ConfigError(f"axis {d.axis!r} (slave {d.slave}): configured mode {d.mode} (0x6060) is not "
                              f"supported by the drive (0x6502 = 0x{bits:08X}: modes {sorted(modes)})")
        return modes

    def start(self) -> None:
        """Open (if not yet) and run the loop in its own thread, and the management thread
        (AL status, AL requests, recovery). Returns once the threads run."""
        if self._thread is not None:
            return
        # GC settings first: a full collection between OP and the first cycle could outlast the
        # slaves' SM watchdog (100 ms) in a large process
        self._prepare_process()
        try:
            self.open()
        except BaseException:
            self._restore_process()
            raise
        self._mgmt.rt_priority = helper_priority(self.rt_priority)
        self._mgmt.start()
        if self.recorder is not None:
            self.recorder.start()
        self._thread = threading.Thread(target=self._run, name=f"cycle-{self.config.host}", daemon=True)
        self._thread.start()

    def stop(self, ordered: bool = True, timeout_s: float | None = None) -> None:
        """Ordered shutdown: every drive to goal DISABLED (seed order: disable operation 0x0007,
        shutdown 0x0006, disable voltage 0x0000), wait until all are down or ``timeout_s``
        (default: the longest transition timeout), then AL INIT and close. Idempotent.
        ``ordered=False`` skips the drive sequence (the SM watchdog of each slave stops the drives)."""
        with self._stop_lock:
            if self._closed:
                return
            if timeout_s is None:
                timeout_s = max([d.cfg.policy.transition_timeout_s for d in self.drives] or [5.0])
            if self._thread is not None and self._thread.is_alive():
                self._begin_stop(ordered, timeout_s)
                self._thread.join(timeout_s + 5.0)
                if self._thread.is_alive():
                    log.error("host %s: cycle thread did not stop", self.config.host)
                    return
            elif self._opened and self.state in ("running", "stopping"):
                self._begin_stop(ordered, timeout_s)
                while not self._stop_done():
                    self.tick()
                self._finish_stop()
            self._close_bus()

    def _begin_stop(self, ordered: bool, timeout_s: float) -> None:
        self._ordered_stop = ordered
        self._stop_deadline_ns = self.clock_ns() + int(timeout_s * 1e9) if ordered else 0
        self._stop_requested.set()

    def _stop_done(self) -> bool:
        if self.state != "stopping":
            return False
        if self.clock_ns() >= self._stop_deadline_ns:
            return True
        return all(d.lost or d.state in _DOWN_STATES for d in self.drives)

    def _finish_stop(self) -> None:
        self._mgmt.stop()  # the bus is the cycle's alone from here
        not_down = [f"{d.axis}={d.state.value}" for d in self.drives if not d.lost and d.state not in _DOWN_STATES]
        if not_down and self._ordered_stop:
            log.warning("host %s: ordered shutdown deadline passed with drives not down: %s",
                        self.config.host, ", ".join(not_down))
        try:
            self.bus.request_al_state(None, ALState.INIT)
        except Exception as e:  # closing anyway
            log.warning("host %s: AL INIT request failed: %s", self.config.host, e)
        self.state = "stopped"

    def _close_bus(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._mgmt.stop()
        if self.recorder is not None:
            self.recorder.stop()
        try:
            self.bus.close()
        except Exception as e:
            log.warning("host %s: bus close failed: %s", self.config.host, e)
        if self.state != "error":
            self.state = "stopped"
        self._stopped.set()

    # ---- doors for the gateway (thread-safe) --------------------------------------------------

    def submit(self, cmd: DriveCommand | AgentCommand) -> bool:
        """Queue a validated command for the next cycle start. False when the inbox is full or
        the agent is not running (the caller answers busy/rejected). Thread-safe, non-blocking."""
        if self.state != "running" or self._stop_requested.is_set():
            return False
        with self._inbox_lock:
            if len(self._inbox) >= INBOX_MAX:
                return False
            self._inbox.append(cmd)
        return True

    def trigger_group(self, group: str, reason: str) -> None:
        """A member of ``group`` faulted or was lost on another host: local members react at the
        next cycle (the configured reflex). Thread-safe."""
        self._triggers.append((group, reason))

    def stats(self) -> CycleStats:
        return self._stats

    def recording(self, what: str = "last", last_s: float = 10.0, timeout_s: float = 5.0) -> RecordingData:
        """A flight recording (``Recorder.fetch``); raises RecordingUnavailable. Thread-safe, not
        for the cycle thread (``what='now'`` blocks until the window after the trigger is recorded)."""
        if self.recorder is None:
            raise RecordingUnavailable(f"the flight recorder of {self.config.host} is off ([recorder] seconds = 0)")
        return self.recorder.fetch(what, last_s, timeout_s)

    # ---- the loop -------------------------------------------------------------------------------

    def _prepare_process(self) -> None:
        """Process-wide settings while the loop runs (restored when it ends); see docs/agent-cycle.md."""
        self._old_switch = sys.getswitchinterval()
        self._gc_was_enabled = gc.isenabled()
        if self.switch_interval_s:
            # A thread waiting for the GIL asks for it after this long (default 5 ms): the cycle
            # thread waits at most about this long when another thread holds the GIL.
            sys.setswitchinterval(self.switch_interval_s)
        if self.manage_gc:
            # No cyclic-GC pauses in the loop: move what exists to the permanent generation and
            # disable collection while running (reference counting still frees everything acyclic).
            gc.collect()
            gc.freeze()
            gc.disable()

    def _restore_process(self) -> None:
        if self.manage_gc:
            gc.unfreeze()
            if self._gc_was_enabled:
                gc.enable()
        if self.switch_interval_s:
            sys.setswitchinterval(self._old_switch)

    def _run(self) -> None:
        if not hasattr(self, "_old_switch"):
            self._prepare_process()
        set_thread_fifo(self.rt_priority, f"the cycle thread of {self.config.host}")
        try:
            period = self.period_ns
            t0 = self.clock_ns()
            k = 0
            while True:
                deadline = t0 + k * period + self._dc_adjust_ns
                now = self.clock_ns()
                if now < deadline:
                    self._wait_until(deadline)
                    now = self.clock_ns()
                if now - deadline > period:
                    self.overruns += 1
                    k = (now - t0) // period  # skip the missed slots: no catch-up burst
                self._cycle(now)
                k += 1
                if self._stop_requested.is_set() and self.state == "running":
                    self._enter_stopping(now)
                if self.state == "stopping" and self._stop_done():
                    self._finish_stop()
                    break
        except BaseException as e:  # the loop must not die silently
            self.error = e
            self.state = "error"
            log.exception("host %s: cycle thread failed", self.config.host)
            self._mgmt.stop()
            try:
                self.bus.request_al_state(None, ALState.INIT)
            except Exception:
                pass
        finally:
            self._restore_process()

    def _wait_until(self, deadline_ns: int) -> None:
        remaining = deadline_ns - self.clock_ns() - SPIN_NS
        if remaining > 0:
            self._sleep(remaining / 1e9)
        while self.clock_ns() < deadline_ns:
            pass

    def tick(self) -> CycleSnapshot:
        """Run one cycle now (tests and tools; never while the thread runs). Returns its snapshot."""
        now = self.clock_ns()
        if self._stop_requested.is_set() and self.state == "running":
            self._enter_stopping(now)
        self._cycle(now)
        assert self.latest is not None
        return self.latest

    def _enter_stopping(self, now_ns: int) -> None:
        self.state = "stopping"
        self._drain_inbox_rejecting("agent stopping", now_ns)
        if self._nmt is not None:
            self._finish_nmt("failed", "agent stopping", now_ns)
        if self._ordered_stop:
            for d in self.drives:
                if d.pending is not None:
                    self._resolve(d, "failed", "agent stopping", now_ns)
                self._motion_abort(d, "agent stopping", now_ns)
                d.ctrl.set_halt(False)
                d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        log.info("host %s: ordered shutdown of %d drive(s)", self.config.host, len(self.drives))

    # ---- one cycle --------------------------------------------------------------------------------

    def _cycle(self, now_ns: int) -> None:
        """One cycle. Cycle thread only."""
        self.cycles += 1
        cycle = self.cycles
        if self._last_start_ns:
            p = now_ns - self._last_start_ns
            self._periods[cycle % STATS_WINDOW] = p
            if p > self._period_max_ns:
                self._period_max_ns = p
            if self.period_log is not None and self.period_log_len < len(self.period_log):
                self.period_log[self.period_log_len] = p
                self.period_log_len += 1
        period_ns = now_ns - self._last_start_ns if self._last_start_ns else 0
        self._last_start_ns = now_ns
        now_s = now_ns / 1e9
        events = self._events = []
        bus = self.bus

        wkc = bus.exchange()
        self._last_wkc = wkc
        dcs = self._dc
        if dcs is not None and wkc > 0:
            # keep the cycle in step with SYNC0: PI on the frame's phase (bus_agent.bus.dc)
            self._dc_adjust_ns += dcs.step(self._dc_time())
            self._dc_offsets[cycle % STATS_WINDOW] = dcs.offset_ns
            if self.dc_log is not None and 0 < self.period_log_len <= len(self.dc_log):
                self.dc_log[self.period_log_len - 1] = dcs.offset_ns
        all_op_wanted = self._nmt is None and all(s == ALState.OP for s in self._desired_al.values())
        wkc_bad = wkc != bus.expected_wkc
        if wkc_bad and all_op_wanted:
            self.wkc_errors += 1
        mgmt = self._mgmt
        if wkc_bad and self._al_poll_ok and not self._wkc_was_bad:
            mgmt.kick()  # a new working counter error: look at the AL status now
        self._wkc_was_bad = wkc_bad
        fast = wkc_bad or self._nmt is not None or not self._al_poll_ok or bool(self._no_answer_since)
        if fast != mgmt.fast:
            mgmt.fast = fast
            mgmt.wake()
        if not mgmt.threaded and not self._closed:
            mgmt.run_once(now_ns)
        if mgmt.reports:
            self._apply_reports(now_ns)

        for d in self.drives:
            i = d.inputs = bus.inputs(d.slave)
            if d.sdo_mode_display:
                i.modes_of_operation_display = d.mode_display_sdo
            if d.sdo_error_code:
                i.error_code = d.error_code_sdo
        if self._take_emergencies is not None:
            for slave, code, register, text in self._take_emergencies():
                for d in self.drives:
                    if d.slave == slave:
                        self._event(d.axis, "emcy", f"EMCY 0x{code:04X} {text} (error register 0x{register:02X})",
                                    error_code=code)

        # Reflex origins are detected on the fresh statusword, before any controller step, so the
        # other members get their new goal in this very cycle.
        origins: list[tuple[str, str]] = []
        for d in self.drives:
            if d.lost:
                continue
            st = decode_statusword(d.inputs.statusword)
            if st in _FAULT_STATES and d.state not in _FAULT_STATES:
                if d.sdo_error_code:
                    mgmt.sdo(SdoJob(d.slave, "error_code", deadline_ns=now_ns + 1_000_000_000))  # 0x603F not mapped
                for g in self.groups.of_axis(d.axis):
                    origins.append((g, f"{self.config.host}/{d.axis} fault 0x{d.inputs.error_code:04X}"))
                d.fault_since_ns = now_ns
                d.last_fault_ns = now_ns
            elif st in _FAULT_STATES:
                d.last_fault_ns = now_ns
            elif d.error_code_sdo and d.sdo_error_code:
                d.error_code_sdo = 0  # out of fault: the SDO-read 0x603F no longer applies
        for g, reason in self._lost_origins:
            origins.append((g, reason))
        self._lost_origins = []

        if self.state == "running":
            self._apply_inbox(now_ns)
        while self._triggers:
            g, reason = self._triggers.popleft()
            self._reflex(g, None, f"remote: {reason}", now_ns)
        for g, reason in origins:
            origin_axis = reason.split("/", 1)[1].split(" ", 1)[0]
            self._reflex(g, origin_axis, reason, now_ns)
            if self.group_sink is not None:
                self.group_sink(g, reason)

        for d in self.drives:
            if d.lost:
                # Outputs of a lost slave: disable voltage and hold; applied if it comes back.
                o = d.out
                o.controlword = 0
                o.target_position = d.target_position = d.inputs.position_actual
                o.target_velocity = d.target_velocity = 0
                o.target_torque = d.target_torque = 0
                d.controlword = 0
                bus.set_outputs(d.slave, o)
                continue
            self._auto_reset(d, now_ns)
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            prev = d.state
            d.state = d.ctrl.state if d.ctrl.state is not None else decode_statusword(d.inputs.statusword)
            self._motion_step(d, out.hold_target, now_ns)
            o = d.out
            o.controlword = d.controlword = out.controlword
            o.modes_of_operation = out.mode_of_operation
            if out.mode_of_operation != d.mode_written and (d.sdo_mode or d.sdo_mode_display):
                # 0x6060 or 0x6061 not mapped: written and/or read back by SDO (management thread);
                # the controller waits for the echo of 0x6061 as with PDOs
                d.mode_written = out.mode_of_operation
                mgmt.sdo(SdoJob(d.slave, "mode", out.mode_of_operation, written=not d.sdo_mode,
                                deadline_ns=now_ns + int(d.cfg.policy.transition_timeout_s * 1e9)))
            if out.hold_target:
                # CSP/CSV/CST before Operation enabled: no stale target (a jump or a following
                # error on enable). Velocity and torque are held at zero.
                d.target_position = d.inputs.position_actual
                d.target_velocity = 0
                d.target_torque = 0
            o.target_position = d.target_position
            o.target_velocity = d.target_velocity
            o.target_torque = d.target_torque
            bus.set_outputs(d.slave, o)
            if out.events:
                self._controller_events(d, out.events, prev, now_ns)

        for d in self.drives:
            pend = d.pending
            if pend is not None and now_ns >= pend.deadline_ns:
                if pend.kind == "goal" and d.ctrl.goal in _UPWARD_GOALS:
                    # Nobody waits for this goal any more: do not pursue it.
                    d.ctrl.set_goal(Goal.DISABLED, now_s)
                self._resolve(d, "timeout", f"{pend.cmd.op} not done within {pend.cmd.timeout_s:g} s", now_ns)
        if self._nmt is not None:
            self._step_nmt(now_ns)
        if cycle % RECOVER_EVERY_CYCLES == 0:
            self._update_recover_set()

        rec = self.recorder
        if rec is not None:
            rec.record(cycle, now_ns, period_ns, wkc, self.drives, events)
        if cycle % STATS_EVERY == 0:
            self._update_stats()
        snap = CycleSnapshot(cycle=cycle, time_ns=self._wall_ns(), drives=self._drive_snapshots(),
                             events=tuple(events), stats=self._stats, agent_state=self.state)
        self.latest = snap
        sink = self.snapshot_sink
        if sink is not None:
            sink(snap)

    # ---- AL state, lost and found ------------------------------------------------------------------

    def _apply_reports(self, now_ns: int) -> None:
        """Reports of the management thread, in the order they were made."""
        reports = self._mgmt.reports
        while reports:
            r = reports.popleft()
            if r[0] == "al":
                self._apply_al(r[1], r[2], now_ns)
            elif r[0] == "sdo":
                self._apply_sdo(r[1], r[2], r[3], r[4], now_ns)
            else:
                self._apply_returned(r[1], r[2], now_ns)

    def _apply_sdo(self, slave: int, what: str, value: int | None, error: str, now_ns: int) -> None:
        """A result of an SDO job (objects the drive does not map)."""
        for d in self.drives:
            if d.slave != slave:
                continue
            if what == "mode_display" and value is not None:
                d.mode_display_sdo = value
            elif what == "error_code" and value is not None:
                if value != d.error_code_sdo and d.state in _FAULT_STATES:
                    self._event(d.axis, "fault", f"0x603F = 0x{value:04X} (read by SDO: not in the PDO mapping)",
                                to_state=d.state.value, error_code=value)
                d.error_code_sdo = value
            elif what == "mode_write" and d.pending is not None and d.pending.kind == "mode":
                self._resolve(d, "failed", f"0x6060 = {d.mode_written} by SDO refused: {error}", now_ns)
            elif error:
                log.warning("axis %s: SDO %s: %s", d.axis, what, error)

    def _apply_al(self, statuses: Sequence[SlaveALStatus] | None, ticket: int, now_ns: int) -> None:
        self._last_al_poll = self.cycles
        self._al_ticket = ticket
        if statuses is None:
            statuses = [SlaveALStatus(ALState.NONE, False, 0)] * len(self.slaves)
        ok = True
        nmt_slaves = self._nmt.slaves if self._nmt is not None else ()
        for pos, st in enumerate(statuses):
            old = self._al_status[pos] if pos < len(self._al_status) else None
            if pos < len(self._al_status):
                self._al_status[pos] = st
            if old is not None and (old.state != st.state or old.error != st.error):
                for d in self.drives:
                    if d.slave == pos:
                        self._event(d.axis, "al_state", f"slave {pos} AL {old.state.wire_name} -> {st.state.wire_name}"
                                    + (" (no answer)" if st.state == ALState.NONE else "")
                                    + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else ""),
                                    error_code=st.status_code if st.error else 0)
            want = self._desired_al.get(pos, ALState.OP)
            if st.state != want or st.error:
                ok = False
            if st.state != ALState.NONE:
                self._no_answer_since.pop(pos, None)
        confirm_ns = NO_ANSWER_CONFIRM_CYCLES * self.period_ns
        lost_now = False
        for d in self.drives:
            d.al = self._al_status[d.slave]
            want = self._desired_al.get(d.slave, ALState.OP)
            gone = d.al.state != want or (d.al.error and want == ALState.OP)
            if gone and not d.lost and d.slave not in nmt_slaves:
                if d.al.state == ALState.NONE:
                    # No answer: lost only if a later read confirms it (not a dropped frame).
                    since = self._no_answer_since.setdefault(d.slave, now_ns)
                    if now_ns - since < confirm_ns:
                        continue
                self._mark_lost(d, now_ns)
                lost_now = True
        self._al_poll_ok = ok
        if lost_now:
            self._update_recover_set()

    def _mark_lost(self, d: _Drive, now_ns: int) -> None:
        st = d.al
        why = (f"slave {d.slave} AL {st.state.wire_name}"
               + (f" error 0x{st.status_code:04X} {al_status_text(st.status_code)}" if st.error else "")
               + f", working counter {self._last_wkc}/{self.bus.expected_wkc}")
        d.lost = True
        self._no_answer_since.pop(d.slave, None)
        self._epoch[d.slave] = self._epoch.get(d.slave, 0) + 1
        log.warning("drive %s/%s lost: %s", self.config.host, d.axis, why)
        self._event(d.axis, "lost", why, from_state=d.state.value, error_code=st.status_code if st.error else 0)
        if d.pending is not None:
            self._resolve(d, "failed", f"slave lost: {why}", now_ns)
        self._motion_abort(d, f"slave lost: {why}", now_ns, drop=True)
        # Never re-enabled without a new command once it returns.
        d.ctrl.set_halt(False)
        d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        for g in self.groups.of_axis(d.axis):
            self._lost_origins.append((g, f"{self.config.host}/{d.axis} lost ({why})"))

    def _update_recover_set(self) -> None:
        """Tell the management thread which slaves to bring back to OP: lost ones wanted in OP
        (while running) and those of an NMT command in its recover phase."""
        keys: set[tuple[int, int]] = set()
        if self.state == "running":
            for d in self.drives:
                if d.lost and self._desired_al.get(d.slave) == ALState.OP:
                    keys.add((d.slave, self._epoch.get(d.slave, 0)))
        n = self._nmt
        if n is not None and n.phase == "recover":
            for s in n.slaves:
                st = self._al_status[s]
                if st.state != ALState.OP or st.error:
                    keys.add((s, self._epoch.get(s, 0)))
        fs = frozenset(keys)
        if fs != self._mgmt.recover_set:
            self._mgmt.recover_set = fs
            self._mgmt.wake()

    def _apply_returned(self, slave: int, epoch: int, now_ns: int) -> None:
        """A slave of the recover set is back in OP: 'found', goal stays DISABLED."""
        if epoch != self._epoch.get(slave, 0):
            return  # lost again since that recovery began
        self._al_status[slave] = SlaveALStatus(ALState.OP, False, 0)
        self._no_answer_since.pop(slave, None)
        for other in self.drives:
            if other.slave != slave:
                continue
            other.al = self._al_status[slave]
            if other.lost:
                other.lost = False
                other.state = decode_statusword(other.inputs.statusword)
                other.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
                log.info("drive %s/%s found: slave %d back in OP, goal disabled", self.config.host, other.axis, slave)
                self._event(other.axis, "found", f"slave {slave} back in OP; goal stays disabled")
        self._update_recover_set()

    # ---- commands ----------------------------------------------------------------------------------

    def _drain_inbox_rejecting(self, reason: str, now_ns: int) -> None:
        with self._inbox_lock:
            cmds = list(self._inbox)
            self._inbox.clear()
        for cmd in cmds:
            if isinstance(cmd, AgentCommand):
                self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=reason))
            else:
                for axis in cmd.axes:
                    d = self._by_axis.get(axis)
                    self._outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=reason,
                                               state=d.state.value if d else "unknown"))

    def _apply_inbox(self, now_ns: int) -> None:
        if not self._inbox:
            return
        with self._inbox_lock:
            cmds = list(self._inbox)
            self._inbox.clear()
        for cmd in cmds:
            try:
                if isinstance(cmd, AgentCommand):
                    self._apply_agent(cmd, now_ns)
                else:
                    self._apply_drive(cmd, now_ns)
            except Exception as e:  # a bad command must not stop the loop
                log.exception("host %s: command %s failed", self.config.host, getattr(cmd, "request_id", "?"))
                if isinstance(cmd, AgentCommand):
                    self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"internal error: {e}"))

    def _refusal(self, d: _Drive) -> str:
        """Why no command can act on ``d`` now ('' if one can)."""
        if d.lost:
            return f"slave {d.slave} lost (AL {d.al.state.wire_name})"
        want = self._desired_al.get(d.slave, ALState.OP)
        if want != ALState.OP or (self._nmt is not None and d.slave in self._nmt.slaves):
            return f"slave {d.slave} not operational (AL {d.al.state.wire_name}, nmt in progress or stopped)"
        return ""

    def _apply_drive(self, cmd: DriveCommand, now_ns: int) -> None:
        now_s = now_ns / 1e9
        start_ns = cmd.received_ns or now_ns
        deadline = start_ns + int(cmd.timeout_s * 1e9)
        if cmd.op == "move" and (cmd.args.get("sync") or cmd.args.get("targets") is not None):
            self._group_move(cmd, now_ns)
            return
        seen: set[str] = set()
        for axis in cmd.axes:
            if axis in seen:
                continue
            seen.add(axis)
            d = self._by_axis.get(axis)
            if d is None:
                self._outcome(cmd, Outcome(axis=axis, outcome="rejected", reason=f"no axis {axis!r} on {self.config.host}"))
                continue
            why = self._refusal(d)
            if why:
                self._reply(d, cmd, "rejected", why, now_ns, start_ns)
                continue
            op = cmd.op
            kind = None
            if op in MOTION_OPS:
                self._motion_command(d, cmd, now_ns)
                continue
            if op in GOAL_OF_OP and GOAL_OF_OP[op] is not Goal.ENABLED:
                # Still following the profile (decelerating) until the drive leaves Operation enabled.
                self._motion_abort(d, f"{op} ({cmd.request_id})", now_ns)
            if op in GOAL_OF_OP:
                d.ctrl.set_goal(GOAL_OF_OP[op], now_s)
                kind = "goal"
            elif op == "fault_reset":
                if d.state in _FAULT_STATES or decode_statusword(d.inputs.statusword) in _FAULT_STATES:
                    d.ctrl.request_fault_reset(now_s)
                    d.auto_attempts = 0
                    kind = "fault_reset"
                else:
                    # Idempotent: the aim (no fault) holds already. See docs/agent-cycle.md.
                    self._supersede(d, cmd, now_ns)
                    self._reply(d, cmd, "done", "not in fault: nothing to reset", now_ns, start_ns)
                    continue
            elif op == "set_mode":
                mode = cmd.args.get("mode")
                if not isinstance(mode, int) or isinstance(mode, bool) or mode not in _VALID_MODES:
                    self._reply(d, cmd, "rejected", f"mode {mode!r} is not a CiA 402 mode (0x6060)", now_ns, start_ns)
                    continue
                sup = d.ctrl.supported_modes
                if sup is not None and mode not in sup:
                    # Known from 0x6502 at start-up: rejected now, nothing sent, nothing superseded.
                    self._reply(d, cmd, "rejected", f"mode {mode} ({Mode(mode).name.lower()}) is not supported by the "
                                f"drive (0x6502: modes {sorted(sup)})", now_ns, start_ns)
                    continue
                if d.motion.plan is not None:
                    self._reply(d, cmd, "rejected", f"axis in motion ({d.motion.axis_state.value}): halt or stop it "
                                "before changing the mode", now_ns, start_ns)
                    continue
                d.ctrl.request_mode(mode, now_s)
                kind = "mode"
            elif op == "halt":
                on = cmd.args.get("on", True)
                if not isinstance(on, bool):
                    self._reply(d, cmd, "rejected", f"halt 'on' must be a boolean, got {on!r}", now_ns, start_ns)
                    continue
                if on:
                    self._motion_abort(d, f"halt ({cmd.request_id})", now_ns)
                d.ctrl.set_halt(on)  # controlword bit 8, written this cycle
                self._reply(d, cmd, "done", f"halt {'on' if on else 'off'}", now_ns, start_ns)
                continue
            else:
                self._reply(d, cmd, "rejected", f"op {op!r} is not a drive command of the cycle", now_ns, start_ns)
                continue
            self._supersede(d, cmd, now_ns)
            d.pending = _Pending(cmd=cmd, kind=kind, start_cycle=self.cycles, start_ns=start_ns, deadline_ns=deadline)

    def _supersede(self, d: _Drive, cmd: DriveCommand, now_ns: int) -> None:
        if d.pending is not None:
            self._resolve(d, "failed", f"superseded by {cmd.request_id}", now_ns)

    def _reply(self, d: _Drive, cmd: DriveCommand, outcome: str, reason: str, now_ns: int, start_ns: int,
               start_cycle: int | None = None, duration_s: float = 0.0) -> None:
        o = Outcome(axis=d.axis, outcome=outcome, state=d.state.value, error_code=d.inputs.error_code,
                    reason=reason, elapsed_s=max(0.0, (now_ns - start_ns) / 1e9),
                    cycles=self.cycles - (start_cycle if start_cycle is not None else self.cycles),
                    duration_s=duration_s)
        self._event(d.axis, "outcome", f"{cmd.op} {outcome}" + (f": {reason}" if reason else ""),
                    to_state=d.state.value, error_code=d.inputs.error_code, request_id=cmd.request_id)
        self._outcome(cmd, o)

    def _resolve(self, d: _Drive, outcome: str, reason: str, now_ns: int) -> None:
        p = d.pending
        if p is None:
            return
        d.pending = None
        self._reply(d, p.cmd, outcome, reason, now_ns, p.start_ns, p.start_cycle)

    @staticmethod
    def _outcome(cmd: DriveCommand | AgentCommand, outcome: Outcome) -> None:
        try:
            cmd.on_outcome(outcome)
        except Exception:
            log.exception("on_outcome callback of %s failed", cmd.request_id)

    def _controller_events(self, d: _Drive, evs: Sequence[ControllerEvent], prev: State, now_ns: int) -> None:
        p = d.pending
        for ev in evs:
            k = ev.kind
            if k == EventKind.TRANSITION:
                self._event(d.axis, "transition", ev.reason, from_state=ev.from_state.value,
                            to_state=ev.to_state.value)
            elif k == EventKind.FAULT:
                self._event(d.axis, "fault", ev.reason or f"error code 0x{d.inputs.error_code:04X}",
                            from_state=ev.from_state.value, to_state=ev.to_state.value,
                            error_code=d.inputs.error_code)
            if p is None or d.pending is not p:
                continue
            terminal = OUTCOME_OF_EVENT.get((p.kind, k))
            if terminal is not None:
                outcome, default_reason = terminal
                if outcome == "done":
                    reason = ev.reason if ev.reason == DISABLED_IN_FAULT else ""
                else:
                    reason = ev.reason or default_reason
                self._resolve(d, outcome, reason, now_ns)

    def _auto_reset(self, d: _Drive, now_ns: int) -> None:
        a = d.cfg.policy.auto_reset
        if not a.enabled:
            return
        if d.state != State.FAULT:
            if d.auto_attempts and now_ns - d.last_fault_ns > a.window_s * 1e9:
                d.auto_attempts = 0
                d.auto_exhausted = False
            return
        if d.pending is not None:
            return
        if d.auto_attempts >= a.max_attempts:
            if not d.auto_exhausted:
                d.auto_exhausted = True
                self._event(d.axis, "warning", f"auto fault reset: {a.max_attempts} attempts exhausted, "
                            "waiting for a fault_reset command", error_code=d.inputs.error_code)
            return
        wait_s = min(a.backoff_s * (2 ** d.auto_attempts), a.backoff_max_s)
        if now_ns - d.fault_since_ns >= wait_s * 1e9:
            d.auto_attempts += 1
            d.fault_since_ns = now_ns
            d.ctrl.request_fault_reset(now_ns / 1e9)
            self._event(d.axis, "warning", f"auto fault reset attempt {d.auto_attempts}/{a.max_attempts}",
                        error_code=d.inputs.error_code)

    # ---- group reflexes ------------------------------------------------------------------------------

    def _reflex(self, group: str, origin_axis: str | None, reason: str, now_ns: int) -> None:
        goal = Goal.QUICK_STOP if self.config.reflex == "quick_stop" else Goal.DISABLED
        for axis in self.groups.reacting(group, origin_axis):
            d = self._by_axis[axis]
            if d.lost:
                continue
            if d.pending is not None:
                self._resolve(d, "failed", f"group {group} reflex: {reason}", now_ns)
            self._motion_abort(d, f"group {group} reflex: {reason}", now_ns)
            d.ctrl.set_goal(goal, now_ns / 1e9)
            self._event(axis, "reflex", f"group {group}: {goal.value} ({reason})", from_state=d.state.value)

    # ---- NMT (cia402.md §5) -----------------------------------------------------------------------

    def _apply_agent(self, cmd: AgentCommand, now_ns: int) -> None:
        if cmd.op != "nmt":
            self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"agent op {cmd.op!r} unknown"))
            return
        command = cmd.args.get("command")
        if command not in NMT_TARGET:
            self._outcome(cmd, Outcome(axis="", outcome="rejected",
                                       reason=f"nmt command {command!r} is not one of {', '.join(NMT_TARGET)}"))
            return
        axis = cmd.args.get("axis")
        if axis is not None and axis != "":
            d = self._by_axis.get(axis)
            if d is None:
                self._outcome(cmd, Outcome(axis="", outcome="rejected", reason=f"no axis {axis!r} on {self.config.host}"))
                return
            slaves: tuple[int, ...] = (d.slave,)
        else:
            slaves = tuple(range(len(self.slaves)))
        if self._nmt is not None:
            self._finish_nmt("failed", f"superseded by {cmd.request_id}", now_ns)
        start_ns = cmd.received_ns or now_ns
        down_s = max([d.cfg.policy.transition_timeout_s for d in self.drives if d.slave in slaves] or [1.0])
        self._nmt = _Nmt(cmd=cmd, command=command, slaves=slaves, phase="bring_down", start_cycle=self.cycles,
                         start_ns=start_ns, deadline_ns=start_ns + int(cmd.timeout_s * 1e9),
                         down_deadline_ns=now_ns + int(down_s * 1e9))
        if command != "start":
            # Leaving OP: drives on these slaves are first taken down by the ordered sequence.
            for d in self.drives:
                if d.slave in slaves:
                    if d.pending is not None:
                        self._resolve(d, "failed", f"nmt {command} ({cmd.request_id})", now_ns)
                    self._motion_abort(d, f"nmt {command} ({cmd.request_id})", now_ns)
                    d.ctrl.set_halt(False)
                    d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        else:
            self._enter_nmt_recover(self._nmt)
        self._nmt.ticket = self._mgmt.tickets
        self._mgmt.kick()

    def _enter_nmt_recover(self, n: _Nmt) -> None:
        n.phase = "recover"
        for s in n.slaves:
            self._desired_al[s] = ALState.OP
            self._epoch[s] = self._epoch.get(s, 0) + 1
        self._update_recover_set()

    def _step_nmt(self, now_ns: int) -> None:
        n = self._nmt
        assert n is not None
        if now_ns >= n.deadline_ns:
            self._finish_nmt("timeout", f"nmt {n.command} not done within {n.cmd.timeout_s:g} s ({n.phase})", now_ns)
            return
        mgmt = self._mgmt
        if n.phase == "bring_down":
            up = [d for d in self.drives if d.slave in n.slaves and not d.lost
                  and d.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.SWITCHED_ON,
                                  State.READY_TO_SWITCH_ON)]
            if up and now_ns < n.down_deadline_ns:
                return
            if up:
                n.note = f"; drives not down in time: {', '.join(d.axis for d in up)}"
            for s in n.slaves:
                self._desired_al[s] = NMT_TARGET[n.command] if n.command in ("stop", "preop") else ALState.INIT
            if n.command in ("stop", "preop"):
                target = NMT_TARGET[n.command]
                for s in n.slaves:
                    if self._al_status[s].state != target:
                        n.ticket = mgmt.request_state(s, target)
                n.phase = "to_target"
            else:
                for s in n.slaves:
                    n.ticket = mgmt.request_state(s, ALState.INIT, nmt=n.command)  # CAN: reset node / comm.
                n.phase = "to_init"
            return
        if self._al_ticket < n.ticket:
            return  # no AL status read since the last request was written
        states = [self._al_status[s] for s in n.slaves]
        if n.phase == "to_init":
            if all(st.state == ALState.INIT for st in states):
                if n.command == "reset_comm":
                    for s in n.slaves:
                        self._desired_al[s] = ALState.PREOP
                        n.ticket = mgmt.request_state(s, ALState.PREOP)
                    n.phase = "to_target"
                else:  # reset_node: full reconfiguration back to OP (management thread)
                    self._enter_nmt_recover(n)
            return
        if n.phase == "to_target":
            target = self._desired_al[n.slaves[0]]
            if all(st.state == target and not st.error for st in states):
                self._finish_nmt("done", f"AL {target.wire_name}{n.note}", now_ns)
            return
        if n.phase == "recover":
            # The management thread recovers the slaves (recover set); reports set _al_status.
            if all(self._al_status[s].state == ALState.OP and not self._al_status[s].error for s in n.slaves):
                for d in self.drives:
                    if d.slave in n.slaves:
                        d.lost = False
                        d.al = self._al_status[d.slave]
                self._finish_nmt("done", f"AL op; goals stay disabled{n.note}", now_ns)
                self._update_recover_set()

    def _finish_nmt(self, outcome: str, reason: str, now_ns: int) -> None:
        n = self._nmt
        if n is None:
            return
        self._nmt = None
        if outcome != "done":
            # Leave the AL states where they are, and watch them from now on.
            for s in n.slaves:
                self._desired_al[s] = self._al_status[s].state if outcome != "failed" else self._desired_al[s]
        log.info("host %s: nmt %s %s: %s", self.config.host, n.command, outcome, reason)
        self._events.append(CycleEvent(axis="", kind="al_state", detail=f"nmt {n.command} {outcome}: {reason}",
                                       request_id=n.cmd.request_id))
        self._outcome(n.cmd, Outcome(axis="", outcome=outcome, reason=reason,
                                     elapsed_s=max(0.0, (now_ns - n.start_ns) / 1e9),
                                     cycles=self.cycles - n.start_cycle))

    # ---- output --------------------------------------------------------------------------------------

    def _event(self, axis: str, kind: str, detail: str = "", *, from_state: str = "unknown",
               to_state: str = "unknown", error_code: int = 0, request_id: str = "") -> None:
        self._events.append(CycleEvent(axis=axis, kind=kind, detail=detail, from_state=from_state,
                                       to_state=to_state, error_code=error_code, request_id=request_id))

    def _drive_snapshots(self) -> tuple[DriveSnapshot, ...]:
        out = []
        for d in self.drives:
            i = d.inputs
            c = d.ctrl
            out.append(DriveSnapshot(
                axis=d.axis, slave=d.slave, state=d.state.value, statusword=i.statusword,
                controlword=d.controlword, goal=c.goal.value, halt=c.halt, mode=c.mode,
                mode_display=i.modes_of_operation_display, position=i.position_actual,
                velocity=i.velocity_actual, torque=i.torque_actual, error_code=i.error_code,
                error_text=self._error_text(d.slave, i.error_code),
                al_state=d.al.state.wire_name if d.al.state in ALState else "none", lost=d.lost,
                absent=d.absent, object_names=d.object_names, objects=i.extra, dc=d.dc,
                axis_state=d.motion.axis_state.value, homed=d.motion.homed, target_position=d.target_position,
                following_error=following_error(d), motion_request_id=d.motion.request_id))
        return tuple(out)

    def _error_text(self, slave: int, error_code: int) -> str:
        """The text of the bus's last emergency of ``slave`` when it is about this error code."""
        t = self._error_texts.get(slave) if error_code else None
        return t[1] if t is not None and t[0] == error_code else ""

    def _update_stats(self) -> None:
        ps = sorted(self._periods)
        n = len(ps)
        self._stats = CycleStats(
            cycles=self.cycles, cycle_us=self.config.cycle_us,
            period_p50_us=ps[n // 2] / 1000, period_p99_us=ps[min(n - 1, (n * 99) // 100)] / 1000,
            period_max_us=self._period_max_ns / 1000, overruns=self.overruns, wkc_errors=self.wkc_errors,
            expected_wkc=self.bus.expected_wkc, **self._dc_stats())

    def _dc_stats(self) -> dict[str, float]:
        if self._dc is None:
            return {}
        offs = sorted(self._dc_offsets[:min(self.cycles, STATS_WINDOW)] or [0])
        n = len(offs)
        return {"dc_offset_p50_us": offs[n // 2] / 1000, "dc_offset_p99_us": offs[min(n - 1, (n * 99) // 100)] / 1000}
