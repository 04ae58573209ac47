"""``drivectl`` as a user runs it (a subprocess) against three ``bus-agent`` processes."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from typing import Iterator

import pytest
import zenoh

from bus_agent.sim.child import wait_for
from supervisor.fleet import Fleet
from supervisor.session import zenoh_config
from supervisor.testbed import Proc, _env, free_port, start_cli_agent, start_router

pytestmark = pytest.mark.timeout(180)

HOSTS = ("h1", "h2", "h3")
N = 2


@pytest.fixture(scope="module")
def bed() -> Iterator[str]:
    router, ep = start_router()
    agents: list[Proc] = []
    try:
        for h in HOSTS:
            agents.append(start_cli_agent(h, N, ep))
        with Fleet(connect=[ep]) as f:
            assert f.wait_for_agents(HOSTS, 10, drives=len(HOSTS) * N)
        yield ep
    finally:
        for p in agents:
            p.stop()
        router.stop()


def drivectl(ep: str, *args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", ep, *args],
                          capture_output=True, text=True, timeout=timeout_s, env=_env())


class CommandSpy:
    """A queryable on every command key: records each query that reaches the key space."""

    def __init__(self, ep: str) -> None:
        self.keys: list[str] = []
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config("client", [ep]))
        self._q = [self.session.declare_queryable("drives/@v1/*/drive/*/cmd/*", self._on),
                   self.session.declare_queryable("drives/@v1/*/agent/cmd/*", self._on)]

    def _on(self, query: zenoh.Query) -> None:
        with self._lock:
            self.keys.append(str(query.key_expr))
        query.drop()

    def close(self) -> None:
        for q in self._q:
            q.undeclare()
        self.session.close()


@pytest.fixture()
def spy(bed: str) -> Iterator[CommandSpy]:
    s = CommandSpy(bed)
    try:
        yield s
    finally:
        s.close()


def test_status_json_lists_every_drive(bed: str) -> None:
    r = drivectl(bed, "--json", "status")
    assert r.returncode == 0, r.stderr
    body = json.loads(r.stdout)
    assert set(HOSTS) <= set(body["agents"])
    drives = [d for d in body["drives"] if d["host"] in HOSTS]
    assert len(drives) == len(HOSTS) * N
    assert all(d["agent_alive"] and d["state"] == "switch_on_disabled" for d in drives)


def test_status_table(bed: str) -> None:
    r = drivectl(bed, "status", "h1")
    assert r.returncode == 0, r.stderr
    assert "h1" in r.stdout and "axis0" in r.stdout and "h2" not in r.stdout


@pytest.mark.parametrize(
    "args",
    [
        ("enable", "h1/x/y"),           # three levels
        ("enable", "h1/x#"),            # illegal character
        ("enable",),                    # a moving verb needs a target
        ("enable", "h7*/axis0"),        # matches no drive
        ("enable", "@nogroup"),         # unknown group
        ("mode", "42", "h1/*"),         # no such mode
        ("halt", "--sideways", "h1/*"), # unknown option
        ("--timeout", "-1", "disable", "h1/*"),
        ("nmt", "explode"),             # no such NMT command
        ("nmt", "stop", "--host", "h1/axis0"),
        ("nmt", "stop", "--host", "h1", "--host", "h2", "--slave", "0"),
        ("frobnicate",),
        ("--group", "g=h1/*", "enable", "@g"),  # group members must be concrete
    ],
)
def test_bad_selectors_and_arguments_exit_2_and_send_nothing(bed: str, spy: CommandSpy, args: tuple[str, ...]) -> None:
    r = drivectl(bed, *args)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert r.stderr.strip(), "the reason must be printed"
    assert spy.keys == []


def test_no_agent_reachable_exit_3() -> None:
    r = drivectl(f"tcp/127.0.0.1:{free_port()}", "status")
    assert r.returncode == 3 and "no agent" in r.stderr
    router, ep = start_router()
    try:
        r = drivectl(ep, "--discovery", "0.3", "enable", "**")
        assert r.returncode == 3 and "no bus agent" in r.stderr
    finally:
        router.stop()


def test_enable_disable_round_trip_json(bed: str) -> None:
    r = drivectl(bed, "--json", "enable", "h1/*", "h2/axis1")
    assert r.returncode == 0, r.stdout + r.stderr
    body = json.loads(r.stdout)
    assert body["ok"] and [s["step"] for s in body["steps"]] == ["switch_on", "enable"]
    assert {(d["host"], d["axis"]) for d in body["final"]} == {("h1", "axis0"), ("h1", "axis1"), ("h2", "axis1")}
    assert all(d["state"] == "operation_enabled" for d in body["final"])
    r = drivectl(bed, "disable", "--stage", "h1/*", "--stage", "h2/*")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "reached the goal" in r.stdout
    r = drivectl(bed, "--json", "status")
    assert all(d["state"] == "switch_on_disabled" for d in json.loads(r.stdout)["drives"] if d["host"] in HOSTS)


def test_partial_failure_exit_1_lists_the_drive(bed: str) -> None:
    from bus_agent.sim.control import sim_inject

    with Fleet(connect=[bed]) as f:
        assert f.wait_for_agents(HOSTS, 10, drives=len(HOSTS) * N)
        sim_inject(f.session, "h3", 1, "fault", error_code=0x2310)
        assert f.wait_until(lambda f: f.status("h3/axis1").state == "fault", 5)
    try:
        r = drivectl(bed, "--timeout", "1", "switch-on", "h3/*")
        assert r.returncode == 1, r.stdout + r.stderr
        assert "h3/axis1" in r.stdout and "FAILED" in r.stdout
        r = drivectl(bed, "--json", "enable", "h3/*")  # refused before anything moves
        assert r.returncode == 1 and "nothing sent" in json.loads(r.stdout)["reason"]
    finally:
        assert drivectl(bed, "fault-reset", "h3/axis1").returncode == 0
        assert drivectl(bed, "disable", "h3/*").returncode == 0


def _results(r: subprocess.CompletedProcess) -> dict[str, dict]:
    """'host/axis' (or host for agent commands) -> its result in a ``--json`` command report."""
    body = json.loads(r.stdout)
    rows = body["final"] if "final" in body else body["results"]
    return {f"{x['host']}/{x['axis']}" if x["axis"] else x["host"]: x for x in rows}


def test_quick_stop_halt_mode_nmt(bed: str) -> None:
    """Each verb's per-drive outcome, and its effect as the drives' own status shows it."""
    h2 = [f"h2/axis{i}" for i in range(N)]
    with Fleet(connect=[bed]) as fleet:
        def seen(pred, what: str) -> None:  # status is published on change
            wait_for(pred, 10, what)

        assert drivectl(bed, "enable", "h2/*").returncode == 0
        r = drivectl(bed, "--json", "halt", "h2/*")
        assert r.returncode == 0, r.stdout + r.stderr
        assert {k: v["outcome"] for k, v in _results(r).items()} == {k: "done" for k in h2}
        seen(lambda: all(fleet.status(k).halt for k in h2), "halt bit set on h2")
        assert drivectl(bed, "halt", "--off", "h2/*").returncode == 0
        seen(lambda: not any(fleet.status(k).halt for k in h2), "halt bit cleared on h2")
        r = drivectl(bed, "--json", "quick-stop", "h2/*")
        assert r.returncode == 0, r.stdout + r.stderr
        assert {k: (v["outcome"], v["state"]) for k, v in _results(r).items()} == {
            k: ("done", "quick_stop_active") for k in h2}
        assert drivectl(bed, "disable", "**").returncode == 0
        r = drivectl(bed, "--json", "mode", "csv", "h1/axis0")
        assert r.returncode == 0, r.stdout + r.stderr
        assert _results(r)["h1/axis0"]["outcome"] == "done"
        seen(lambda: fleet.status("h1/axis0").mode_display == 9, "0x6061 echo of csv")
        assert drivectl(bed, "mode", "csp", "h1/axis0").returncode == 0
        seen(lambda: fleet.status("h1/axis0").mode_display == 8, "0x6061 echo of csp")
        r = drivectl(bed, "--json", "nmt", "preop", "--host", "h1", "--slave", "0")
        assert r.returncode == 0, r.stdout + r.stderr
        assert json.loads(r.stdout)["final"][0]["host"] == "h1"
        seen(lambda: fleet.status("h1/axis0").al_state == "preop", "h1 slave 0 in PRE-OP")
        assert fleet.status("h1/axis1").al_state == "op"  # only slave 0
        assert drivectl(bed, "nmt", "start", "--host", "h1").returncode == 0
        seen(lambda: fleet.status("h1/axis0").al_state == "op", "h1 slave 0 back in OP")


def test_watch_draws_the_live_table(bed: str) -> None:
    r = drivectl(bed, "watch", "--duration", "1", "h2")
    assert r.returncode == 0, r.stderr
    assert "h2" in r.stdout and "axis1" in r.stdout
