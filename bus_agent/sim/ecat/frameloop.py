"""The emulator's frame loop: one AF_PACKET socket, answer every frame at once or never.

Imperative shell around :class:`~bus_agent.sim.ecat.segment.Segment`: receive into a
preallocated buffer, drop frames that waited too long in the socket (SOEM may already have
reused their index: a late answer would be taken for a newer request), answer in place with
the request's exact length, then do application work (drive models, watchdogs, control
requests) while no frame is waiting.
"""

from __future__ import annotations

import fcntl
import gc
import logging
import random
import socket
import struct
import time
from collections import deque
from typing import Callable, Protocol

from bus_agent.sim.ecat.segment import Segment

log = logging.getLogger(__name__)

ETH_P_ECAT = 0x88A4
SIOCGSTAMP = 0x8906
TIMEVAL = struct.Struct("@qq")


class ControlChannel(Protocol):
    def poll(self, handle: Callable[[dict], dict]) -> None: ...

    def close(self) -> None: ...


class FaultInjection:
    """Frame-level faults requested through the control interface."""

    def __init__(self) -> None:
        self.drop_count = 0
        self.drop_ratio = 0.0
        self.delay_count = 0
        self.delay_s = 0.0
        self.rng = random.Random(0x88A4)


class FrameLoop:
    """Serve ``segment`` on ``ifname`` until :meth:`stop` (or SIGTERM in the CLI)."""

    def __init__(self, segment: Segment, ifname: str, *, step_s: float = 0.001, idle_step_s: float = 0.01,
                 stale_s: float = 0.0018, step_budget: int = 8):
        self.segment = segment
        self.ifname = ifname
        self.step_s = step_s
        self.idle_step_s = idle_step_s
        self.stale_s = stale_s
        self.step_budget = step_budget
        self.faults = FaultInjection()
        self.controls: list[ControlChannel] = []
        self.handle_control: Callable[[dict], dict] = lambda req: {"ok": False, "error": "no handler"}
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ECAT))
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind((ifname, ETH_P_ECAT))
        self._buf = bytearray(2048)
        self._mv = memoryview(self._buf)
        self._stamp = bytearray(TIMEVAL.size)
        self._delayed: deque[tuple[float, bytes]] = deque()
        self._running = False
        self.counters = {"frames": 0, "answered": 0, "stale": 0, "dropped": 0, "delayed": 0, "bad": 0}

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self.sock.close()
        for c in self.controls:
            c.close()

    def _age(self, now_wall: float) -> float:
        # kernel receive timestamp of the last frame (enables timestamping on first use)
        fcntl.ioctl(self.sock.fileno(), SIOCGSTAMP, self._stamp, True)
        sec, usec = TIMEVAL.unpack_from(self._stamp)
        return now_wall - (sec + usec * 1e-6)

    def run(self, on_ready: Callable[[], None] | None = None) -> None:
        sock, buf, mv, seg, faults, counters = self.sock, self._buf, self._mv, self.segment, self.faults, self.counters
        recv_into, send = sock.recv_into, sock.send
        process = seg.process
        monotonic, wall = time.monotonic, time.time
        stale_s = self.stale_s
        last_ctrl = monotonic()
        busy = False  # a model-step round is under way: poll, do not sleep
        drain = False  # a frame was just answered: look for the next one before other work
        self._running = True
        gc.collect()
        gc.freeze()  # everything built so far is immortal: the collector never scans it
        gc.disable()
        if on_ready:
            on_ready()
        timeout = None
        try:
            while self._running:
                active = seg.any_active()
                want = 0.0 if busy or drain else (self.step_s if active or self._delayed else self.idle_step_s)
                if self._delayed:
                    want = min(want, max(0.0, self._delayed[0][0] - monotonic()))
                if want != timeout:
                    timeout = want
                    sock.settimeout(timeout)
                try:
                    n = recv_into(buf)
                except (TimeoutError, BlockingIOError):
                    n = 0
                now = monotonic()
                if n:
                    counters["frames"] += 1
                    if stale_s and self._age(wall()) > stale_s:
                        counters["stale"] += 1
                    elif faults.drop_count or faults.drop_ratio:
                        if faults.drop_count:
                            faults.drop_count -= 1
                            counters["dropped"] += 1
                        elif faults.rng.random() < faults.drop_ratio:
                            counters["dropped"] += 1
                        elif process(mv, n, now):
                            send(mv[:n])
                            counters["answered"] += 1
                    elif process(mv, n, now):
                        if faults.delay_count:
                            faults.delay_count -= 1
                            counters["delayed"] += 1
                            self._delayed.append((now + faults.delay_s, bytes(mv[:n])))
                        else:
                            send(mv[:n])
                            counters["answered"] += 1
                    else:
                        counters["bad"] += 1
                    drain = True
                    continue  # answer back-to-back frames (multi-frame cycles) first
                drain = False
                while self._delayed and self._delayed[0][0] <= now:
                    send(self._delayed.popleft()[1])
                was_busy = busy
                busy = seg.step_some(now, self.step_s if active else self.idle_step_s, self.step_budget)
                if was_busy and not busy:
                    seg.check_watchdogs(monotonic())
                if now - last_ctrl >= 0.005:
                    last_ctrl = now
                    seg.check_watchdogs(now)
                    for channel in self.controls:
                        channel.poll(self.handle_control)
                    gc.collect(0)  # young objects only, off the hot path
        finally:
            gc.enable()
            gc.unfreeze()
