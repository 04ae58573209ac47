"""Helpers for the multi-host system test: the full stack on hosts that are network namespaces.

:class:`MultiHostRun` builds a bed (``bus_agent.sim.netns.multihost_*``) and starts, inside each
host namespace (``ip netns exec``): ``ecat-sim`` on ``ecs0``, a ``drives-router`` on the host's
address, and ``bus-agent --ifname ecm0`` (pysoem, real EtherCAT frames) connected to that
router. Routers connect to the routers of lower-numbered hosts. Supervisors run as
:class:`SupervisorProc` children in any namespace: a ``supervisor.Fleet`` driven by JSON lines
on stdin/stdout, with ``arrival``/``departure`` events stamped with ``time.monotonic()``
(one clock for every namespace).

This file is also the supervisor child: ``python tests/system/multihost.py supervisor
--connect EP --name N``.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script
    sys.path.insert(0, str(ROOT))

from bus_agent.sim.child import ChildProcess, child_env  # noqa: E402
from bus_agent.sim.netns import MultiHostBed, multihost_down, multihost_link, multihost_plan, multihost_up  # noqa: E402

ROUTER_PORT = 7447


# One child-process implementation for every test bed (bus_agent/sim/child.py).
Proc = ChildProcess
_env = child_env


class PathControlClient:
    """ecat-sim's UNIX-datagram control from outside the simulator's namespace.

    ``ControlClient`` autobinds an abstract address, which belongs to the caller's network
    namespace, so replies from a simulator in another namespace would be lost. A filesystem
    path works across namespaces."""

    _n = itertools.count()

    def __init__(self, server_path: str, timeout_s: float = 2.0) -> None:
        self.server_path = server_path
        self.path = f"{server_path}.c{os.getpid()}-{next(self._n)}"
        if os.path.exists(self.path):
            os.unlink(self.path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(timeout_s)
        self.lock = threading.Lock()

    def request(self, action: str, **args: Any) -> dict:
        with self.lock:
            self.sock.sendto(json.dumps({"action": action, **args}).encode(), self.server_path)
            return json.loads(self.sock.recv(65536))

    def drive_states(self) -> list[str]:
        reply = self.request("status")
        assert reply["ok"], reply
        return [s["drive_state"] for s in reply["slaves"]]

    def slaves(self) -> list[dict]:
        reply = self.request("status")
        assert reply["ok"], reply
        return reply["slaves"]

    def close(self) -> None:
        self.sock.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


class SupervisorProc(Proc):
    """A ``supervisor.Fleet`` in a child process (in a namespace), driven by JSON lines."""

    def __init__(self, name: str, argv: Sequence[str]) -> None:
        self.replies: "queue.SimpleQueue[dict]" = queue.SimpleQueue()
        self.events: list[dict] = []
        self._ids = itertools.count(1)
        super().__init__(name, argv, ready_marker="supervisor ready", stdin=True)

    def on_line(self, line: str) -> None:
        if not line.startswith("{"):
            return
        msg = json.loads(line)
        if "event" in msg:
            self.events.append(msg)
        elif "id" in msg:
            self.replies.put(msg)

    def call(self, op: str, timeout_s: float = 20.0, **args: Any) -> dict:
        """One request; returns the reply's ``result`` (AssertionError on error or timeout)."""
        rid = next(self._ids)
        assert self.popen.stdin is not None
        self.popen.stdin.write(json.dumps({"id": rid, "op": op, **args}) + "\n")
        self.popen.stdin.flush()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                msg = self.replies.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"{self.name}: no reply to {op} in {timeout_s} s:\n{self.output()}") from None
            if msg["id"] == rid:
                break
        if not msg.get("ok"):
            raise AssertionError(f"{self.name}: {op} failed: {msg.get('error')}")
        return msg["result"]

    def event_times(self, event: str, host: str) -> list[float]:
        return [e["t"] for e in list(self.events) if e["event"] == event and e.get("host") == host]


class MultiHostRun:
    """The whole stack on a bed of ``hosts`` host namespaces plus a ``sup`` namespace."""

    def __init__(self, hosts: int = 2, drives: int = 3, groups: dict[str, list[str]] | None = None,
                 prefix: str | None = None, pki: str | None = None, agent_args: Sequence[str] = (),
                 agent_toml: str = "", router_args: Sequence[str] = ()) -> None:
        self.prefix = prefix or f"zm{os.getpid() % 100000}"
        #: A drives-pki directory holding router certificates ``r-<host>`` (SAN: the host's
        #: address), agent certificates ``<host>`` and testbed certificates ``sim-<host>`` (each
        #: ecat-sim then also serves its Zenoh control through its host's router): every link
        #: TLS, every router with the ACL.
        #: None: the plain bed (routers --insecure: they listen on the bed's addresses).
        self.pki = pki
        self.drives = drives
        self.groups = groups or {}
        #: Extra ``bus-agent`` options for every agent (benchmarks: ``--rt-priority N``).
        self.agent_args = list(agent_args)
        self.agent_toml = agent_toml  # appended to every agent's configuration file (tables after [groups])
        #: Extra ``drives-router`` options for every router (benchmarks: ``--rt-priority N``).
        self.router_args = list(router_args)
        self.bed: MultiHostBed = multihost_plan(self.prefix, hosts, extra=("sup",))
        self.workdir = tempfile.mkdtemp(prefix="multihost-")
        self.procs: list[Proc] = []
        self.sims: dict[str, Proc] = {}
        self.controls: dict[str, PathControlClient] = {}
        self.routers: dict[str, Proc] = {}
        self.agents: dict[str, Proc] = {}

    @property
    def host_names(self) -> list[str]:
        return [h.name for h in self.bed.hosts if h.ecat_master]

    def router_endpoint(self, host: str) -> str:
        return f"{'tls' if self.pki else 'tcp'}/{self.bed.host(host).address}:{ROUTER_PORT}"

    def security(self, identity: str) -> list[str]:
        """Command-line options of a process of ``identity`` (none on the plain bed)."""
        return ["--pki", self.pki, "--identity", identity] if self.pki else []

    def spawn(self, cls: type, name: str, host: str, argv: Sequence[str], **kw: Any) -> Any:
        proc = cls(name, self.bed.host(host).exec_argv(*argv), **kw)
        self.procs.append(proc)
        return proc

    def start(self, ready_timeout_s: float = 40.0) -> None:
        multihost_up(self.bed)
        py = sys.executable
        hosts = self.host_names
        for h in hosts:  # everything starts in parallel; readiness is awaited below
            hb = self.bed.host(h)
            sock = os.path.join(self.workdir, f"{h}.sock")
            zenoh_control = ["--zenoh-connect", self.router_endpoint(h), *self.security(f"sim-{h}")] if self.pki else []
            self.sims[h] = self.spawn(Proc, f"ecat-sim {h}", h, [
                py, "-m", "bus_agent.sim.cli", "--ifname", hb.ecat_sim, "--drives", str(self.drives),
                "--name", h, "--control", sock, "--rt-priority", "20", *zenoh_control], ready_marker="ecat-sim ready")
            connect: list[str] = []
            for other in hosts[:hosts.index(h)]:
                connect += ["--connect", self.router_endpoint(other)]
            self.routers[h] = self.spawn(Proc, f"router {h}", h, [
                py, "-m", "bus_agent.router", "--listen", self.router_endpoint(h), *connect,
                *(self.security(f"r-{h}") or ["--insecure"]), *self.router_args],
                ready_marker="drives-router ready")
        for h in hosts:
            self.sims[h].expect_ready(ready_timeout_s)
            self.controls[h] = PathControlClient(os.path.join(self.workdir, f"{h}.sock"))
            self.routers[h].expect_ready(ready_timeout_s)
        for h in hosts:
            self.agents[h] = self.start_agent(h)
        for h in hosts:
            self.agents[h].expect_ready(ready_timeout_s)

    def start_agent(self, host: str) -> Proc:
        hb = self.bed.host(host)
        cfg = Path(self.workdir) / f"{host}.toml"
        lines = [f'host = "{host}"', f'ifname = "{hb.ecat_master}"', "", "[groups]"]
        lines += [f"{g} = [{', '.join(json.dumps(m) for m in members)}]" for g, members in self.groups.items()]
        cfg.write_text("\n".join(lines) + "\n" + self.agent_toml)
        return self.spawn(Proc, f"bus-agent {host}", host, [
            sys.executable, "-m", "bus_agent.cli", "--config", str(cfg), "--ifname", hb.ecat_master or "",
            "--host", host, "--connect", self.router_endpoint(host), "--log-level", "WARNING", *self.security(host),
            *self.agent_args],
            ready_marker="bus-agent ready")

    def start_supervisor(self, ns: str, connect_host: str, name: str, ready_timeout_s: float = 20.0) -> SupervisorProc:
        """A Fleet named ``name`` (on a secure bed: authenticated as principal ``name``)."""
        sup = self.spawn(SupervisorProc, f"supervisor {name}", ns, [
            sys.executable, str(Path(__file__).resolve()), "supervisor",
            "--connect", self.router_endpoint(connect_host), "--name", name, *self.security(name)])
        sup.expect_ready(ready_timeout_s)
        return sup

    def drivectl(self, ns: str, connect_host: str, *args: str, timeout_s: float = 30.0,
                 identity: str | None = None) -> subprocess.CompletedProcess:
        """``drivectl`` in namespace ``ns`` (on a secure bed as ``identity``)."""
        argv = self.bed.host(ns).exec_argv(sys.executable, "-m", "supervisor.cli", "--connect",
                                           self.router_endpoint(connect_host),
                                           *(self.security(identity) if identity else []), *args)
        return subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT, env=_env())

    def link(self, host: str, up: bool) -> None:
        multihost_link(self.bed, host, up)

    @contextlib.contextmanager
    def running(self, prepare: Callable[[], None] = lambda: None) -> Iterator[MultiHostRun]:
        """``prepare()`` (e.g. the certificates), start the bed and yield it; if anything fails,
        print every process's output; close it however the block ends (a module fixture's body)."""
        try:
            prepare()
            self.start()
            yield self
        except BaseException:
            print(self.diagnostics())
            raise
        finally:
            self.close()

    def diagnostics(self) -> str:
        return "\n".join(f"--- {p.name} (exit {p.popen.poll()})\n{p.output(15)}" for p in self.procs)

    def close(self) -> None:
        # Agents first (ordered stop while their bus still answers), then everything else.
        for group in (list(self.agents.values()), [p for p in self.procs if p not in self.agents.values()]):
            for p in group:
                if p.popen.poll() is None:
                    p.popen.send_signal(signal.SIGTERM)
            for p in group:
                try:
                    p.popen.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
        for p in self.procs:
            p.kill()  # reap; no-op when gone
        for c in self.controls.values():
            c.close()
        multihost_down(self.prefix, len(self.host_names), extra=("sup",))
        shutil.rmtree(self.workdir, ignore_errors=True)


# ---- the supervisor child -----------------------------------------------------------------

def _supervisor_main(argv: Sequence[str]) -> int:
    import argparse
    import logging

    from supervisor.fleet import Fleet

    p = argparse.ArgumentParser(prog="multihost.py supervisor")
    p.add_argument("--connect", action="append", required=True)
    p.add_argument("--name", required=True)
    p.add_argument("--pki")
    p.add_argument("--identity")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    out_lock = threading.Lock()

    def emit(msg: dict) -> None:
        with out_lock:
            print(json.dumps(msg), flush=True)

    signal.signal(signal.SIGTERM, lambda *_: sys.stdin.close())
    with Fleet(connect=args.connect, name=args.name, mode="client", connect_timeout_s=10.0, pki=args.pki,
               identity=args.identity) as fleet:
        fleet.on("arrival", lambda host: emit({"event": "arrival", "host": host, "t": time.monotonic()}))
        fleet.on("departure", lambda host: emit({"event": "departure", "host": host, "t": time.monotonic()}))
        print("supervisor ready", flush=True)
        for line in sys.stdin:
            req = json.loads(line)
            try:
                emit({"id": req["id"], "ok": True, "result": _handle(fleet, req)})
            except Exception as exc:  # reported to the test, which fails with it
                emit({"id": req["id"], "ok": False, "error": f"{type(exc).__name__}: {exc}"})
    return 0


def _handle(fleet: Any, req: dict) -> Any:
    op = req["op"]
    if op == "wait_agents":
        ok = fleet.wait_for_agents(req["hosts"], timeout_s=req.get("timeout_s", 10.0), drives=req.get("drives", 0))
        return {"ok": ok, "hosts": fleet.hosts(), "roster": [f"{r.host}/{r.axis}" for r in fleet.roster()]}
    if op == "drives":
        return {f"{r.host}/{r.axis}": {"state": st.state, "lease_holder": st.lease_holder}
                for r, st in fleet.drives().items()}
    if op == "enable":
        report = fleet.enable(*req["selectors"])
        return {"ok": report.ok, "reason": report.reason}
    if op == "lease":
        res = fleet.lease(*req["selectors"], ttl_s=req.get("ttl_s"))
        return {"ok": all(r.ok for r in res.results), "outcomes": {r.name: r.outcome for r in res.results}}
    if op == "group_move":
        called = time.time()
        res = fleet.group_move(req["targets"], timeout_s=req.get("move_timeout_s", 30.0))
        return {"ok": res.ok, "called_s": called, "outcomes": {r.name: r.outcome for r in res.results},
                "durations": {r.name: round(r.duration_s, 6) for r in res.results},
                "errors": [f"{r.name}: {r.error}" for r in res.results if not r.ok]}
    if op == "recording":
        return _recorded_motion(fleet, req["host"], req.get("last_s", 10.0))
    raise ValueError(f"unknown op {op!r}")


def _recorded_motion(fleet: Any, host: str, last_s: float) -> dict[str, list[tuple[float, int, int]]]:
    """Per axis of ``host``'s flight recording (its last ``last_s``): (the agent's wall clock of
    the cycle in s, the 0x607A it wrote, the 0x6064 its drive reported)."""
    from supervisor.recordings import fetch_recording

    rec = fetch_recording(fleet.session, host, "now", last_s)
    ch, n = rec.channels, len(rec.axes)
    t = ch["time_ns"]
    return {axis: [((rec.time_origin_ns + t[i] - t[0]) / 1e9, ch["target_position"][i * n + j], ch["position"][i * n + j])
                   for i in range(rec.n_cycles)] for j, axis in enumerate(rec.axes)}


if __name__ == "__main__":
    if sys.argv[1:2] == ["supervisor"]:
        sys.exit(_supervisor_main(sys.argv[2:]))
    print(__doc__, file=sys.stderr)
    sys.exit(2)
