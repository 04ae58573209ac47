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

import logging
import os
import socket
import threading
import time
from typing import Sequence

from bus_agent import hops
from bus_agent.bus.base import ALState
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import decode_statusword
from bus_agent.cycle.base import INBOX_MAX, SPIN_MIN_NS, SPIN_NS, STATS_EVERY, STATS_WINDOW
from bus_agent.cycle.commands import CommandsMixin
from bus_agent.cycle.drive import ARMED_STATES, DOWN_STATES, FAULT_STATES, UPWARD_GOALS, Drive
from bus_agent.cycle.management import RECOVER_EVERY_CYCLES, SdoJob
from bus_agent.cycle.motion import MotionMixin, write_targets
from bus_agent.cycle.nmt import NmtMixin
from bus_agent.cycle.output import OutputMixin
from bus_agent.cycle.realtime import helper_priority, name_thread, set_thread_fifo, set_timer_slack_ns
from bus_agent.cycle.recorder import RecordingData, RecordingUnavailable
from bus_agent.cycle.slaves import SlavesMixin
from bus_agent.cycle.startup import IdentityMismatch, StartupMixin, decode_supported_modes
from bus_agent.cycle.timing import TimingMixin
from bus_agent.runtime import AgentCommand, CycleSnapshot, CycleStats, DriveCommand

__all__ = ["Cycle", "IdentityMismatch", "decode_supported_modes", "INBOX_MAX", "STATS_EVERY", "SPIN_NS",
           "SPIN_MIN_NS"]

log = logging.getLogger(__name__)



class Cycle(StartupMixin, CommandsMixin, SlavesMixin, NmtMixin, MotionMixin, TimingMixin, OutputMixin):
    """The cyclic process-data loop of one bus agent.

    ``Cycle(bus, config, clock_ns=time.monotonic_ns)``; :meth:`open` brings the segment to OP
    (identity checked), :meth:`start` runs the loop in its own thread, :meth:`stop` performs the
    ordered shutdown. :meth:`tick` runs one cycle synchronously (tests, tools; not while the
    thread runs). Not re-startable after stop.
    """

    # ---- lifecycle --------------------------------------------------------------------------

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
        if self._sleep is time.sleep and self.express_reflex:
            # the sleep before each deadline waits on this, so a remote trigger wakes the cycle
            self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
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
        self.state = "stopped"

    def _close_bus(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._wake_lock:  # no trigger_group writes to the number once closed (it may be reused)
            fd, self._wake_fd = self._wake_fd, -1
            if fd >= 0:
                os.close(fd)
        if self._trigger_sock is not None:
            self._trigger_sock.close()
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

    def trigger_socket(self, sock: socket.socket) -> None:
        """Take group triggers as datagrams ``group NUL reason`` (UTF-8) on ``sock`` as well: the
        cycle thread's sleep waits on it and reads them itself, one thread hop less than
        :meth:`trigger_group` from a reader thread (the gateway process writes them). Call
        before :meth:`start`; the socket is closed with the bus."""
        sock.setblocking(False)
        self._trigger_sock = sock

    def _take_trigger_datagrams(self) -> None:
        sock = self._trigger_sock
        if sock is None:
            return
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # the other end is gone: the bridge reports the loss
                return
            if not data:
                return
            group, _, reason = data.decode("utf-8", "replace").partition("\0")
            self._triggers.append((group, reason))

    def trigger_group(self, group: str, reason: str) -> None:
        """A member of ``group`` faulted or was lost on another host: local members react with
        the configured reflex, at once when the loop is asleep before a deadline (an express
        exchange, :meth:`_express`), else in the running or next cycle. Thread-safe."""
        self._triggers.append((group, reason))
        with self._wake_lock:
            if self._wake_fd >= 0:
                os.eventfd_write(self._wake_fd, 1)

    def stats(self) -> CycleStats:
        return self._stats

    def recording(self, what: str = "last", last_s: float = 10.0, timeout_s: float = 5.0) -> RecordingData:
        """A flight recording (``Recorder.fetch``); raises RecordingUnavailable. Thread-safe, not
        for the cycle thread (``what='now'`` blocks until the window after the trigger is recorded)."""
        if self.recorder is None:
            raise RecordingUnavailable(f"the flight recorder of {self.config.host} is off ([recorder] seconds = 0)")
        return self.recorder.fetch(what, last_s, timeout_s)

    # ---- the loop -------------------------------------------------------------------------------

    def _run(self) -> None:
        if not hasattr(self, "_old_switch"):
            self._prepare_process()
        set_thread_fifo(self.rt_priority, f"the cycle thread of {self.config.host}")
        name_thread(f"cycle-{self.config.host}")
        set_timer_slack_ns(1)
        try:
            period = self.period_ns
            t0 = self.clock_ns()
            k = 0
            while True:
                deadline = t0 + k * period + self._dc_adjust_ns
                now = self.clock_ns()
                while now < deadline:
                    if not self._wait_until(deadline):
                        now = self.clock_ns()
                        break
                    # woken before the deadline by a remote group trigger: apply it now
                    hops.stamp("cy.wake")
                    if self._triggers:
                        self._express(self.clock_ns())
                    now = self.clock_ns()
                self._late_ns = now - deadline
                if now - deadline > period:
                    self.overruns += 1
                    # skip the missed slots (no catch-up burst), on the schedule shifted by DC
                    k = (now - t0 - self._dc_adjust_ns) // period
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
            ref = self._dc_ref
            self._dc_adjust_ns += dcs.step(self._dc_time(), self._late_ns, ref is not None and ref.lost)
            self._dc_offsets[cycle % STATS_WINDOW] = dcs.offset_ns
            if self.dc_log is not None and 0 < self.period_log_len <= len(self.dc_log):
                self.dc_log[self.period_log_len - 1] = dcs.offset_ns
        all_op_wanted = self._all_op_wanted
        if all_op_wanted is None:
            all_op_wanted = self._all_op_wanted = self._nmt is None and all(
                s == ALState.OP for s in self._desired_al.values())
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
        reports = bool(mgmt.reports)
        if reports:
            self._apply_reports(now_ns)
        if self._found and self._confirm_found(wkc, now_ns):
            reports = True  # step every drive this cycle (a found drive's inputs are fresh)

        # The drives to step this cycle: all of them, or (fast path) only those whose inputs
        # changed or that are not at rest; see _at_rest and docs/agent-cycle.md, "Fast paths".
        drives = self.drives
        changed = self._inputs_changed() if self._inputs_changed is not None and self.fast_paths else None
        work: Sequence[Drive] = drives
        # (an express reflex since the last cycle changed goals, and its exchange inputs)
        expressed = bool(self._express_events) or self.express_exchanges != self._express_seen
        self._express_seen = self.express_exchanges
        if (changed is not None and not reports and self.state == "running" and self._nmt is None
                and not self._lost_origins and not expressed):
            work = self._work(changed)
        for d in work:
            i = d.inputs = bus.inputs(d.slave)
            if d.sdo_mode_display:
                i.modes_of_operation_display = d.mode_display_sdo
        if self._take_emergencies is not None:
            for slave, code, register, text in self._take_emergencies():
                for d in drives:
                    if d.slave == slave:
                        self._event(d.axis, "emcy", f"EMCY 0x{code:04X} {text} (error register 0x{register:02X})",
                                    error_code=code)
                        d.last_emcy_code = code if code & 0xFF00 else 0
                        if d.sdo_error_code and d.state in FAULT_STATES and code & 0xFF00 and (
                                not d.error_code_readable or not d.error_code_sdo):
                            d.error_code_sdo = d.inputs.error_code = code  # 0x603F not mapped: the EMCY's
                            self._busy.add(d.index)  # published by the next cycle's step

        # Reflex origins are detected on the fresh statusword, before any controller step, so the
        # other members get their new goal in this very cycle.
        origins: list[tuple[str, str]] = []
        for d in work:
            if d.lost:
                continue
            st = decode_statusword(d.inputs.statusword)
            if d.sdo_error_code:
                # 0x603F not mapped: read by SDO, else the last EMCY's (docs/agent-cycle.md)
                if st not in FAULT_STATES:
                    d.error_code_sdo = 0  # out of fault: no error code applies
                    if d.state in FAULT_STATES:
                        d.last_emcy_code = 0  # that fault's EMCY is not the next one's
                elif d.state not in FAULT_STATES:
                    d.error_code_sdo = d.last_emcy_code
                d.inputs.error_code = d.error_code_sdo
            if st in FAULT_STATES and d.state not in FAULT_STATES:
                if d.sdo_error_code and d.error_code_readable:
                    mgmt.sdo(SdoJob(d.slave, "error_code", deadline_ns=now_ns + 1_000_000_000))  # 0x603F not mapped
                elif self._reads_mailbox:
                    mgmt.sdo(SdoJob(d.slave, "mailbox"))  # the fault's EMCY (the SDO read above gets it too)
                for g in self.groups.of_axis(d.axis):
                    origins.append((g, f"{self.config.host}/{d.axis} fault 0x{d.inputs.error_code:04X}"))
                d.fault_since_ns = now_ns
                d.last_fault_ns = now_ns
            elif st in FAULT_STATES:
                d.last_fault_ns = now_ns
        if origins:
            hops.stamp("cy.fault")
        for g, reason in self._lost_origins:
            origins.append((g, reason))
        self._lost_origins = []

        applied = self._apply_inbox(now_ns) if self.state == "running" else False
        if self._socket_watched:
            self._socket_watched = False  # the sleep before this cycle found the socket empty
        else:
            self._take_trigger_datagrams()  # no sleep (late, tick()): look (a failed recv, ~2 us)
        reacting: dict[str, int] = {}  # the reflexes' reacting drives: their controlwords now
        while self._triggers:
            applied = True
            g, reason = self._triggers.popleft()
            self._reflex(g, None, f"remote: {reason}", now_ns)
            for axis in self.groups.reacting(g):
                reacting.setdefault(axis, self._by_axis[axis].controlword)
        for g, reason in origins:
            origin_axis = reason.split("/", 1)[1].split(" ", 1)[0]
            self._reflex(g, origin_axis, reason, now_ns)
            for axis in self.groups.reacting(g, origin_axis):
                reacting.setdefault(axis, self._by_axis[axis].controlword)
            if self.group_sink is not None:
                self.group_sink(g, reason)
        if applied or origins:
            # commands and reflexes may address any drive: step them all (for the drives at
            # rest, the input and fault checks above would have changed nothing)
            work = drives
            self._all_op_wanted = None  # an NMT command may change the wanted AL states

        self.drives_stepped += len(work)
        busy, armed = self._busy, self._armed
        for d in work:
            if d.lost:
                # Outputs of a lost slave: disable voltage and hold; applied if it comes back.
                o = d.out
                o.controlword = 0
                o.target_position = d.target_position = d.inputs.position_actual
                o.target_velocity = d.target_velocity = 0
                o.target_torque = d.target_torque = 0
                d.controlword = 0
                bus.set_outputs(d.slave, o)
                busy.add(d.index)
                armed.discard(d.index)
                continue
            self._auto_reset(d, now_ns)
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            prev = d.state
            d.state = d.ctrl.state if d.ctrl.state is not None else decode_statusword(d.inputs.statusword)
            targets = (d.target_position, d.target_velocity, d.target_torque)
            idle = d.motion.idle
            if d.state in ARMED_STATES or not idle or d.ctrl.goal in UPWARD_GOALS:
                armed.add(d.index)
            else:
                armed.discard(d.index)
            self._motion_step(d, out.hold_target, now_ns)
            o = d.out
            o.controlword = d.controlword = out.controlword | d.motion.controlword_bits
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
            write_targets(d, out.hold_target)  # through the output stage: the axis limits on the wire
            bus.set_outputs(d.slave, o)
            if out.events:
                self._controller_events(d, out.events, prev, now_ns)
            elif idle and self._at_rest(d, targets):
                busy.discard(d.index)
                continue
            busy.add(d.index)

        for d in work:
            pend = d.pending
            if pend is not None and now_ns >= pend.deadline_ns:
                if pend.kind == "goal" and d.ctrl.goal in UPWARD_GOALS:
                    # Nobody waits for this goal any more: do not pursue it.
                    d.ctrl.set_goal(Goal.DISABLED, now_s)
                self._resolve(d, "timeout", f"{pend.cmd.op} not done within {pend.cmd.timeout_s:g} s", now_ns)
        if self._nmt is not None:
            self._step_nmt(now_ns)
            self._all_op_wanted = None
        if cycle % RECOVER_EVERY_CYCLES == 0:
            self._update_recover_set()

        rec = self.recorder
        express = self._express_events
        if express:
            self._express_events = []
        if rec is not None:
            # express reflexes since the last cycle (already published) trigger windows too
            rec.record(cycle, now_ns, period_ns, wkc, drives, express + events if express else events,
                       None if work is drives else work)
        if cycle % STATS_EVERY == 0:
            self._update_stats()
            self._adapt_spin()
        snap = CycleSnapshot(cycle=cycle, time_ns=self._wall_ns(), drives=self._drive_snapshots(work),
                             events=tuple(events), stats=self._stats, agent_state=self.state)
        self.latest = snap
        sink = self.snapshot_sink
        if sink is not None:
            sink(snap)
        if reacting and self.express_reflex:
            self._express_after_cycle(reacting)
