"""The bridge between the cycle process and the gateway process (``gateway = "process"``).

The Zenoh gateway runs in a child process (``python -m bus_agent.gateway.bridge --fd N``), so Zenoh
callbacks, msgpack and the publish loop never compete with the cycle thread for its GIL. The
cycle process keeps the bus, the :class:`~bus_agent.cycle.cycle.Cycle` and :class:`GatewayProcess`
(two small threads); the child opens the Zenoh session and runs an unchanged
:class:`~bus_agent.gateway.gateway.Gateway` against :class:`CycleProxy`, which has exactly the Cycle
surface the gateway uses. One ``AF_UNIX`` socketpair carries length-prefixed pickled tuples
(:class:`Msg`; see docs/agent-gateway.md for the measured choice of pickle over msgpack).

Cycle -> gateway (thread ``bridge-out``, woken by the snapshot sink):

- the latest snapshot, forwarded at once when a field the gateway publishes on change differs
  (:data:`FORWARD_NOW_FIELDS`, agent state), when it carries events, or when an outcome is
  waiting; otherwise at most every ``forward_period_s`` (positions, velocities, torques, stats);
- every event with the cycle and wall time of the snapshot it came in;
- outcomes tagged with the command id.

The cycle thread only stores the latest snapshot, extends a bounded deque and sets an event.

Gateway -> cycle (thread ``bridge-in``, blocked in ``recv`` otherwise): commands (the
DriveCommand/AgentCommand fields without the callback), sim control calls. Group triggers take
a second, datagram socketpair straight to the cycle thread, whose sleep waits on it
(``Cycle.trigger_socket``); ``Msg.TRIGGER`` through ``bridge-in`` remains for a bridge attached
without it (tests).
``CycleProxy.submit`` is a synchronous round trip (the real ``Cycle.submit`` answer and the
cycle's state), so "inbox full" and "agent stopping" reach the gateway exactly as in-process.

Loss: if the child dies, ``GatewayProcess`` calls ``on_lost`` (the agent runs the ordered
shutdown of every drive and exits non-zero: nobody can command or watch the drives any more)
and from then on logs the cycle's events. If the cycle process dies, the child reads EOF and
exits at once (its links close, so peers drop the agent's liveliness token).
"""

from __future__ import annotations

import collections
import functools
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Callable, Mapping

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import set_thread_fifo
from bus_agent.gateway.wire import (BridgeError, EVENT_BACKLOG, FORWARD_PERIOD_S, ForwardFilter, Msg, READY_TIMEOUT_S, decode_command, dumps, encode_update, loads)

log = logging.getLogger(__name__)

# ---- cycle process side ---------------------------------------------------------------------------


class GatewayProcess:
    """Runs the gateway in a child process and bridges it to ``cycle``.

    ``settings``: ``GatewaySettings`` keyword arguments; ``zenoh``: the agent's ZenohConfig;
    ``sim_handlers``: SimControl handlers of a simulated bus (served through the child's
    session), or None. ``on_lost(reason)`` is called once if the child dies before :meth:`close`.
    Order: :meth:`start` (before ``cycle.start``) -> :meth:`stop_commands` -> ``cycle.stop`` ->
    :meth:`close`.
    """

    def __init__(self, cycle: Any, settings: Mapping[str, Any], zenoh: Any, *,
                 sim_handlers: Mapping[str, Callable[[int, dict], str]] | None = None, n_slaves: int = 0,
                 on_lost: Callable[[str], None] | None = None, forward_period_s: float = FORWARD_PERIOD_S,
                 log_level: int | None = None, rt_priority: int = 0) -> None:
        self.cycle = cycle
        #: SCHED_FIFO of the bridge threads: they take the GIL, so one below a real-time cycle.
        self.rt_priority = rt_priority
        self.settings = dict(settings)
        # The gateway process's reader, publish and command threads: one level below the bridge
        # threads here, so the reflex's and the replies' way through it is not left waiting for
        # a scheduler slice on a busy machine (its own GIL: no inversion with the cycle).
        self.settings.setdefault("rt_priority", max(0, rt_priority - 1) if rt_priority else 0)
        self.zenoh = zenoh
        self.host = self.settings["host"]
        self.sim_handlers = dict(sim_handlers or {})
        self.n_slaves = n_slaves
        self.on_lost = on_lost
        self.log_level = log_level if log_level is not None else logging.getLogger().getEffectiveLevel()
        self.filter = ForwardFilter(min(forward_period_s, self.settings.get("heartbeat_s", 1.0)))
        self.proc: subprocess.Popen | None = None
        self.lost_reason: str | None = None
        self._conn: Connection | None = None
        self._send_lock = threading.Lock()
        # cycle thread -> bridge-out
        self._latest: rt.CycleSnapshot | None = None
        self._events: collections.deque[tuple[rt.CycleEvent, int, int]] = collections.deque(maxlen=EVENT_BACKLOG)
        self._outcomes: collections.deque[tuple[int, rt.Outcome]] = collections.deque()
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._ready = threading.Event()
        self._failed: tuple[str, str] | None = None
        self._running = False
        self._threads: list[threading.Thread] = []
        self.forwarded = 0  # snapshots sent (tests, benchmarks)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    # -- cycle thread: store, extend, set; nothing else

    def on_snapshot(self, snap: rt.CycleSnapshot) -> None:
        if self._outcomes or snap.events:  # a command's outcome; else events (a reflex's path)
            hops.stamp("cy.sink" if self._outcomes else "cy.sink.ev")
        last, self._latest = self._latest, snap
        if snap.events:
            self._events.extend((ev, snap.cycle, snap.time_ns) for ev in snap.events)
        # No drive changed (the cycle hands on the very tuple of drive snapshots), no event, no
        # outcome: nothing to forward now, bridge-out's periodic wake-up forwards the statistics.
        # Saves a thread wake-up and GIL hand-over per cycle at rest (the idle demo).
        if (snap.events or self._outcomes or last is None or snap.drives is not last.drives
                or snap.agent_state != last.agent_state):
            self._wake.set()

    def _on_outcome(self, cid: int, outcome: rt.Outcome) -> None:
        # No wake here: the cycle calls this while it still resolves the other axes of the same
        # cycle; its snapshot sink, right after, wakes bridge-out, so a cycle's outcomes cross
        # in one message with that cycle's snapshot (not one message, decode and publish pass
        # in the gateway process per early outcome).
        self._outcomes.append((cid, outcome))

    # -- life cycle

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Start the child and wait until its gateway is declared. Raises BridgeError."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        # Group triggers go straight to the cycle thread, which waits on this socket in its sleep
        # (Cycle.trigger_socket): one thread hop and GIL hand-over less than through bridge-in.
        trig_ours, trig_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "bus_agent.gateway.bridge", "--fd", str(theirs.fileno()),
                 "--trigger-fd", str(trig_theirs.fileno()), "--log-level", logging.getLevelName(self.log_level)],
                pass_fds=(theirs.fileno(), trig_theirs.fileno()), env=env, stdin=subprocess.DEVNULL)
        except OSError as exc:
            ours.close()
            trig_ours.close()
            raise BridgeError("gateway", f"cannot start the gateway process: {exc}") from None
        finally:
            theirs.close()  # the child's end lives in the child only: its death is our EOF
            trig_theirs.close()
        take = getattr(self.cycle, "trigger_socket", None)
        if take is not None:
            take(trig_ours)
        else:
            trig_ours.close()
        self.attach(Connection(ours.detach()), timeout_s)

    def attach(self, conn: Connection, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Serve the gateway process at the other end of ``conn``: send it INIT, wait for READY
        (raises BridgeError on FAILED, on its exit or after ``timeout_s``), then forward.
        :meth:`start` calls it with its child; tests call it with one end of a socketpair."""
        self._conn = conn
        sim = (self.host, self.n_slaves, tuple(self.sim_handlers)) if self.sim_handlers else None
        try:
            self._send(dumps((Msg.INIT.value, self.settings, self.zenoh, sim)))
        except OSError as exc:
            self._closing.set()
            self._kill()
            raise BridgeError("gateway", f"the gateway process is gone at start-up: {exc}") from None
        # Snapshots flow from now on, so the gateway has one before it declares anything.
        self.cycle.snapshot_sink = self.on_snapshot
        self._threads = [threading.Thread(target=self._in_loop, name="bridge-in", daemon=True),
                         threading.Thread(target=self._out_loop, name="bridge-out", daemon=True)]
        for t in self._threads:
            t.start()
        if not self._ready.wait(timeout_s) or self._failed is not None:
            self.cycle.snapshot_sink = None
            self._closing.set()
            self._kill()
            raise BridgeError(*(self._failed or ("gateway", f"the gateway process did not get ready within "
                                                            f"{timeout_s:g} s")))
        self._running = True
        if not self._threads[0].is_alive():  # died between READY and now
            self._lost("its connection closed")
        log.info("gateway %s: running in process %s", self.host, self.pid)

    def stop_commands(self) -> None:
        """The child stops taking commands and reports agent state ``stopping``."""
        self._try_send(dumps((Msg.STOPPING.value,)))

    def close(self, timeout_s: float = 10.0) -> None:
        """After the cycle stopped: forward the last snapshot, events and outcomes, let the child
        publish them, undeclare and close its session; wait for it to exit. Idempotent."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._wake.set()
        for t in self._threads[1:]:
            t.join(timeout_s)
        if self.proc is not None:
            try:
                code = self.proc.wait(timeout_s)
                if code != 0 and self.lost_reason is None:
                    log.warning("gateway %s: process exited with %s", self.host, _exit_text(code))
            except subprocess.TimeoutExpired:
                log.error("gateway %s: process %d did not exit in %g s: killed", self.host, self.proc.pid, timeout_s)
                self._kill()
        for t in self._threads[:1]:
            t.join(timeout_s)
        if self._conn is not None:
            self._conn.close()

    def _kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)

    # -- sending

    def _send(self, data: bytes) -> None:
        assert self._conn is not None
        with self._send_lock:
            self._conn.send_bytes(data)

    def _try_send(self, data: bytes) -> bool:
        if self.lost_reason is not None or self._conn is None:
            return False
        try:
            self._send(data)
            return True
        except OSError as exc:
            self._lost(f"sending to it failed: {exc}")
            return False

    # -- bridge-out: snapshots, events, outcomes

    def _out_loop(self) -> None:
        set_thread_fifo(self.rt_priority, f"bridge-out of {self.host}")
        while True:
            closing = self._closing.is_set()
            if not closing:
                self._wake.wait(self.filter.period_s)
                self._wake.clear()
            if self._outcomes or self._events:
                hops.stamp("cy.woke" if self._outcomes else "cy.woke.ev")
            try:
                self._forward(final=closing)
            except Exception:
                log.exception("gateway %s: bridge-out", self.host)
            if closing:
                self._try_send(dumps((Msg.CLOSE.value,)))
                return

    def _forward(self, final: bool = False) -> None:
        snap = self._latest
        events = self._events
        outcomes = self._outcomes
        if self.lost_reason is not None:
            self._log_events()
            return
        pending = bool(events or outcomes)
        if snap is None:
            if not pending:
                return
        elif not (self.filter.due(snap, time.monotonic(), pending) or final):
            return
        evs = [events.popleft() for _ in range(len(events))]
        outs = [outcomes.popleft() for _ in range(len(outcomes))]
        if self._try_send(encode_update(snap, evs, outs)):
            self.forwarded += 1
            if outs or evs:
                hops.stamp("cy.forwarded" if outs else "cy.forwarded.ev")

    def _log_events(self) -> None:
        """Without a gateway nobody sees the drives: the log is the only record of the stop."""
        while self._events:
            ev, cycle, _ = self._events.popleft()
            log.warning("drive %s/%s (no gateway): %s %s%s", self.host, ev.axis or "*", ev.kind, ev.detail,
                        f" -> {ev.to_state}" if ev.kind == "transition" else "")
        self._outcomes.clear()

    # -- bridge-in: commands, triggers, sim control, start-up answer

    def _in_loop(self) -> None:
        set_thread_fifo(self.rt_priority, f"bridge-in of {self.host}")
        assert self._conn is not None
        conn = self._conn
        while True:
            try:
                msg = loads(conn.recv_bytes())
            except (EOFError, OSError):
                break
            except Exception:
                log.exception("gateway %s: undecodable bridge message", self.host)
                continue
            try:
                self._handle(msg)
            except Exception:
                log.exception("gateway %s: bridge message %s failed", self.host, msg[0].name)
        if not self._ready.is_set():
            code = self.proc.wait(5) if self.proc is not None else None
            self._failed = ("gateway", f"the gateway process ended during start-up ({_exit_text(code)})")
            self._ready.set()
        elif self._running:
            self._lost("its connection closed")

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind is Msg.SUBMIT:
            hops.stamp("cy.submit")
            _, cid, fields = msg
            cmd = decode_command(fields, functools.partial(self._on_outcome, cid))
            accepted = self.cycle.submit(cmd)
            self._try_send(dumps((Msg.SUBMITTED.value, cid, accepted, self.cycle.state)))
        elif kind is Msg.TRIGGER:
            _, group, reason = msg
            self.cycle.trigger_group(group, reason)
        elif kind is Msg.SIM:
            _, call_id, action, position, args = msg
            try:
                result = (True, str(self.sim_handlers[action](position, args)))
            except Exception as exc:  # refused: the child answers reply_err with this text
                result = (False, str(exc) or type(exc).__name__)
            self._try_send(dumps((Msg.SIM_RESULT.value, call_id, *result)))
        elif kind is Msg.RECORD:
            # Copying (or waiting for a window to close) must not hold up commands: own thread.
            threading.Thread(target=self._record, args=msg[1:], name="bridge-record", daemon=True).start()
        elif kind is Msg.READY:
            self._ready.set()
        elif kind is Msg.FAILED:
            _, what, text = msg
            self._failed = (what, text)
            self._ready.set()
        else:
            log.warning("gateway %s: unexpected bridge message %s", self.host, kind.name)

    def _record(self, call_id: int, what: str, last_s: float, timeout_s: float) -> None:
        try:
            result: tuple = (True, self.cycle.recording(what, last_s, timeout_s))
        except Exception as exc:  # refused or unavailable: the child answers reply_err with this text
            result = (False, str(exc) or type(exc).__name__)
        self._try_send(dumps((Msg.RECORD_RESULT.value, call_id, *result)))

    def _lost(self, why: str) -> None:
        if self.lost_reason is not None or self._closing.is_set():
            return
        code = None
        if self.proc is not None:
            try:
                code = self.proc.wait(1.0)
            except subprocess.TimeoutExpired:
                self._kill()
                code = self.proc.returncode
        self.lost_reason = f"gateway process {self.pid} lost ({why}; {_exit_text(code)})"
        log.error("agent %s: %s: nobody can command or watch the drives: ordered shutdown", self.host,
                  self.lost_reason)
        if self.on_lost is not None:
            self.on_lost(self.lost_reason)
        self._wake.set()


def _exit_text(code: int | None) -> str:
    if code is None:
        return "exit status unknown"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"



if __name__ == "__main__":
    # Run the importable module's copy (its logger name and classes), not this __main__ copy.
    from bus_agent.gateway.child import child_main as _main

    sys.exit(_main())
