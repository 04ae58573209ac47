"""drives-twin as a user runs it: a fleet file of three hosts with groups reproduced exactly,
fault injection and link cuts from the twin, clean stops (SIGTERM, SIGINT, a child dying), started
and stopped repeatedly without leftovers. Routers and agents are separate processes; the links are
real byte relays that Zenoh's link lease has to notice."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest

from bus_agent.sim.child import cmdline, descendants, running, wait_for
from supervisor.fleet import Fleet
from tests.system.twinbed import TwinCli
from twin import Twin, TwinError

pytestmark = [pytest.mark.timeout(300)]

FLEET_TOML = """
[hosts.press]
axes = ["ram", "feed"]
agent = { reflex = "disable" }

[hosts.robot]
axes = ["j1", "j2"]
cycle_us = 2000

[hosts.conv]
axes = ["belt"]

[groups]
line = ["press/feed", "conv/belt"]
arm = ["robot/j1", "robot/j2"]
"""


@pytest.fixture
def fleet_file(tmp_path):
    p = tmp_path / "fleet.toml"
    p.write_text(FLEET_TOML)
    return p


def test_cli_reproduces_the_fleet_injects_faults_and_stops_clean_on_sigterm(fleet_file):
    cli = TwinCli(fleet_file)
    try:
        cli.expect_ready(120)
        assert "hosts=press,robot,conv drives=5 backend=sim" in cli.output() or "drives=5" in cli.output()
        procs = descendants(cli.pid)
        assert sum("bus_agent.cli" in cmdline(p) for p in procs) >= 3
        with Fleet(connect=[cli.endpoint], name="checker") as fleet:
            assert fleet.wait_for_agents(["press", "robot", "conv"], timeout_s=10, drives=5)
            assert fleet.host_axes() == {"press": ["ram", "feed"], "robot": ["j1", "j2"], "conv": ["belt"]}
            assert fleet.groups() == {"line": ["press/feed", "conv/belt"], "arm": ["robot/j1", "robot/j2"]}
            assert fleet.agents()["robot"].status.cycle_us == 2000
            assert fleet.enable("@line").ok

            assert cli.command("fault conv/belt 0x2310") == "ok slave 0: fault 0x2310 injected"
            assert fleet.wait_until(lambda f: f.status("conv/belt").state == "fault"
                                    and f.status("conv/belt").error_code == 0x2310, 10)
            # the group reflex on the other host: press uses reflex = "disable" (its agent override)
            assert fleet.wait_until(lambda f: f.status("press/feed").state != "operation_enabled", 10)
            assert fleet.status("press/ram").state == "switch_on_disabled"  # nobody asked: untouched
            # bad input: a clear error, nothing changes
            assert cli.command("fault conv/nope").startswith("error drive 'conv/nope': host conv has no axis")
            assert cli.command("sim robot/j1 explode").startswith("error drive robot/j1: explode refused")
            assert cli.command("cut mars").startswith("error no host 'mars'")
            assert cli.command("frobnicate").startswith("error unknown command 'frobnicate'")
            assert "robot/j1=switch_on_disabled" in cli.command("status")
        cli.popen.send_signal(signal.SIGTERM)
        assert cli.popen.wait(90) == 0
        wait_for(lambda: not running(procs), 10, "no child of the twin left")
        assert "drives-twin stopped" in cli.output()
    finally:
        cli.kill()


def test_cli_agent_killed_is_reported_and_everything_stops(fleet_file):
    cli = TwinCli(fleet_file)
    try:
        cli.expect_ready(120)
        procs = descendants(cli.pid)
        victim = next(p for p in procs if "bus_agent.cli" in cmdline(p) and "robot.toml" in cmdline(p))
        os.kill(victim, signal.SIGKILL)
        assert cli.popen.wait(90) == 1
        out = cli.output()
        assert "bus-agent robot exited unexpectedly (exit code -9)" in out
        wait_for(lambda: not running(procs), 10, "no child of the twin left")
    finally:
        cli.kill()


def test_cli_sigkilled_takes_every_child_with_it_and_cleanup_removes_its_work_directory(tmp_path):
    two = tmp_path / "two.toml"
    two.write_text('[hosts.k1]\naxes = ["a"]\n[hosts.k2]\naxes = ["b"]\n')
    cli = TwinCli(two)
    try:
        cli.expect_ready(120)
        procs = descendants(cli.pid)  # router, two agents, their gateway processes
        assert sum("bus_agent.cli" in cmdline(p) for p in procs) == 2 and len(procs) >= 5
        workdir = cli.workdir()
        os.kill(cli.pid, signal.SIGKILL)  # no handler runs: nothing is stopped in order
        cli.popen.wait(10)
        wait_for(lambda: not running(procs), 20, f"no child of the SIGKILLed twin left ({running(procs)})")
        assert workdir.is_dir()  # only the next start or --cleanup can remove it
        done = subprocess.run([sys.executable, "-m", "twin.cli", "--cleanup"], capture_output=True, text=True,
                              timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr
        assert f"removed work directory {workdir} of dead twin {cli.pid}" in done.stdout
        assert not workdir.exists()
    finally:
        cli.kill()


def test_cli_bad_fleet_failed_start_and_sigint(tmp_path, fleet_file):
    bad = tmp_path / "bad.toml"
    bad.write_text('[hosts.h1]\naxes = ["a"]\nagent = { host = "x" }\n')
    done = subprocess.run([sys.executable, "-m", "twin.cli", "--fleet", str(bad)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and "hosts.h1.agent: key(s) ['host'] are set by the twin" in done.stderr
    done = subprocess.run([sys.executable, "-m", "twin.cli", "--fleet", str(tmp_path / "none.toml")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "cannot read" in done.stderr

    # --pki and --identity are passed through: their refusals come from the twin, before anything runs
    for extra, needle in ((["--identity", "alice"], "--identity needs --pki"),
                          (["--pki", str(tmp_path)], f"--pki {tmp_path}: no ca.pem there")):
        done = subprocess.run([sys.executable, "-m", "twin.cli", "--fleet", str(fleet_file), *extra],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and needle in done.stderr, done.stderr

    done = subprocess.run([sys.executable, "-m", "twin.cli", "--fleet", str(fleet_file), "--listen", "tcp/x"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 3 and re.search(r"drives-router did not become ready \(exit [23]\)", done.stderr), \
        done.stderr

    one = tmp_path / "one.toml"
    one.write_text('[hosts.h1]\naxes = ["a"]\n')
    cli = TwinCli(one)
    try:
        cli.expect_ready(120)
        procs = descendants(cli.pid)
        cli.popen.send_signal(signal.SIGINT)
        assert cli.popen.wait(90) == 0
        wait_for(lambda: not running(procs), 10, "no child of the twin left")
    finally:
        cli.kill()


def test_twin_cut_restore_kill_restart_and_repeated_start_stop():
    fleets = [{"hosts": {"c1": {"axes": ["a", "b"]}, "c2": {"axes": ["x"]}}, "groups": {"g": ["c1/a", "c2/x"]}},
              {"hosts": {"c1": {"axes": ["a"]}}}]
    seen: list[set[int]] = []
    for fleet in fleets:
        exits: list[str] = []
        twin = Twin(fleet, on_unexpected_exit=exits.append)
        with twin:
            pids = set(twin.pids().values())
            seen.append(pids)
            assert len(pids) == 1 + len(fleet["hosts"])
            f = twin.fleet
            if len(fleet["hosts"]) == 2:
                twin.cut("c1")  # noticed through the link lease, not a closed socket
                assert f.wait_until(lambda f: "c1" not in f.hosts(), 15)
                assert "c2" in f.hosts()
                twin.restore("c1")
                twin.wait_answering(["c1"], 30)
                twin.kill_agent("c2")
                assert f.wait_until(lambda f: "c2" not in f.hosts(), 15)
                twin.restart_agent("c2")
                twin.kill_router()
                assert f.wait_until(lambda f: not f.hosts(), 15)
                twin.restart_router()
                assert set(f.hosts()) == {"c1", "c2"}
                twin.unplug("c1/b")
                assert wait_for(lambda: (st := f.status("c1/b")) is not None and st.lost, 10, "c1/b lost")
                twin.plug("c1/b")
                assert wait_for(lambda: (st := f.status("c1/b")) is not None and not st.lost, 20, "c1/b back")
                twin.fault("c1/b", 0x7500)
                assert twin.wait_state("c1/b", "fault", 10).error_code == 0x7500
                with pytest.raises(TwinError, match="not operation_enabled after 0.5 s .last: switch_on_disabled"):
                    twin.wait_state("c1/a", "operation_enabled", 0.5)
                assert twin.unexpected_exits == [] and exits == []  # everything above was asked for
            else:  # a crash nobody asked for: reported
                os.kill(twin.agents["c1"].pid, signal.SIGKILL)
                wait_for(lambda: exits, 10, "the twin to notice")
                assert "bus-agent c1 exited unexpectedly (exit code -9)" in exits[0]
                assert twin.unexpected_exits == exits
            workdir = twin.workdir
        assert not os.path.exists(workdir)
        wait_for(lambda: not running(pids), 10, "the twin's processes gone")
    assert not seen[0] & seen[1]  # separate runs
