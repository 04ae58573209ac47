"""The gateway process: ``python -m bus_agent.gateway.bridge --fd N`` runs :func:`child_main`.

It opens the Zenoh session and runs an unchanged :class:`~bus_agent.gateway.gateway.Gateway`
against :class:`CycleProxy`, which has exactly the Cycle surface the gateway uses, over the
socketpair to the cycle process (:mod:`bus_agent.gateway.bridge`).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import logging
import os
import signal
import socket
import sys
import threading
from multiprocessing.connection import Connection
from typing import Any, Callable, Sequence

from bus_agent import hops
from bus_agent import runtime as rt
from bus_agent.cycle.realtime import name_thread, set_thread_fifo
from bus_agent.gateway.wire import (RECORD_MARGIN_S, SUBMIT_TIMEOUT_S, Msg, decode_event, decode_outcome, decode_snapshot,
                                    dumps, encode_command, loads)

log = logging.getLogger("bus_agent.gateway.bridge")

#: The gateway process's GIL switch interval (Python's default is 5 ms). How long ``gw-command``,
#: woken with a batch of outcomes, may wait for the reader or the publisher to let go of the GIL:
#: 64-drive enables, two alternating pairs at load 2.6-2.9, outcomes handed over -> taken up by
#: ``gw-command`` 1.38 and 1.37 ms at 0.5 ms, 1.0 and 0.78 ms at 0.1 ms; gateway CPU per round
#: unchanged (21-23 against 20-25 ms).
GIL_SWITCH_INTERVAL_S = 0.0001
#: Name prefixes of zenoh's runtime threads (its pools: app, acc, tx, rx, net).
ZENOH_THREADS = ("app-", "acc-", "tx-", "rx-", "net-")
#: How often the gateway process looks for new zenoh threads to schedule (:func:`zenoh_threads_fifo`).
ZENOH_SCAN_S = 1.0

# ---- gateway process side ---------------------------------------------------------------------------


class CycleProxy:
    """The Cycle surface the gateway uses (``gateway.CycleLike``), in the gateway process.

    ``submit`` is a round trip to the cycle process (at most ``SUBMIT_TIMEOUT_S``; no answer =
    refused); ``trigger_group`` is one message; ``snapshot_sink``/``event_sink`` are called from
    the reader thread with forwarded snapshots and events; outcomes reach each command's
    ``on_outcome`` from the reader thread too. ``bad_sink`` gets each forwarded snapshot first,
    before the sinks wake the publish thread (the gateway publishes a fault or loss from there).
    """

    def __init__(self, conn: Connection, axes: Sequence[str]) -> None:
        self._conn = conn
        self.axes = tuple(axes)
        self.snapshot_sink: Callable[[rt.CycleSnapshot], None] | None = None
        self.event_sink: Callable[[list[tuple[rt.CycleEvent, int, int]]], None] | None = None
        self.group_sink: Callable[[str, str], None] | None = None  # the cycle process does not forward it
        self.bad_sink: Callable[[rt.CycleSnapshot], None] | None = None
        self.latest: rt.CycleSnapshot | None = None
        # The last snapshot tuple read and its snapshot: unchanged drives keep their objects.
        self._previous: tuple[Any, rt.CycleSnapshot] | None = None
        #: Group triggers as datagrams straight to the cycle thread; None: Msg.TRIGGER to bridge-in.
        self.trigger_sock: socket.socket | None = None
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
        hops.stamp("gw.answer")
        if answer is None:
            self.state = "error"  # why submit said no (the command path's refusal text reads it)
            accepted = False
        else:
            accepted, self.state = answer
        if not accepted:
            with self._lock:
                self._callbacks.pop(cid, None)
        return accepted

    def trigger_group(self, group: str, reason: str) -> None:
        try:
            if self.trigger_sock is not None:  # to the cycle thread itself (Cycle.trigger_socket)
                self.trigger_sock.send(f"{group}\0{reason}".encode("utf-8", "replace")[:4096])
            else:
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
            if outcomes_t or events_t:
                hops.stamp("gw.update" if outcomes_t else "gw.update.ev")
            # Outcomes first, before decoding the snapshot (64 drives: a fraction of a millisecond)
            # and before the sinks wake the publish thread, whose pass (a status put per changed
            # drive, an event put per event) would otherwise hold the GIL while the command thread
            # waits to send the replies.
            for cid, o in outcomes_t:
                self._deliver(cid, decode_outcome(o))
            if outcomes_t:
                hops.stamp("gw.delivered")
            events = [decode_event(e) for e in events_t]
            if snap_t is not None:
                snap = decode_snapshot(snap_t, () if self.event_sink is not None
                                       else tuple(e for e, _, _ in events), self._previous)
                self._previous = (snap_t, snap)
                self.latest = snap
                self.state = snap.agent_state
                if self.bad_sink is not None:
                    # Before the sinks: they wake the publish thread, which (at real-time priority)
                    # took the GIL and the publish lock from here and held a fault's status up
                    # behind its own pass by a few hundred microseconds (bench_reflex's hops).
                    self.bad_sink(snap)
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
    p.add_argument("--trigger-fd", type=int, help="this end of the datagram socketpair for group triggers")
    p.add_argument("--log-level", default="INFO")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s[gw]: %(message)s")
    # The cycle process decides when to stop (after the ordered shutdown, while we still publish).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # Threads here (reader, publish, command, zenoh callbacks) hand the GIL back and forth around
    # every zenoh call; a shorter switch interval bounds how long a reply waits for a busy thread.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
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
    if args.trigger_fd is not None:
        proxy.trigger_sock = socket.socket(fileno=args.trigger_fd)
    done = threading.Event()
    ending: list[str] = []
    gws: list[Any] = []   # the gateway, once declared

    def publish_bad(snap: rt.CycleSnapshot) -> None:
        for gw in gws:
            gw.publisher.publish_bad_now(snap)

    proxy.bad_sink = publish_bad

    def reader() -> None:
        name_thread("bridge-reader")
        set_thread_fifo(settings.get("rt_priority", 0), f"bridge-reader of {host}")
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
                proxy.dispatch(msg)  # a fault or loss goes out first, from here (bad_sink)
            except Exception:
                log.exception("gateway %s: bridge message %s failed", host, msg[0].name)
        done.set()

    # Reading starts now: snapshots sent while the session opens are taken (the latest is kept).
    threading.Thread(target=reader, name="bridge-reader", daemon=True).start()

    import zenoh

    from bus_agent.gateway.gateway import Gateway, GatewaySettings
    from bus_agent.gateway.hostclaim import claim_config
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
        gw = Gateway(session, proxy, GatewaySettings(**settings), claim_config=claim_config(zcfg))
        gw.start()
        gws.append(gw)
        if settings.get("rt_priority", 0):
            threading.Thread(target=_zenoh_threads_loop, args=(settings["rt_priority"], done), name="gw-sched",
                             daemon=True).start()
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
        hops.write()  # os._exit skips atexit
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


def zenoh_threads_fifo(priority: int, seen: set[int]) -> int:
    """Put this process's zenoh runtime threads (:data:`ZENOH_THREADS`) not in ``seen`` under
    SCHED_FIFO ``priority``; returns how many. Linux only; a refusal is logged once per thread.

    The gateway's own threads run under SCHED_FIFO (``GatewaySettings.rt_priority``); zenoh's
    threads, which carry every reply and put to the network, did not, so while ``gw-command``
    answered 16 drives they waited for a free core: the first reply left after the last one
    was handed over (docs/agent-gateway.md, "Where the time goes")."""
    n = 0
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return 0
    for tid in tids:
        if tid in seen:
            continue
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                name = f.read().strip()
        except OSError:
            continue  # ended meanwhile
        if not name.startswith(ZENOH_THREADS):
            continue
        seen.add(tid)
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            n += 1
        except OSError as exc:
            log.warning("zenoh thread %s (%d): SCHED_FIFO %d refused: %s", name, tid, priority, exc)
    return n


def _zenoh_threads_loop(priority: int, done: threading.Event) -> None:
    """Thread ``gw-sched``: zenoh starts some runtime pools on first use (a peer's first link),
    so new threads are looked for every :data:`ZENOH_SCAN_S` (a directory listing)."""
    name_thread("gw-sched")
    seen: set[int] = set()
    while True:
        zenoh_threads_fifo(priority, seen)
        if done.wait(ZENOH_SCAN_S):
            return


def _sim_handler(proxy: CycleProxy, action: str, position: int, args: dict) -> str:
    return proxy.sim_call(action, position, args)
