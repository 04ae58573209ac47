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
DriveCommand/AgentCommand fields without the callback), group triggers, sim control calls.
``CycleProxy.submit`` is a synchronous round trip (the real ``Cycle.submit`` answer and the
cycle's state), so "inbox full" and "agent stopping" reach the gateway exactly as in-process.

Loss: if the child dies, ``GatewayProcess`` calls ``on_lost`` (the agent runs the ordered
shutdown of every drive and exits non-zero: nobody can command or watch the drives any more)
and from then on logs the cycle's events. If the cycle process dies, the child reads EOF and
exits at once (its links close, so peers drop the agent's liveliness token).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import itertools
import logging
import operator
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from enum import IntEnum
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from bus_agent import runtime as rt
from bus_agent.cycle.realtime import set_thread_fifo

log = logging.getLogger(__name__)

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


def decode_snapshot(t: Sequence[Any], events: tuple[rt.CycleEvent, ...] = ()) -> rt.CycleSnapshot:
    cycle, time_ns, agent_state, stats, drives = t
    return rt.CycleSnapshot(cycle=cycle, time_ns=time_ns, drives=tuple(rt.DriveSnapshot(*d) for d in drives),
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
        self._latest = snap
        if snap.events:
            self._events.extend((ev, snap.cycle, snap.time_ns) for ev in snap.events)
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
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "bus_agent.gateway.bridge", "--fd", str(theirs.fileno()),
                 "--log-level", logging.getLevelName(self.log_level)],
                pass_fds=(theirs.fileno(),), env=env, stdin=subprocess.DEVNULL)
        except OSError as exc:
            ours.close()
            raise BridgeError("gateway", f"cannot start the gateway process: {exc}") from None
        finally:
            theirs.close()  # the child's end lives in the child only: its death is our EOF
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


# ---- gateway process side ---------------------------------------------------------------------------


class CycleProxy:
    """The Cycle surface the gateway uses (``gateway.CycleLike``), in the gateway process.

    ``submit`` is a round trip to the cycle process (at most ``SUBMIT_TIMEOUT_S``; no answer =
    refused); ``trigger_group`` is one message; ``snapshot_sink``/``event_sink`` are called from
    the reader thread with forwarded snapshots and events; outcomes reach each command's
    ``on_outcome`` from the reader thread too.
    """

    def __init__(self, conn: Connection, axes: Sequence[str]) -> None:
        self._conn = conn
        self.axes = tuple(axes)
        self.snapshot_sink: Callable[[rt.CycleSnapshot], None] | None = None
        self.event_sink: Callable[[list[tuple[rt.CycleEvent, int, int]]], None] | None = None
        self.group_sink: Callable[[str, str], None] | None = None  # the cycle process does not forward it
        self.latest: rt.CycleSnapshot | None = None
        self.state = "running"
        self._send_lock = threading.Lock()
        self._ids = itertools.count(1)
        self._callbacks: dict[int, list] = {}   # cid -> [on_outcome, outcomes still expected]
        self._answers: dict[int, list] = {}     # cid/call id -> [Event, answer]
        self._lock = threading.Lock()

    def stats(self) -> rt.CycleStats:
        return self.latest.stats if self.latest is not None else rt.CycleStats()

    def _send(self, data: bytes) -> None:
        with self._send_lock:
            self._conn.send_bytes(data)

    def _round_trip(self, key: int, data: bytes, timeout_s: float) -> Any:
        done = threading.Event()
        slot: list[Any] = [done, None]
        with self._lock:
            self._answers[key] = slot
        try:
            self._send(data)
            if not done.wait(timeout_s):
                return None
            return slot[1]
        except OSError:
            return None
        finally:
            with self._lock:
                self._answers.pop(key, None)

    def submit(self, cmd: rt.DriveCommand | rt.AgentCommand) -> bool:
        cid = next(self._ids)
        expected = len(cmd.axes) if isinstance(cmd, rt.DriveCommand) else 1
        with self._lock:
            self._callbacks[cid] = [cmd.on_outcome, expected]
        answer = self._round_trip(cid, encode_command(cid, cmd), SUBMIT_TIMEOUT_S)
        if answer is None:
            self.state = "error"  # why submit said no (Gateway._refused reads it)
            accepted = False
        else:
            accepted, self.state = answer
        if not accepted:
            with self._lock:
                self._callbacks.pop(cid, None)
        return accepted

    def trigger_group(self, group: str, reason: str) -> None:
        try:
            self._send(dumps((Msg.TRIGGER.value, group, reason)))
        except OSError as exc:
            log.error("group %s trigger not delivered to the cycle: %s", group, exc)

    def sim_call(self, action: str, position: int, args: dict, timeout_s: float = 5.0) -> str:
        """Run a simulator control handler in the cycle process; raises ValueError if refused."""
        call_id = -next(self._ids)
        answer = self._round_trip(call_id, dumps((Msg.SIM.value, call_id, action, position, args)), timeout_s)
        if answer is None:
            raise ValueError("the cycle process did not answer")
        ok, text = answer
        if not ok:
            raise ValueError(text)
        return text

    def recording(self, what: str, last_s: float, timeout_s: float) -> Any:
        """A flight recording from the cycle process (``Cycle.recording``); raises LookupError."""
        call_id = -next(self._ids)
        answer = self._round_trip(call_id, dumps((Msg.RECORD.value, call_id, what, last_s, timeout_s)),
                                  timeout_s + RECORD_MARGIN_S)
        if answer is None:
            raise LookupError("the cycle process did not answer with a recording in time")
        ok, value = answer
        if not ok:
            raise LookupError(value)
        return value

    # reader thread

    def dispatch(self, msg: tuple) -> None:
        kind = msg[0]
        if kind is Msg.UPDATE:
            _, snap_t, events_t, outcomes_t = msg
            events = [decode_event(e) for e in events_t]
            if snap_t is not None:
                snap = decode_snapshot(snap_t, () if self.event_sink is not None
                                       else tuple(e for e, _, _ in events))
                self.latest = snap
                self.state = snap.agent_state
            # Outcomes first: the sinks wake the publish thread, whose pass (a status put per
            # changed drive, an event put per event) would otherwise hold the GIL while the
            # command thread waits to send the replies.
            for cid, o in outcomes_t:
                self._deliver(cid, decode_outcome(o))
            if events and self.event_sink is not None:
                self.event_sink(events)
            if snap_t is not None and self.snapshot_sink is not None and self.latest is not None:
                self.snapshot_sink(self.latest)
        elif kind in (Msg.SUBMITTED, Msg.SIM_RESULT, Msg.RECORD_RESULT):
            with self._lock:
                slot = self._answers.get(msg[1])
            if slot is not None:
                slot[1] = tuple(msg[2:])
                slot[0].set()

    def _deliver(self, cid: int, outcome: rt.Outcome) -> None:
        with self._lock:
            entry = self._callbacks.get(cid)
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] <= 0:
                del self._callbacks[cid]
        try:
            entry[0](outcome)
        except Exception:
            log.exception("on_outcome of command %d failed", cid)


def child_main(argv: Sequence[str] | None = None) -> int:
    """The gateway process: ``python -m bus_agent.gateway.bridge --fd N [--log-level L]``."""
    p = argparse.ArgumentParser(prog="python -m bus_agent.gateway.bridge")
    p.add_argument("--fd", type=int, required=True, help="this end of the socketpair to the cycle process")
    p.add_argument("--log-level", default="INFO")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s[gw]: %(message)s")
    # The cycle process decides when to stop (after the ordered shutdown, while we still publish).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    conn = Connection(args.fd)
    try:
        kind, settings, zcfg, sim = loads(conn.recv_bytes())
    except (EOFError, OSError, ValueError) as exc:
        log.error("gateway process: no start message from the cycle process: %s", exc)
        return 1
    assert kind is Msg.INIT

    def fail(what: str, text: str) -> int:
        try:
            conn.send_bytes(dumps((Msg.FAILED.value, what, text)))
        except OSError:
            pass
        return 3

    host = settings["host"]
    proxy = CycleProxy(conn, settings["axes"])
    done = threading.Event()
    ending: list[str] = []
    gws: list[Any] = []   # the gateway, once declared

    def reader() -> None:
        while True:
            try:
                msg = loads(conn.recv_bytes())
            except (EOFError, OSError):
                ending.append("eof")
                break
            except Exception:
                log.exception("gateway %s: undecodable bridge message", host)
                continue
            if msg[0] is Msg.CLOSE:
                ending.append("close")
                break
            if msg[0] is Msg.STOPPING:
                for gw in gws:
                    gw.stop_commands()
                    gw.agent_state_override = "stopping"
                continue
            try:
                proxy.dispatch(msg)
            except Exception:
                log.exception("gateway %s: bridge message %s failed", host, msg[0].name)
        done.set()

    # Reading starts now: snapshots sent while the session opens are taken (the latest is kept).
    threading.Thread(target=reader, name="bridge-reader", daemon=True).start()

    import zenoh

    from bus_agent.gateway.gateway import Gateway, GatewaySettings
    from bus_agent.gateway.zenoh_config import ZenohConfigError, from_settings
    from schemas import keys

    try:
        session = zenoh.open(from_settings(zcfg))
    except (ZenohConfigError, zenoh.ZError) as exc:
        return fail("zenoh", str(exc))
    # One round trip to the peers/routers before the first publication: it returns after the
    # declarations they sent on connecting (their subscribers), so the first status (published
    # in the gateway's first pass) is not dropped for want of a known subscriber.
    try:
        for _ in session.liveliness().get(keys.ALL_ALIVE, timeout=1.0):
            pass
    except Exception as exc:
        log.debug("gateway %s: liveliness get: %s", host, exc)
    sim_control = None
    try:
        gw = Gateway(session, proxy, GatewaySettings(**settings))
        gw.start()
        gws.append(gw)
        if sim is not None:
            from bus_agent.sim.control import SimControl

            segment, n_slaves, actions = sim
            handlers = {a: functools.partial(_sim_handler, proxy, a) for a in actions}
            sim_control = SimControl(session, segment, handlers, n_slaves)
    except Exception as exc:
        log.exception("gateway %s: start-up failed", host)
        session.close()
        return fail("gateway", str(exc))
    conn.send_bytes(dumps((Msg.READY.value,)))
    done.wait()
    if not (ending and ending[0] == "close"):
        # The cycle process is gone (its drives stop through their SM watchdog). Exit at once:
        # the kernel closes our links, so every peer drops this agent's liveliness token now,
        # as if the whole agent had crashed; a Python-level session close only adds delay.
        log.error("gateway %s: the cycle process is gone: exiting", host)
        logging.shutdown()
        os._exit(1)
    gw.close()
    if sim_control is not None:
        sim_control.close()
    try:
        session.close()
    except Exception as exc:
        log.warning("gateway %s: zenoh session close: %s", host, exc)
    log.info("gateway %s: closed", host)
    return 0


def _sim_handler(proxy: CycleProxy, action: str, position: int, args: dict) -> str:
    return proxy.sim_call(action, position, args)


if __name__ == "__main__":
    # Run the importable module's copy (its logger name and classes), not this __main__ copy.
    from bus_agent.gateway.bridge import child_main as _main

    sys.exit(_main())
