"""The agent's cyclic loop: process data, CiA 402 controllers, group reflexes, commands, snapshots.

Only this thread touches the bus and the drive controllers. The gateway talks to it through three
thread-safe doors and one callback:

- :meth:`Cycle.submit` -- a validated ``DriveCommand``/``AgentCommand`` into a bounded inbox;
  applied at the next cycle start; every addressed axis later gets exactly one ``Outcome``.
- :meth:`Cycle.trigger_group` -- a group triggered on another host; local members react.
- :attr:`Cycle.snapshot_sink` -- called with one immutable ``CycleSnapshot`` per cycle (must only
  enqueue); :attr:`Cycle.latest` holds the last one for pulls.
- :attr:`Cycle.group_sink` -- called ``(group, reason)`` when a *local* member faults or is lost,
  so the gateway can carry the trigger to the other hosts (must only enqueue).

:class:`Cycle` owns the parts and calls them in order; each part owns its state (docs/agent-cycle.md,
"The parts"). One cycle (:meth:`Cycle.run_cycle`): exchange -> working counter check -> management
reports (AL status, lost/found) -> commands and remote triggers -> group reflexes -> step every
controller -> write outputs -> pending-command deadlines -> snapshot. Everything that can block on
a slave (AL status reads, AL state requests, recovery of a lost slave with its SDOs) runs in a
separate management thread (:class:`bus_agent.cycle.management.Management`) while the cycle keeps
exchanging process data; the cycle only posts requests to it and reads its reports. Timing
(:class:`~bus_agent.cycle.timing.Timing`): drift-free deadlines ``t0 + k * period`` from a
monotonic clock; sleep coarse, spin the last :data:`SPIN_NS`; a cycle that starts more than one
period late counts as an overrun and the schedule skips the missed slots (no burst of catch-up
cycles). See docs/agent-cycle.md for the decisions (outcomes, NMT, shutdown, GC).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from array import array
from typing import Callable, Sequence

from bus_agent.bus.base import ALState, Bus, SlaveInfo
from bus_agent.cia402.controller import Goal
from bus_agent.config import AgentConfig
from bus_agent.cycle.commands import Commands
from bus_agent.cycle.controllers import Controllers
from bus_agent.cycle.drive import DOWN_STATES, Drive, Segment
from bus_agent.cycle.events import EventLog
from bus_agent.cycle.groups import Groups
from bus_agent.cycle.management import RECOVER_EVERY_CYCLES, Management
from bus_agent.cycle.motion import MotionStage
from bus_agent.cycle.nmt import Nmt
from bus_agent.cycle.outcomes import INBOX_MAX, CommandBook
from bus_agent.cycle.output import Snapshots
from bus_agent.cycle.realtime import helper_priority, name_thread, set_thread_fifo, set_timer_slack_ns
from bus_agent.cycle.recorder import Recorder, RecordingData, RecordingUnavailable
from bus_agent.cycle.reflexes import Reflexes
from bus_agent.cycle.slaves import SlaveHealth
from bus_agent.cycle.startup import IdentityMismatch, decode_supported_modes, open_segment, start_dc
from bus_agent.cycle.stats import STATS_EVERY, Statistics
from bus_agent.cycle.timing import SPIN_MIN_NS, SPIN_NS, DcSteering, Timing
from bus_agent.cycle.triggers import TriggerInbox
from bus_agent.runtime import AgentCommand, CycleSnapshot, CycleStats, DriveCommand

__all__ = ["Cycle", "IdentityMismatch", "decode_supported_modes", "INBOX_MAX", "STATS_EVERY", "SPIN_NS",
           "SPIN_MIN_NS"]

log = logging.getLogger(__name__)


class Cycle:
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
        self.period_ns = period_ns = config.cycle_us * 1000
        self._wall_ns = wall_ns
        #: SCHED_FIFO priority of the cycle thread (0: normal scheduling). Needs CAP_SYS_NICE.
        self.rt_priority = rt_priority
        #: Called with each CycleSnapshot from the cycle thread; must only enqueue.
        self.snapshot_sink: Callable[[CycleSnapshot], None] | None = None
        #: Called (group, reason) from the cycle thread when a local member triggers a group.
        self.group_sink: Callable[[str, str], None] | None = None
        self.latest: CycleSnapshot | None = None
        self.state = "starting"            # schemas.messages.AGENT_STATES
        self.error: BaseException | None = None
        #: The flight recorder (created in :meth:`open`; None when ``[recorder] seconds = 0``).
        self.recorder: Recorder | None = None
        #: The cycle thread (None before :meth:`start`).
        self.thread: threading.Thread | None = None
        # the parts (docs/agent-cycle.md, "The parts"), each given what it needs
        seg = self._seg = Segment(config.host, Groups(config.host, config.groups, ()))
        events = self._events = EventLog()
        stats = self.statistics = Statistics(config.cycle_us, record_periods)
        mgmt = self._mgmt = Management(bus, clock_ns, period_ns, config.host)
        book = self._book = CommandBook(events, stats)
        motion = self._motion = MotionStage(seg, book, mgmt, stats, wall_ns)
        health = self.health = SlaveHealth(bus, seg, mgmt, book, motion, events, stats, period_ns)
        nmt = self.nmt = Nmt(seg, health, book, motion, mgmt, events, stats)
        self._commands = Commands(seg, book, motion, health, nmt, stats)
        triggers = self.triggers = TriggerInbox()
        reflex_goal = Goal.QUICK_STOP if config.reflex == "quick_stop" else Goal.DISABLED
        self.reflexes = Reflexes(bus, seg, triggers, book, motion, events, reflex_goal)
        ctl = self.controllers = Controllers(bus, seg, mgmt, book, motion, events)
        self.snapshots = Snapshots(seg, ctl.error_texts)
        self.dc = DcSteering()
        # A real-time cycle thread (rt_priority) spins the fixed SPIN_NS (jitter first), a normal
        # one adapts (CPU first: the demo, a laptop); bench/bench_idle.py compares them.
        self.timing = Timing(period_ns, clock_ns, sleep, triggers, self.dc, stats, ctl.armed,
                             spin_ns=SPIN_NS if rt_priority else None, manage_gc=manage_gc,
                             switch_interval_s=switch_interval_s)
        self._stop_requested = threading.Event()
        self._stopped = threading.Event()
        self._stop_lock = threading.Lock()
        self._stop_deadline_ns = 0
        self._ordered_stop = True
        self._opened = False
        self._closed = False

    # ---- what the parts hold, as the Cycle's public surface -------------------------------------------

    @property
    def clock_ns(self) -> Callable[[], int]:
        """The monotonic clock of the loop (the timing's)."""
        return self.timing.clock_ns

    @clock_ns.setter
    def clock_ns(self, clock: Callable[[], int]) -> None:
        self.timing.clock_ns = clock

    @property
    def slaves(self) -> list[SlaveInfo]:
        return self._seg.slaves

    @property
    def drives(self) -> list[Drive]:
        return self._seg.drives

    @property
    def groups(self) -> Groups:
        return self._seg.groups

    @groups.setter
    def groups(self, groups: Groups) -> None:
        self._seg.groups = groups

    @property
    def axes(self) -> tuple[str, ...]:
        return self._seg.axes

    @property
    def cycles(self) -> int:
        return self.statistics.cycles

    @property
    def overruns(self) -> int:
        return self.statistics.overruns

    @property
    def wkc_errors(self) -> int:
        return self.statistics.wkc_errors

    @property
    def drives_stepped(self) -> int:
        """Drive steps made in full so far (at most cycles x drives; the fast path skips the rest)."""
        return self.statistics.drives_stepped

    @property
    def period_log(self) -> array | None:
        """Optional full record of periods (ns) for benchmarks (``record_periods`` slots)."""
        return self.statistics.period_log

    @period_log.setter
    def period_log(self, log_: array | None) -> None:
        self.statistics.period_log = log_

    @property
    def period_log_len(self) -> int:
        return self.statistics.period_log_len

    @period_log_len.setter
    def period_log_len(self, n: int) -> None:
        self.statistics.period_log_len = n

    @property
    def dc_log(self) -> array | None:
        """Optional record of frame-to-SYNC0 offsets (ns), beside period_log (benchmarks)."""
        return self.dc.log

    @dc_log.setter
    def dc_log(self, log_: array | None) -> None:
        self.dc.log = log_

    @property
    def dc_states(self) -> tuple[str, ...]:
        return self.dc.states

    @property
    def express_exchanges(self) -> int:
        return self.reflexes.exchanges

    @property
    def express_reflex(self) -> bool:
        """Apply a remote group trigger at once in an express exchange (:meth:`express`) rather
        than at the next deadline; False: the next cycle applies it."""
        return self.triggers.express

    @express_reflex.setter
    def express_reflex(self, on: bool) -> None:
        self.triggers.express = on

    @property
    def spin_ns(self) -> int | None:
        """Spin before each deadline (ns): None adapts it to the sleep's overshoot (SPIN_MIN_NS ..
        SPIN_NS), a number fixes it (0: none). Default: a real-time cycle thread (rt_priority)
        spins the fixed SPIN_NS, a normal one adapts (docs/agent-cycle.md, Timing)."""
        return self.timing.spin_ns

    @spin_ns.setter
    def spin_ns(self, ns: int | None) -> None:
        self.timing.spin_ns = ns

    @property
    def spin_at_rest(self) -> bool:
        """False: the spin is made only while a period's jitter can matter (some drive in
        :data:`~bus_agent.cycle.drive.ARMED_STATES`, asked to go up, or moving; SYNC0 running);
        with every drive off the loop only sleeps (``[cycle] spin_at_rest``)."""
        return self.timing.spin_at_rest

    @spin_at_rest.setter
    def spin_at_rest(self, on: bool) -> None:
        self.timing.spin_at_rest = on

    @property
    def fast_paths(self) -> bool:
        """Skip the per-drive work of drives at rest (docs/agent-cycle.md, "Fast paths"); False:
        every drive is stepped in full every cycle (tests compare both)."""
        return self.controllers.fast_paths

    @fast_paths.setter
    def fast_paths(self, on: bool) -> None:
        self.controllers.fast_paths = on

    def stats(self) -> CycleStats:
        return self.statistics.current

    # ---- lifecycle --------------------------------------------------------------------------

    def _set_state(self, state: str) -> None:
        self.state = state
        self.health.running = state == "running"  # lost slaves are brought back while running

    def open(self) -> list[SlaveInfo]:
        """Open the bus, check every configured identity (0x1018), map PDOs and reach OP.

        Raises IdentityMismatch / BusError / ConfigError; on error the bus is closed. Not cycle-safe
        (blocking, seconds)."""
        seg = self._seg
        if self._opened:
            return seg.slaves
        try:
            seg.slaves, drives = open_segment(self.bus, self.config, self.period_ns)
            seg.drives.extend(drives)
        except BaseException:
            self._set_state("error")
            self._close_bus()
            raise
        seg.by_axis.update((d.axis, d) for d in seg.drives)
        self.controllers.start()
        start_dc(self.bus, self.config, self.period_ns, seg.drives, self.dc)
        self.health.start(len(seg.slaves))
        seg.groups = Groups(self.config.host, self.config.groups, seg.axes)
        rc = self.config.recorder
        if rc.seconds:
            self.recorder = Recorder(seg.axes, self.config.cycle_us, rc.seconds, rc.pre_s, rc.post_s,
                                     wall_ns=self._wall_ns, mono_ns=self.clock_ns)
        self.statistics.current = CycleStats(cycle_us=self.config.cycle_us, expected_wkc=self.bus.expected_wkc)
        self._opened = True
        self._set_state("running")
        log.info("host %s: %d slave(s) in OP, %d drive(s) %s, expected working counter %d",
                 self.config.host, len(seg.slaves), len(seg.drives), ",".join(seg.axes), self.bus.expected_wkc)
        return seg.slaves

    def start(self) -> None:
        """Open (if not yet) and run the loop in its own thread, and the management thread
        (AL status, AL requests, recovery). Returns once the threads run."""
        if self.thread is not None:
            return
        # GC settings first: a full collection between OP and the first cycle could outlast the
        # slaves' SM watchdog (100 ms) in a large process
        self.timing.prepare_process()
        try:
            self.open()
        except BaseException:
            self.timing.restore_process()
            raise
        if self.timing.real_sleep and self.triggers.express:
            # the sleep before each deadline waits on this, so a remote trigger wakes the cycle
            self.triggers.open_wake()
        self._mgmt.rt_priority = helper_priority(self.rt_priority)
        self._mgmt.start()
        if self.recorder is not None:
            self.recorder.start()
        self.thread = threading.Thread(target=self.run, name=f"cycle-{self.config.host}", daemon=True)
        self.thread.start()

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
            thread = self.thread
            if thread is not None and thread.is_alive():
                self.begin_stop(ordered, timeout_s)
                thread.join(timeout_s + 5.0)
                if thread.is_alive():
                    log.error("host %s: cycle thread did not stop", self.config.host)
                    return
            elif self._opened and self.state in ("running", "stopping"):
                self.begin_stop(ordered, timeout_s)
                while not self._stop_done():
                    self.tick()
                self._finish_stop()
            self._close_bus()

    def begin_stop(self, ordered: bool, timeout_s: float) -> None:
        """Ask the loop to stop: the next cycle begins the shutdown (ordered: every drive down,
        waited for at most ``timeout_s``). Thread-safe; :meth:`stop` calls it and waits."""
        self._ordered_stop = ordered
        self._stop_deadline_ns = self.clock_ns() + int(timeout_s * 1e9) if ordered else 0
        self._stop_requested.set()

    def _stop_done(self) -> bool:
        if self.state != "stopping":
            return False
        if self.clock_ns() >= self._stop_deadline_ns:
            return True
        return all(d.lost or d.state in DOWN_STATES for d in self.drives)

    def _finish_stop(self) -> None:
        self._mgmt.stop()  # the bus is the cycle's alone from here
        not_down = [f"{d.axis}={d.state.value}" for d in self.drives if not d.lost and d.state not in DOWN_STATES]
        if not_down and self._ordered_stop:
            log.warning("host %s: ordered shutdown deadline passed with drives not down: %s",
                        self.config.host, ", ".join(not_down))
        try:
            self.bus.request_al_state(None, ALState.INIT)
        except Exception as e:  # closing anyway
            log.warning("host %s: AL INIT request failed: %s", self.config.host, e)
        self._set_state("stopped")

    def _close_bus(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.triggers.close()
        self._mgmt.stop()
        if self.recorder is not None:
            self.recorder.stop()
        try:
            self.bus.close()
        except Exception as e:
            log.warning("host %s: bus close failed: %s", self.config.host, e)
        if self.state != "error":
            self._set_state("stopped")
        self._stopped.set()

    # ---- doors for the gateway (thread-safe) --------------------------------------------------

    def submit(self, cmd: DriveCommand | AgentCommand) -> bool:
        """Queue a validated command for the next cycle start. False when the inbox is full or
        the agent is not running (the caller answers busy/rejected). Thread-safe, non-blocking."""
        if self.state != "running" or self._stop_requested.is_set():
            return False
        return self._book.submit(cmd)

    def trigger_socket(self, sock: socket.socket) -> None:
        """Take group triggers as datagrams ``group NUL reason`` (UTF-8) on ``sock`` as well: the
        cycle thread's sleep waits on it and reads them itself, one thread hop less than
        :meth:`trigger_group` from a reader thread (the gateway process writes them). Call
        before :meth:`start`; the socket is closed with the bus."""
        self.triggers.set_socket(sock)

    def trigger_group(self, group: str, reason: str) -> None:
        """A member of ``group`` faulted or was lost on another host: local members react with
        the configured reflex, at once when the loop is asleep before a deadline (an express
        exchange, :meth:`express`), else in the running or next cycle. Thread-safe."""
        self.triggers.push(group, reason)

    def recording(self, what: str = "last", last_s: float = 10.0, timeout_s: float = 5.0) -> RecordingData:
        """A flight recording (``Recorder.fetch``); raises RecordingUnavailable. Thread-safe, not
        for the cycle thread (``what='now'`` blocks until the window after the trigger is recorded)."""
        if self.recorder is None:
            raise RecordingUnavailable(f"the flight recorder of {self.config.host} is off ([recorder] seconds = 0)")
        return self.recorder.fetch(what, last_s, timeout_s)

    # ---- the loop -------------------------------------------------------------------------------

    def run(self) -> None:
        """The loop of the cycle thread (:meth:`start` runs it) until the shutdown is done."""
        timing = self.timing
        timing.prepare_process()
        set_thread_fifo(self.rt_priority, f"the cycle thread of {self.config.host}")
        name_thread(f"cycle-{self.config.host}")
        set_timer_slack_ns(1)
        try:
            timing.begin()
            while True:
                now = timing.next_start(self._woken)
                self.run_cycle(now)
                if self._stop_requested.is_set() and self.state == "running":
                    self._enter_stopping(now)
                if self.state == "stopping" and self._stop_done():
                    self._finish_stop()
                    break
        except BaseException as e:  # the loop must not die silently
            self.error = e
            self._set_state("error")
            log.exception("host %s: cycle thread failed", self.config.host)
            self._mgmt.stop()
            try:
                self.bus.request_al_state(None, ALState.INIT)
            except Exception:
                pass
        finally:
            timing.restore_process()

    def _woken(self) -> None:
        """The sleep before a deadline ended early: apply the remote triggers now."""
        if self.triggers.queue:
            self.express(self.clock_ns())

    def tick(self) -> CycleSnapshot:
        """Run one cycle now (tests and tools; never while the thread runs). Returns its snapshot."""
        now = self.clock_ns()
        if self._stop_requested.is_set() and self.state == "running":
            self._enter_stopping(now)
        self.run_cycle(now)
        assert self.latest is not None
        return self.latest

    def _enter_stopping(self, now_ns: int) -> None:
        self._set_state("stopping")
        self._book.reject_all("agent stopping", self._seg.by_axis)
        if self.nmt.run is not None:
            self.nmt.finish("failed", "agent stopping", now_ns)
        if self._ordered_stop:
            for d in self.drives:
                if d.pending is not None:
                    self._book.resolve(d, "failed", "agent stopping", now_ns)
                self._motion.abort(d, "agent stopping", now_ns)
                d.ctrl.set_halt(False)
                d.ctrl.set_goal(Goal.DISABLED, now_ns / 1e9)
        log.info("host %s: ordered shutdown of %d drive(s)", self.config.host, len(self.drives))

    def express(self, now_ns: int) -> None:
        """Remote group triggers that arrived between two cycles, applied at once
        (:meth:`Reflexes.express`, one extra exchange where that is safe). Its events go out at
        once in a snapshot stamped before the exchange, numbered as the last cycle. Cycle thread
        (the loop calls it when a trigger ends the sleep)."""
        events = self._events.begin()
        reflexes = self.reflexes
        send = reflexes.express(now_ns)
        time_ns = self._wall_ns()  # the reflex's time: when it was applied, before the frame
        if send:
            reflexes.exchange()
        snap = CycleSnapshot(cycle=self.statistics.cycles, time_ns=time_ns, drives=self.snapshots.drive_snapshots(),
                             events=tuple(events), stats=self.statistics.current, agent_state=self.state)
        reflexes.published(events)
        self.latest = snap
        sink = self.snapshot_sink
        if sink is not None:
            sink(snap)

    # ---- one cycle --------------------------------------------------------------------------------

    def run_cycle(self, now_ns: int) -> None:
        """One cycle starting at ``now_ns``: each part in the documented order. Cycle thread only
        (:meth:`run`, :meth:`tick`)."""
        stats = self.statistics
        period_ns = stats.begin_cycle(now_ns)
        cycle = stats.cycles
        events = self._events.begin()
        bus = self.bus
        health = self.health
        nmt = self.nmt
        ctl = self.controllers
        running = self.state == "running"

        # exchange -> working counter check -> management reports
        wkc = bus.exchange()
        dc = self.dc
        if dc.sync is not None and wkc > 0:
            dc.step(cycle, stats.period_log_len)  # keep the cycle in step with SYNC0
        health.check_wkc(wkc, nmt.run)
        mgmt = self._mgmt
        if not mgmt.threaded and not self._closed:
            mgmt.run_once(now_ns)
        reports = bool(mgmt.reports)
        if reports:
            health.apply_reports(now_ns, nmt.run)
        if health.confirm_found(wkc, now_ns, nmt.run):
            reports = True  # step every drive this cycle (a found drive's inputs are fresh)

        # The drives to step this cycle: all of them, or (fast path) only those whose inputs
        # changed or that are not at rest; see Controllers and docs/agent-cycle.md, "Fast paths".
        drives = self._seg.drives
        changed = ctl.changed_slaves()
        work: Sequence[Drive] = drives
        # (an express reflex since the last cycle changed goals, and its exchange inputs)
        expressed, express_events = self.reflexes.take_express()
        losing = health.losing
        if (changed is not None and not reports and running and nmt.run is None
                and not losing and not expressed):
            work = ctl.select(changed)
        if work:
            ctl.read_inputs(work)
        ctl.take_emergencies()
        origins = ctl.new_faults(work, now_ns) if work else []
        if losing:
            origins += health.take_lost_origins()

        # commands and remote triggers -> group reflexes
        cmds = self._book.take() if running else None
        applied = bool(cmds)
        if cmds:
            self._commands.apply(cmds, now_ns)
        triggers = self.triggers
        triggers.look()
        if triggers.queue:
            applied = True
        reacting = self.reflexes.apply(origins, now_ns) if applied or origins else {}
        group_sink = self.group_sink
        if group_sink is not None:
            for g, reason in origins:
                group_sink(g, reason)
        if applied or origins:
            # commands and reflexes may address any drive: step them all (for the drives at
            # rest, the input and fault checks above would have changed nothing)
            work = drives
            health.wanted_changed()  # an NMT command may change the wanted AL states

        # controllers -> outputs -> deadlines
        if work:
            stats.drives_stepped += len(work)
            ctl.step(work, now_ns)
            self._book.deadlines(work, now_ns)
        if nmt.run is not None:
            nmt.step(now_ns)
            health.wanted_changed()
        if cycle % RECOVER_EVERY_CYCLES == 0:
            health.update_recover_set(nmt.run)

        # snapshot
        rec = self.recorder
        if rec is not None:
            # express reflexes since the last cycle (already published) trigger windows too
            rec.record(cycle, now_ns, period_ns, wkc, drives, express_events + events if express_events else events,
                       None if work is drives else work)
        if cycle % STATS_EVERY == 0:
            stats.update(bus.expected_wkc, dc.figures(cycle))
            self.timing.adapt_spin()
        snap = CycleSnapshot(cycle=cycle, time_ns=self._wall_ns(), drives=self.snapshots.drive_snapshots(work),
                             events=tuple(events), stats=stats.current, agent_state=self.state)
        self.latest = snap
        sink = self.snapshot_sink
        if sink is not None:
            sink(snap)
        if reacting and triggers.express:
            self.reflexes.express_after_cycle(reacting)
