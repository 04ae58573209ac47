"""Fault injection and inspection of a running ``ecat-sim`` (JSON requests).

A request is a JSON object ``{"action": ..., ...}``; the reply ``{"ok": true, ...}`` or
``{"ok": false, "error": "..."}``. Bad input changes nothing. Actions:

- ``ping`` -> slaves count and segment name; ``status`` -> per-slave AL/drive snapshot and counters
- ``fault {slave, error_code}``: the drive model detects a fault (CiA 402 transition 13, EMCY)
- ``unplug {slave}`` / ``plug {slave}``: the slave stops answering / comes back reset in INIT
- ``drop_frames {count | ratio}``: drop the next ``count`` frames, or each with probability ``ratio``
- ``delay_frames {count, delay_ms}``: answer the next ``count`` frames ``delay_ms`` late
- ``wkc_fault {slave, on}``: the slave's process data stops counting in the working counter
- ``mute_sdo {slave, index, subindex, skip, count}``: of the slave's SDO uploads of that object,
  answer the next ``skip``, then give the ``count`` after them no answer (a lost mailbox answer)
- ``refuse_sdo {slave, index, subindex, abort}``: every SDO transfer of that object is aborted
  with ``abort`` (e.g. 0x06020000, a drive without the object); ``abort`` 0 lifts it
- ``bad_sii {slave, before}``: the slave's SII (its EEPROM) gets a category whose length sends
  SOEM's category walk back to its own header for ever, before the ``general`` category
  (config_init loops) or the ``pdo`` ones (config_map loops for a slave whose PDO sizes CoE did
  not give); kept until the simulator ends

Transports: a UNIX datagram socket (path) or a TCP loopback port (one JSON object per line).
"""

from __future__ import annotations

import json
import logging
import os
import socket
from typing import BinaryIO, Callable

from bus_agent.sim.ecat.frameloop import FrameLoop
from bus_agent.sim.ecat.sii import LOOP_BEFORE, looping_sii

log = logging.getLogger(__name__)

ACTIONS = ("ping", "status", "fault", "unplug", "plug", "drop_frames", "delay_frames", "wkc_fault", "mute_sdo",
           "refuse_sdo", "bad_sii")


class ControlError(ValueError):
    pass


def _int(req: dict, key: str, lo: int, hi: int) -> int:
    value = req.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ControlError(f"{key} must be an integer in {lo}..{hi}, got {value!r}")
    return value


def apply_action(loop: FrameLoop, name: str, req: dict) -> dict:
    """Validate and apply one control request to the running loop (loop thread only)."""
    seg = loop.segment
    n = len(seg.escs)
    try:
        action = req.get("action")
        if action not in ACTIONS:
            raise ControlError(f"unknown action {action!r}; known: {', '.join(ACTIONS)}")
        if action == "ping":
            return {"ok": True, "slaves": n, "segment": name, "ifname": loop.ifname}
        if action == "status":
            return {"ok": True, "segment": name, "slaves": seg.status(), "counters": dict(loop.counters)}
        if action == "fault":
            slave = _int(req, "slave", 0, n - 1)
            code = _int(req, "error_code", 1, 0xFFFF)
            seg.escs[slave].model.inject_fault(code)
        elif action == "unplug":
            seg.unplug(_int(req, "slave", 0, n - 1))
        elif action == "plug":
            seg.plug(_int(req, "slave", 0, n - 1))
        elif action == "drop_frames":
            if "ratio" in req:
                ratio = req["ratio"]
                if not isinstance(ratio, (int, float)) or isinstance(ratio, bool) or not 0.0 <= ratio <= 1.0:
                    raise ControlError(f"ratio must be a number in 0..1, got {ratio!r}")
                loop.faults.drop_ratio = float(ratio)
            else:
                loop.faults.drop_count = _int(req, "count", 0, 1_000_000)
        elif action == "delay_frames":
            count = _int(req, "count", 0, 1_000_000)
            delay = req.get("delay_ms")
            if not isinstance(delay, (int, float)) or isinstance(delay, bool) or not 0 <= delay <= 10_000:
                raise ControlError(f"delay_ms must be a number in 0..10000, got {delay!r}")
            loop.faults.delay_count, loop.faults.delay_s = count, delay / 1000.0
        elif action == "wkc_fault":
            slave = _int(req, "slave", 0, n - 1)
            on = req.get("on")
            if not isinstance(on, bool):
                raise ControlError(f"on must be true or false, got {on!r}")
            seg.set_wkc_fault(slave, on)
        elif action == "mute_sdo":
            slave = _int(req, "slave", 0, n - 1)
            mute = [_int(req, "index", 0, 0xFFFF), _int(req, "subindex", 0, 0xFF), _int(req, "skip", 0, 1000),
                    _int(req, "count", 1, 1000)]
            seg.escs[slave].mailbox.mute = mute
        elif action == "refuse_sdo":
            slave = _int(req, "slave", 0, n - 1)
            key = (_int(req, "index", 0, 0xFFFF), _int(req, "subindex", 0, 0xFF))
            abort = _int(req, "abort", 0, 0xFFFFFFFF)
            refuse = seg.escs[slave].mailbox.refuse
            if abort:
                refuse[key] = abort
            else:
                refuse.pop(key, None)
        elif action == "bad_sii":
            slave = _int(req, "slave", 0, n - 1)
            before = req.get("before")
            if before not in LOOP_BEFORE:
                raise ControlError(f"before must be one of {', '.join(LOOP_BEFORE)}, got {before!r}")
            esc = seg.escs[slave]
            esc.sii[:] = looping_sii(esc.sii, before)
        log.info("control: %s", req)
        return {"ok": True}
    except ControlError as exc:
        return {"ok": False, "error": str(exc)}
    except Exception as exc:  # never let a control request stop the segment
        log.exception("control request %r failed", req)
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}


def _decode(data: bytes) -> dict | None:
    try:
        req = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        return None
    return req if isinstance(req, dict) else None


class UnixControl:
    """UNIX datagram server: one JSON request per datagram, the reply to the sender."""

    def __init__(self, path: str):
        self.path = path
        if os.path.exists(path):
            os.unlink(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.setblocking(False)

    def poll(self, handle: Callable[[dict], dict]) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(65536)
            except BlockingIOError:
                return
            req = _decode(data)
            reply = handle(req) if req is not None else {"ok": False, "error": "request is not a JSON object"}
            if addr:
                try:
                    self.sock.sendto(json.dumps(reply).encode(), addr)
                except OSError as exc:
                    log.debug("control reply to %s lost: %s", addr, exc)

    def close(self) -> None:
        self.sock.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


class TcpControl:
    """TCP server on 127.0.0.1: newline-delimited JSON requests and replies."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.listen(8)
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.clients: dict[socket.socket, bytearray] = {}

    def poll(self, handle: Callable[[dict], dict]) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except BlockingIOError:
                break
            conn.setblocking(False)
            self.clients[conn] = bytearray()
        for conn, pending in list(self.clients.items()):
            try:
                data = conn.recv(65536)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if not data:
                conn.close()
                del self.clients[conn]
                continue
            pending += data
            while b"\n" in pending:
                line, _, rest = bytes(pending).partition(b"\n")
                pending[:] = rest
                req = _decode(line)
                reply = handle(req) if req is not None else {"ok": False, "error": "request is not a JSON object"}
                try:
                    conn.sendall(json.dumps(reply).encode() + b"\n")
                except OSError:
                    pass

    def close(self) -> None:
        for conn in self.clients:
            conn.close()
        self.sock.close()


class ControlClient:
    """Client for either transport: ``ControlClient("/run/x.sock")`` or ``ControlClient(5555)``."""

    def __init__(self, where: str | int, timeout: float = 2.0):
        self.where = where
        self.timeout = timeout
        self._tcp: socket.socket | None = None
        self._unix: socket.socket | None = None
        self._rfile: BinaryIO | None = None

    def request(self, action: str, **args) -> dict:
        payload = json.dumps({"action": action, **args}).encode()
        if isinstance(self.where, int) or str(self.where).isdigit():
            if self._tcp is None:
                self._tcp = socket.create_connection(("127.0.0.1", int(self.where)), timeout=self.timeout)
                self._rfile = self._tcp.makefile("rb")
            self._tcp.sendall(payload + b"\n")
            assert self._rfile is not None
            line = self._rfile.readline()
            if not line:
                raise ConnectionError("control connection closed")
            return json.loads(line)
        if self._unix is None:
            self._unix = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._unix.bind("")  # autobind: an abstract address the server can answer
            self._unix.settimeout(self.timeout)
        self._unix.sendto(payload, str(self.where))
        return json.loads(self._unix.recv(65536))

    def close(self) -> None:
        for s in (self._rfile, self._tcp, self._unix):
            if s is not None:
                s.close()
        self._tcp = self._unix = self._rfile = None
