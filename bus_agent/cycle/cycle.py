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

import gc
import logging
import os
import select
import socket
import sys
import threading
import time
from typing import Sequence

from bus_agent.bus.base import ALState
from bus_agent.cia402.controller import Goal
from bus_agent.cia402.states import State, decode_statusword
from bus_agent.cycle.base import (INBOX_MAX, SPIN_MARGIN_NS, SPIN_MIN_NS, SPIN_NS, SPIN_QUANTILE, STATS_EVERY,
                                  STATS_WINDOW)
from bus_agent.cycle.commands import CommandsMixin
from bus_agent.cycle.drive import DOWN_STATES, FAULT_STATES, UPWARD_GOALS, Drive
from bus_agent.cycle.management import RECOVER_EVERY_CYCLES, SdoJob
from bus_agent.cycle.motion import MotionMixin, following_error
from bus_agent.cycle.nmt import NmtMixin
from bus_agent.cycle.realtime import helper_priority, name_thread, set_thread_fifo, set_timer_slack_ns
from bus_agent.cycle.recorder import RecordingData, RecordingUnavailable
from bus_agent.cycle.slaves import SlavesMixin
from bus_agent.cycle.startup import IdentityMismatch, StartupMixin, decode_supported_modes
from bus_agent.runtime import AgentCommand, CycleSnapshot, CycleStats, DriveCommand, DriveSnapshot

__all__ = ["Cycle", "IdentityMismatch", "decode_supported_modes", "INBOX_MAX", "STATS_EVERY", "SPIN_NS",
           "SPIN_MIN_NS"]

log = logging.getLogger(__name__)



class Cycle(StartupMixin, CommandsMixin, SlavesMixin, NmtMixin, MotionMixin):
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

    def _wait_until(self, deadline_ns: int) -> bool:
        """Sleep until the spin before ``deadline_ns``, then spin to it. True (at once, without
        spinning) when a remote trigger woke the sleep; a trigger during the spin waits for the
        cycle (at most the spin away)."""
        spin = self.spin_ns if self.spin_ns is not None else self._spin_auto_ns
        wake = deadline_ns - spin
        remaining = wake - self.clock_ns()
        if remaining > 0:
            if self._doze(remaining / 1e9):
                return True
            over = self._oversleep[self.cycles % STATS_WINDOW] = self.clock_ns() - wake
            if over > self._spin_auto_ns:  # late past the spin: more spin from the next cycle on
                self._spin_auto_ns = min(SPIN_NS, over + SPIN_MARGIN_NS)
        while self.clock_ns() < deadline_ns:
            pass
        return False

    def _doze(self, seconds: float) -> bool:
        """Sleep ``seconds``, or until ``trigger_group`` writes the wake eventfd (True). select's
        timeout has microsecond resolution, and the thread's 1 ns timer slack holds as for a sleep."""
        fd = self._wake_fd
        if fd < 0:
            self._sleep(seconds)
            # an injected sleep (tests, tools): a trigger queued meanwhile counts as a wake
            return self.express_reflex and bool(self._triggers)
        sock = self._trigger_sock
        ready = select.select((fd,) if sock is None else (fd, sock), (), (), seconds)[0]
        if not ready:
            return False
        if fd in ready:
            try:
                os.eventfd_read(fd)
            except OSError:  # BlockingIOError: read by a wake before; EBADF: closed while stopping
                pass
        if sock is not None and sock in ready:
            self._take_trigger_datagrams()
        return True

    def _adapt_spin(self) -> None:
        """The adaptive spin (see SPIN_MIN_NS) from the overshoots of the last sleeps."""
        over = sorted(self._oversleep)
        q = over[min(len(over) - 1, int(len(over) * SPIN_QUANTILE))]
        self._spin_auto_ns = min(SPIN_NS, max(SPIN_MIN_NS, q + SPIN_MARGIN_NS))

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
            if d.sdo_error_code:
                i.error_code = d.error_code_sdo
        if self._take_emergencies is not None:
            for slave, code, register, text in self._take_emergencies():
                for d in drives:
                    if d.slave == slave:
                        self._event(d.axis, "emcy", f"EMCY 0x{code:04X} {text} (error register 0x{register:02X})",
                                    error_code=code)

        # Reflex origins are detected on the fresh statusword, before any controller step, so the
        # other members get their new goal in this very cycle.
        origins: list[tuple[str, str]] = []
        for d in work:
            if d.lost:
                continue
            st = decode_statusword(d.inputs.statusword)
            if st in FAULT_STATES and d.state not in FAULT_STATES:
                if d.sdo_error_code:
                    mgmt.sdo(SdoJob(d.slave, "error_code", deadline_ns=now_ns + 1_000_000_000))  # 0x603F not mapped
                for g in self.groups.of_axis(d.axis):
                    origins.append((g, f"{self.config.host}/{d.axis} fault 0x{d.inputs.error_code:04X}"))
                d.fault_since_ns = now_ns
                d.last_fault_ns = now_ns
            elif st in FAULT_STATES:
                d.last_fault_ns = now_ns
            elif d.error_code_sdo and d.sdo_error_code:
                d.error_code_sdo = 0  # out of fault: the SDO-read 0x603F no longer applies
        for g, reason in self._lost_origins:
            origins.append((g, reason))
        self._lost_origins = []

        applied = self._apply_inbox(now_ns) if self.state == "running" else False
        self._take_trigger_datagrams()
        while self._triggers:
            applied = True
            g, reason = self._triggers.popleft()
            self._reflex(g, None, f"remote: {reason}", now_ns)
        for g, reason in origins:
            origin_axis = reason.split("/", 1)[1].split(" ", 1)[0]
            self._reflex(g, origin_axis, reason, now_ns)
            if self.group_sink is not None:
                self.group_sink(g, reason)
        if applied or origins:
            # commands and reflexes may address any drive: step them all (for the drives at
            # rest, the input and fault checks above would have changed nothing)
            work = drives
            self._all_op_wanted = None  # an NMT command may change the wanted AL states

        self.drives_stepped += len(work)
        busy = self._busy
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
                continue
            self._auto_reset(d, now_ns)
            out = d.ctrl.step(d.inputs.statusword, d.inputs.modes_of_operation_display, now_s)
            prev = d.state
            d.state = d.ctrl.state if d.ctrl.state is not None else decode_statusword(d.inputs.statusword)
            targets = (d.target_position, d.target_velocity, d.target_torque)
            idle = d.motion.idle
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
            o.target_position = d.target_position
            o.target_velocity = d.target_velocity
            o.target_torque = d.target_torque
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

    # ---- the fast path ---------------------------------------------------------------------------

    def _work(self, changed: Sequence[int]) -> Sequence[Drive]:
        """The drives to step in a cycle without commands, reflexes or management reports: those
        whose inputs changed (``changed``: slave positions) and those not at rest, in
        configuration order. Cycle thread only."""
        busy = self._busy
        if not changed:
            if not busy:
                return ()
            idx = busy
        else:
            idx = set(busy)
            of_slave = self._drives_of_slave
            for pos in changed:
                idx.update(of_slave.get(pos, ()))
        drives = self.drives
        return [drives[k] for k in sorted(idx)]

    def _at_rest(self, d: Drive, targets_before: tuple[int, int, int]) -> bool:
        """True when a full step of ``d`` (just made, without controller events, its motion idle
        before it) would repeat itself exactly while its inputs do not change and no command,
        reflex or report reaches it: the cycle may then skip it. The controller settled (its
        output depends on the two inputs only), the motion is idle (:attr:`AxisMotion.idle`), the
        targets did not move (the motion observes them), no command pending, no automatic fault
        reset running (its backoff reads the clock), no emergency text that may change. Cycle thread only."""
        if d.pending is not None or not d.ctrl.settled or not d.motion.idle:
            return False
        if (d.target_position, d.target_velocity, d.target_torque) != targets_before:
            return False
        if d.cfg.policy.auto_reset.enabled and (d.state is State.FAULT or d.auto_attempts):
            return False
        return not (d.inputs.error_code and self._error_texts)

    # ---- output --------------------------------------------------------------------------------------

    def _drive_snapshots(self, work: Sequence[Drive] | None = None) -> tuple[DriveSnapshot, ...]:
        """Every drive's snapshot. A drive whose published values did not change since the last
        cycle keeps its DriveSnapshot (the same immutable object), and when no drive changed the
        tuple of the last cycle is returned as it was: building 26-field records for drives at rest
        was the largest share of the cycle's CPU per drive. Only the drives stepped this cycle
        (``work``; None: all) are looked at: the others' values are those of the last cycle.
        Cycle thread only."""
        changed = False
        texts = self._error_texts
        snaps = self._snap_list
        if len(snaps) != len(self.drives):
            snaps = self._snap_list = [d.snapshot for d in self.drives]
        for d in self.drives if work is None else work:
            i = d.inputs
            c = d.ctrl
            m = d.motion
            key = (d.state, i.statusword, d.controlword, c.goal, c.halt, c.mode, i.modes_of_operation_display,
                   i.position_actual, i.velocity_actual, i.torque_actual, i.error_code,
                   texts.get(d.slave) if i.error_code else None, d.al, d.lost, d.absent, d.object_names, i.extra,
                   d.dc, m.axis_state, m.homed, d.target_position, m.request_id)
            if d.snapshot is None or key != d.snapshot_key:
                # positional, in DriveSnapshot's field order (26 keywords cost 2.7 x the call;
                # tests/unit/test_fast_paths.py pins the order)
                d.snapshot = DriveSnapshot(
                    d.axis, d.slave, d.state.value, i.statusword,                      # axis slave state statusword
                    d.controlword, c.goal.value, c.halt, c.mode,                       # controlword goal halt mode
                    i.modes_of_operation_display, i.position_actual,                  # mode_display position
                    i.velocity_actual, i.torque_actual, i.error_code,                  # velocity torque error_code
                    self._error_text(d.slave, i.error_code),                           # error_text
                    d.al.state.wire_name if d.al.state in ALState else "none", d.lost,  # al_state lost
                    d.absent, d.object_names, i.extra, d.dc,                           # absent object_names objects dc
                    m.axis_state.value, m.homed, d.target_position,                    # axis_state homed target_position
                    following_error(d), m.request_id)                                 # following_error motion_request_id
                d.snapshot_key = key
                snaps[d.index] = d.snapshot
                changed = True
        last = self._drive_snaps
        if changed or len(last) != len(snaps):
            last = self._drive_snaps = tuple(snaps)  # type: ignore[arg-type]
        return last

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
