"""Issue 9: what an operator sees can be trusted. ``drivectl`` and ``Fleet`` against real
``bus-agent`` processes behind a router: error texts, the audit trail, refused enables listed as
failures, the expected fleet, "did you mean", ``watch --json``, disable of a faulted drive."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator

import pytest
import zenoh

from bus_agent.sim.child import wait_for
from bus_agent.sim.control import sim_inject
from schemas import keys
from schemas.messages import Event, decode
from supervisor.fleet import Fleet
from supervisor.session import zenoh_config
from supervisor.testbed import Proc, _env, start_cli_agent, start_router
from supervisor.watch import status_rows

pytestmark = pytest.mark.timeout(240)

HOSTS = ("t1", "t2")
N = 2


class Bed:
    def __init__(self) -> None:
        self.router, self.ep = start_router()
        self.agents: dict[str, Proc] = {}

    def start(self, host: str, n: int = N) -> Proc:
        self.agents[host] = start_cli_agent(host, n, self.ep, log_level="INFO")
        return self.agents[host]

    def close(self) -> None:
        for p in self.agents.values():
            p.stop()
        self.router.stop()


@pytest.fixture(scope="module")
def bed() -> Iterator[Bed]:
    b = Bed()
    try:
        for h in HOSTS:
            b.start(h)
        with Fleet(connect=[b.ep]) as f:
            assert f.wait_for_agents(HOSTS, 20, drives=len(HOSTS) * N)
        yield b
    finally:
        b.close()


def drivectl(ep: str, *args: str, cwd: str | None = None, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", ep, *args], capture_output=True,
                          text=True, timeout=timeout_s, env=_env(), cwd=cwd)


class Events:
    """Every drive event of the fleet, decoded."""

    def __init__(self, ep: str) -> None:
        self.items: list[Event] = []
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config("client", [ep]))
        self._sub = self.session.declare_subscriber(keys.drive_event("*", "*"), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.items.append(decode(sample.payload.to_bytes(), Event))

    def of(self, kind: str) -> list[Event]:
        with self._lock:
            return [e for e in self.items if e.kind == kind]

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def _fault(ep: str, host: str, slave: int, code: int) -> None:
    with Fleet(connect=[ep]) as f:
        sim_inject(f.session, host, slave, "fault", error_code=code)
        assert f.wait_until(lambda f: (st := f.status(f"{host}/axis{slave}")) is not None and st.state == "fault", 10)


def _reset(ep: str, sel: str) -> None:
    assert drivectl(ep, "fault-reset", sel).returncode == 0
    assert drivectl(ep, "disable", sel).returncode == 0


def test_error_text_is_filled_and_shown_and_disable_in_fault_is_not_a_failure(bed: Bed) -> None:
    _fault(bed.ep, "t1", 1, 0x2310)
    try:
        body = json.loads(drivectl(bed.ep, "--json", "status", "t1").stdout)
        row = next(d for d in body["drives"] if d["axis"] == "axis1")
        assert (row["error_code"], row["error_text"]) == (0x2310, "continuous over-current")
        r = drivectl(bed.ep, "status", "t1")
        assert "continuous over-current" in r.stdout, r.stdout
        # disable of a drive in Fault: it is already without torque; reported as such, exit 0
        r = drivectl(bed.ep, "disable", "t1/axis1", "--json")
        assert r.returncode == 0, r.stdout + r.stderr
        res = json.loads(r.stdout)["final"][0]
        assert (res["outcome"], res["state"]) == ("done", "fault") and "without torque" in res["error"]
    finally:
        _reset(bed.ep, "t1/axis1")


def test_refused_enable_lists_the_blocking_drive_as_failure(bed: Bed) -> None:
    _fault(bed.ep, "t2", 0, 0x3210)
    try:
        with Fleet(connect=[bed.ep]) as fleet:  # the README's supervisor example, as written there
            assert fleet.wait_for_agents(HOSTS, 10, drives=len(HOSTS) * N)
            report = fleet.enable("t2/*")
            assert not report.ok and "nothing sent" in report.reason
            assert [(r.host, r.axis, r.outcome, r.error_code) for r in report.failures] == \
                [("t2", "axis0", "rejected", 0x3210)]
            assert fleet.status("t2/axis1").state == "switch_on_disabled"  # nothing moved
    finally:
        _reset(bed.ep, "t2/axis0")


def test_audit_trail_logs_and_publishes_who_commanded(bed: Bed) -> None:
    ev = Events(bed.ep)
    try:
        r = drivectl(bed.ep, "--name", "alice", "switch-on", "t1/axis0")
        assert r.returncode == 0, r.stdout + r.stderr
        r = drivectl(bed.ep, "--name", "bob", "mode", "42", "t1/axis0")  # refused by drivectl: exit 2, nothing sent
        assert r.returncode == 2
        with zenoh.open(zenoh_config("client", [bed.ep])) as s:  # a malformed command reaches the agent
            list(s.get(keys.drive_cmd("t1", "axis1", "enable"), payload=b"\x01garbage", timeout=5))
        cmds = wait_for(lambda: len(ev.of("command")) >= 2 and ev.of("command"), 10, "command events")
        accepted = [e for e in cmds if e.axis == "axis0" and "accepted" in e.detail]
        assert accepted and accepted[0].requester == "alice" and "switch_on" in accepted[0].detail
        assert accepted[0].request_id.startswith("alice-switch_on")
        refused = [e for e in cmds if e.axis == "axis1" and "refused" in e.detail]
        assert refused and refused[0].requester == "anonymous"
        log = wait_for(lambda: [ln for ln in bed.agents["t1"].lines if "from alice" in ln], 10, "audit log")
        assert "INFO" in log[0] and "switch_on" in log[0] and "axis0" in log[0] and "accepted" in log[0]
        assert any("refused" in ln and "enable" in ln for ln in bed.agents["t1"].lines)
    finally:
        ev.close()
        assert drivectl(bed.ep, "disable", "t1/axis0").returncode == 0


@pytest.mark.parametrize("args, hint", [
    (("enable", "axis1"), "*/axis1"),
    (("enable", "t1/axis9"), "t1/axis1"),
    (("disable", "t3/axis0"), "no host 't3'"),
    (("status", "t1/axs0"), "t1/axis0"),
])
def test_unknown_drive_is_exit_2_with_did_you_mean(bed: Bed, args: tuple[str, ...], hint: str) -> None:
    r = drivectl(bed.ep, *args)
    assert r.returncode == 2 and hint in r.stderr, (r.returncode, r.stdout, r.stderr)


def test_unquoted_star_expanded_by_the_shell(bed: Bed, tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("x")
    r = drivectl(bed.ep, "disable", "notes.txt", cwd=str(tmp_path))  # what `drivectl disable *` becomes
    assert r.returncode == 2 and "shell" in r.stderr and "'**'" in r.stderr, r.stderr
    r = drivectl(bed.ep, "--json", "disable", "notes.txt", cwd=str(tmp_path))
    assert r.returncode == 2 and json.loads(r.stdout)["error"] == "usage"


def test_watch_json_prints_one_line_per_change(bed: Bed) -> None:
    p = subprocess.Popen([sys.executable, "-m", "supervisor.cli", "--connect", bed.ep, "watch", "t2/axis1",
                          "--json", "--duration", "20"], stdout=subprocess.PIPE, text=True, env=_env())
    try:
        assert p.stdout is not None
        first = json.loads(p.stdout.readline())
        assert (first["event"], first["host"], first["axis"], first["state"]) == \
            ("status", "t2", "axis1", "switch_on_disabled")
        assert {"error_code", "lost", "al_state"} <= set(first)
        assert drivectl(bed.ep, "switch-on", "t2/axis1").returncode == 0
        states = []
        while "switched_on" not in states:
            line = json.loads(p.stdout.readline())  # a table would not parse
            assert line["axis"] == "axis1"
            states.append(line["state"])
    finally:
        p.kill()
        p.wait()
        assert drivectl(bed.ep, "disable", "t2/axis1").returncode == 0


def test_expected_fleet_offline_missing_unexpected(bed: Bed, tmp_path: Path) -> None:
    fleet_file = tmp_path / "fleet.toml"
    fleet_file.write_text('[hosts.t1]\naxes = ["axis0", "axis1"]\n[hosts.t9]\naxes = ["x", "y"]\n')
    r = drivectl(bed.ep, "--json", "status", "--fleet", str(fleet_file))
    assert r.returncode == 1, r.stdout + r.stderr
    body = json.loads(r.stdout)
    offline = {(d["host"], d["axis"]) for d in body["drives"] if d["state"] == "offline"}
    assert offline == {("t9", "x"), ("t9", "y")} and body["absent"] == ["t9/x", "t9/y"]
    assert body["unexpected_hosts"] == ["t2"] and body["agents"]["t2"]["expected"] is False
    assert body["agents"]["t9"]["state"] == "offline"
    r = drivectl(bed.ep, "status", "--fleet", str(fleet_file))
    assert "offline" in r.stdout and "unexpected" in r.stdout
    # a command matching expected-but-absent drives reports each of them missing, exit 1
    r = drivectl(bed.ep, "--json", "--fleet", str(fleet_file), "quick-stop", "t9/*")
    assert r.returncode == 1, r.stdout + r.stderr
    final = json.loads(r.stdout)["final"]
    assert {(d["axis"], d["outcome"]) for d in final} == {("x", "missing"), ("y", "missing")}
    # the same through the environment, and an enable is refused with t9's drives as failures
    env = {**_env(), "DRIVES_FLEET": str(fleet_file)}
    r = subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", bed.ep, "--json", "enable", "t9/x"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 1 and json.loads(r.stdout)["final"][0]["outcome"] == "missing"
    # a malformed fleet file is a usage error
    fleet_file.write_text("[hosts.t1]\naxis = 1\n")
    r = drivectl(bed.ep, "status", "--fleet", str(fleet_file))
    assert r.returncode == 2 and "hosts.t1" in r.stderr


def test_verbose_status_shows_agent_cycle_figures(bed: Bed) -> None:
    r = drivectl(bed.ep, "status", "-v")
    assert r.returncode == 0, r.stderr
    assert "period p99 us" in r.stdout and "WKC errors" in r.stdout and "overruns" in r.stdout


def test_sim_verbs_inject_by_axis_name(bed: Bed) -> None:
    r = drivectl(bed.ep, "--json", "sim", "fault", "t1/axis1", "0x4310")
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads(r.stdout)["results"][0]["slave"] == 1
    with Fleet(connect=[bed.ep]) as f:
        assert f.wait_until(lambda f: (st := f.status("t1/axis1")) is not None and st.state == "fault"
                            and st.error_text == "excess drive temperature", 10)
        assert drivectl(bed.ep, "sim", "unplug", "t1/axis0").returncode == 0
        assert f.wait_until(lambda f: f.status("t1/axis0").lost, 10)
        assert drivectl(bed.ep, "sim", "plug", "t1/axis0").returncode == 0
        assert f.wait_until(lambda f: not f.status("t1/axis0").lost and f.status("t1/axis0").al_state == "op", 20)
        wkc = f.agents()["t1"].status.wkc_errors
        assert drivectl(bed.ep, "sim", "wkc-fault", "on", "t1/axis0").returncode == 0
        assert f.wait_until(lambda f: f.agents()["t1"].status.wkc_errors > wkc, 10)
        assert drivectl(bed.ep, "sim", "wkc-fault", "off", "t1/axis0").returncode == 0
        assert f.wait_until(lambda f: not f.status("t1/axis0").lost, 20)
    # bad input: exit 2, nothing injected
    for args in (("sim", "fault", "t1/axis1"), ("sim", "fault", "t1/axis1", "hot"), ("sim", "wkc-fault", "maybe"),
                 ("sim", "unplug", "t1/axis7"), ("sim", "explode", "t1/axis0")):
        r = drivectl(bed.ep, *args)
        assert r.returncode == 2 and r.stderr.strip(), (args, r.stdout, r.stderr)
    # a segment with no simulator: exit 1, with what to check
    r = drivectl(bed.ep, "sim", "unplug", "t1/axis0", "--segment", "seg9", "--timeout", "1")
    assert r.returncode == 1 and "seg9" in r.stdout, r.stdout + r.stderr
    _reset(bed.ep, "t1/axis1")


def test_lease_verb_holds_until_interrupted_and_release_gives_back(bed: Bed) -> None:
    import signal
    p = subprocess.Popen([sys.executable, "-m", "supervisor.cli", "--connect", bed.ep, "--name", "holder", "lease",
                          "t2/*", "--ttl", "3", "--json"], stdout=subprocess.PIPE, text=True, env=_env())
    try:
        assert p.stdout is not None
        line = json.loads(p.stdout.readline())
        assert line == {"event": "leased", "holder": "holder", "drives": ["t2/axis0", "t2/axis1"]}
        r = drivectl(bed.ep, "--name", "other", "--json", "switch-on", "t2/axis0")
        assert r.returncode == 1 and json.loads(r.stdout)["final"][0]["outcome"] == "busy"
        p.send_signal(signal.SIGINT)
        assert p.wait(30) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    with Fleet(connect=[bed.ep]) as f:  # released on exit: no holder, no lease reaction
        assert f.wait_until(lambda f: not f.status("t2/axis0").lease_holder, 10)
    with Fleet(connect=[bed.ep], name="keeper") as keeper:
        assert keeper.wait_for_agents(HOSTS, 10)
        assert keeper.lease("t2/axis1", ttl_s=60).ok
        r = drivectl(bed.ep, "--name", "keeper", "--json", "release", "t2/axis1")
        assert r.returncode == 0, r.stdout + r.stderr
        assert json.loads(r.stdout)["final"][0]["outcome"] == "done"
        assert keeper.wait_until(lambda f: not f.status("t2/axis1").lease_holder, 10)


def test_one_agent_per_host_name(bed: Bed) -> None:
    """A second agent under a taken host name refuses to start (exit 3) before declaring
    anything; two that meet later (a partition healing) both say so, and supervisors refuse to
    command that host."""
    from bus_agent.sim.child import ChildProcess, free_port

    second = start_cli_agent_raw(bed.ep, "t1")
    try:
        assert second.popen.wait(60) == 3, second.output()
        assert "host name 't1' is taken" in second.output()
    finally:
        second.stop()  # an agent that wrongly started must not outlive the test
    # A partition: c1 runs on the bed's router; another c1 comes up behind a router that is not
    # there yet (nothing to see at its start), then that router appears and links to the bed's.
    bed.start("c1", 1)
    far = f"tcp/127.0.0.1:{free_port()}"
    late = start_cli_agent_raw(far, "c1", ready=True)
    bridge = ChildProcess("bridge-router", [sys.executable, "-m", "bus_agent.router", "--listen", far, "--connect",
                                            bed.ep], ready_marker="drives-router ready")
    try:
        bridge.expect_ready(20)
        with Fleet(connect=[bed.ep]) as f:
            assert f.wait_until(lambda f: "c1" in f.conflicts(), 20), f.agents().get("c1")
            assert f.wait_until(lambda f: all(a.status and a.status.conflict for a in [f.agents()["c1"]]), 10)
            res = f.command("switch_on", "c1/*")
            assert [(r.outcome, "not sent" in r.error) for r in res.results] == [("rejected", True)]
            report = f.enable("c1/axis0")
            assert not report.ok and report.failures[0].outcome == "rejected"
            assert {st.state for st in f.fetch_status("c1/*").values()} == {"switch_on_disabled"}
        r = drivectl(bed.ep, "status", "c1")
        assert r.returncode == 1 and "conflict" in r.stdout.lower(), r.stdout
        log = wait_for(lambda: [ln for ln in late.lines if "also used by agent instance" in ln], 10, "conflict log")
        assert "ERROR" in log[0]
        # Without an expected fleet, a long-lived Fleet keeps a departed host visible as gone.
        with Fleet(connect=[bed.ep]) as watcher:
            assert watcher.wait_for_agents(["c1"], 10, drives=len(HOSTS) * N + 1)
            bridge.stop()
            late.stop()
            bed.agents.pop("c1").stop()
            assert watcher.wait_until(lambda f: "c1" not in f.hosts(), 20)
            rows = [r for r in status_rows(watcher) if r["host"] == "c1"]
            assert [(r["axis"], r["agent"], r["agent_alive"]) for r in rows] == [("axis0", "gone", False)]
    finally:
        bridge.stop()
        late.stop()
        if "c1" in bed.agents:
            bed.agents.pop("c1").stop()


def start_cli_agent_raw(router: str, host: str, ready: bool = False) -> Proc:
    from bus_agent.sim.child import ChildProcess, free_port

    p = ChildProcess(f"bus-agent {host}", [sys.executable, "-m", "bus_agent.cli", "--sim", "1", "--host", host,
                                           "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", router],
                     ready_marker="bus-agent ready")
    if ready:
        p.expect_ready(60)
    return p
