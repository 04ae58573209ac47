"""A CAN test bed: a network namespace with only ``lo`` (multicast routed on it), where the CAN
processes of one test talk over python-can's ``udp_multicast`` interface.

python-can's udp_multicast sets the hop limit / TTL to 1 and binds on every interface; in this
namespace there is no other interface, so no frame can leave it (and the namespace's own group
address cannot collide with another test's). Root only; the namespace is named per pid.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Sequence

from bus_agent.sim.child import ChildProcess, wait_for
from bus_agent.sim.netns import netns_add, netns_del

CHANNEL = "239.74.163.12"
LISTENER = """
import can, json, sys
bus = can.Bus(interface="udp_multicast", channel=sys.argv[1], fd=False)
print("listening", flush=True)
while True:
    m = bus.recv(1.0)
    if m is not None:
        print(json.dumps({"id": m.arbitration_id, "data": m.data.hex(), "t": m.timestamp}), flush=True)
"""


class CanBed:
    """One namespace; ``run``/``spawn`` put processes in it."""

    def __init__(self, tag: str) -> None:
        self.netns = f"zc{tag}{os.getpid() % 100000}"
        netns_add(self.netns)
        subprocess.run(["ip", "-n", self.netns, "link", "set", "lo", "multicast", "on"], check=True)
        subprocess.run(["ip", "-n", self.netns, "route", "add", "224.0.0.0/4", "dev", "lo"], check=True)
        self.children: list[ChildProcess] = []
        self.sockets: list[str] = []

    def argv(self, *argv: str) -> list[str]:
        return ["ip", "netns", "exec", self.netns, *argv]

    def spawn(self, name: str, argv: Sequence[str], ready: str, timeout_s: float = 30.0) -> ChildProcess:
        p = ChildProcess(name, self.argv(*argv), ready_marker=ready)
        self.children.append(p)
        p.expect_ready(timeout_s)
        return p

    def module(self, name: str, module: str, *args: str, ready: str, timeout_s: float = 30.0) -> ChildProcess:
        return self.spawn(name, [sys.executable, "-m", module, *args], ready, timeout_s)

    def listener(self, channel: str = CHANNEL) -> "FrameLog":
        p = FrameLog("can-listener", self.argv(sys.executable, "-c", LISTENER, channel), ready_marker="listening")
        self.children.append(p)
        p.expect_ready(20)
        return p

    def run(self, *argv: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
        from bus_agent.sim.child import child_env

        return subprocess.run(self.argv(*argv), capture_output=True, text=True, timeout=timeout_s, env=child_env())

    def unix_endpoint(self, name: str) -> str:
        """A Zenoh endpoint on a UNIX socket: the file system is shared with the test process, so
        it reaches into the namespace without any network route."""
        path = f"/tmp/{self.netns}-{name}.sock"
        if os.path.exists(path):
            os.unlink(path)
        self.sockets.append(path)
        return f"unixsock-stream/{path}"

    def drivectl(self, endpoint: str, *args: str) -> tuple[int, str]:
        """``drivectl --connect EP ...`` inside the namespace: (exit code, stdout + stderr)."""
        r = self.run(sys.executable, "-m", "supervisor.cli", "--connect", endpoint, *args)
        return r.returncode, r.stdout + r.stderr

    def states(self, endpoint: str) -> dict[str, dict]:
        """``drivectl --json status`` as {"host/axis": row}."""
        rc, out = self.drivectl(endpoint, "--json", "status")
        assert rc == 0, out
        doc = json.loads(out)
        rows = doc["drives"] if isinstance(doc, dict) else doc
        return {f"{r['host']}/{r['axis']}": r for r in rows}

    def close(self) -> None:
        for p in reversed(self.children):
            p.stop(10)
            if not isinstance(p, FrameLog):  # shown by pytest when a test failed
                print(f"---- {p.name} (exit {p.popen.poll()}):\n{p.output(60)}")
        netns_del(self.netns)
        for path in self.sockets:
            if os.path.exists(path):
                os.unlink(path)


class FrameLog(ChildProcess):
    """A plain python-can listener: every frame on the channel as (COB-ID, data)."""

    def frames(self) -> list[tuple[int, bytes]]:
        out = []
        for line in list(self.lines):
            if line.startswith("{"):
                f = json.loads(line)
                out.append((f["id"], bytes.fromhex(f["data"])))
        return out

    def wait_frame(self, cob_id: int, data: bytes | None, after: int = 0, timeout_s: float = 15) -> int:
        """Index of the first frame (cob_id, data) at or after index ``after`` (any data: None)."""
        def find() -> int | None:
            for i, fr in enumerate(self.frames()[after:], start=after):
                if fr[0] == cob_id and (data is None or fr[1] == data):
                    return i + 1
            return None
        return wait_for(find, timeout_s, f"frame 0x{cob_id:03X} {data.hex() if data is not None else '*'}") - 1
