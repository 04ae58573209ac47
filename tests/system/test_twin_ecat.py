"""drives-twin's ecat backend (root): each host a network namespace with its own veth pair, ecat-sim on
one end and the agent's pysoem on the other; faults through ecat-sim; nothing left after a stop,
also when an agent died first; a twin killed with SIGKILL takes its children with it, and the next
start removes the namespace it left."""

from __future__ import annotations

import os
import signal
import subprocess

import pytest

from bus_agent.sim.child import descendants, running, wait_for
from tests.conftest import require, require_root
from tests.system.twinbed import TwinCli
from twin import Twin

pytestmark = [pytest.mark.timeout(240), pytest.mark.root]


def leftovers(prefix: str) -> list[str]:
    """Namespaces and links (root namespace) whose name starts with ``prefix``."""
    ns = [n for n in os.listdir("/run/netns") if n.startswith(prefix)] if os.path.isdir("/run/netns") else []
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True).stdout
    return ns + [ln.split(":")[1].strip() for ln in links.splitlines() if ln.split(":")[1].strip().startswith(prefix)]


def test_ecat_twin_runs_pysoem_per_namespace_and_leaves_nothing():
    require_root()
    require(subprocess.run(["which", "ip"], capture_output=True).returncode == 0, "iproute2 (`ip`)",
            "install iproute2")
    fleet = {"hosts": {"e1": {"axes": ["x", "y"]}, "e2": {"axes": ["z"], "profile": "indy7"}},
             "groups": {"g": ["e1/x", "e2/z"]}}
    exits: list[str] = []
    twin = Twin(fleet, backend="ecat", on_unexpected_exit=exits.append)
    prefix = twin.prefix
    with twin:
        f = twin.fleet
        assert {h: a.status.backend for h, a in f.agents().items() if a.status} == {"e1": "pysoem", "e2": "pysoem"}
        assert f.host_axes() == {"e1": ["x", "y"], "e2": ["z"]}
        assert sorted(os.listdir("/run/netns")) >= sorted([f"{prefix}h1", f"{prefix}h2"])
        assert f.enable("@g").ok
        assert twin.fault("e2/z", 0x2310)           # through ecat-sim's Zenoh control, segment e2
        assert twin.wait_state("e2/z", "fault", 10).error_code == 0x2310
        twin.wait_state("e1/x", "switch_on_disabled", 10)  # the group reflex on the other host
        assert twin.inject("e1/y", "drop_frames", count=3)  # an ecat-sim-only action
        os.kill(twin.agents["e1"].pid, signal.SIGKILL)      # an agent dies inside its namespace
        wait_for(lambda: exits, 10, "the twin to notice")
    assert "bus-agent e1 exited unexpectedly" in exits[0]
    assert leftovers(prefix) == []
    assert not os.path.exists(twin.workdir)


def test_ecat_twin_sigkilled_takes_its_children_and_the_next_start_removes_its_namespace(tmp_path):
    require_root()
    fleet = tmp_path / "fleet.toml"
    fleet.write_text('[hosts.k1]\naxes = ["a"]\n')
    cli = TwinCli(fleet, "--backend", "ecat")
    try:
        cli.expect_ready(120)
        prefix = f"tw{cli.pid % 100000}"
        procs = descendants(cli.pid)  # router, ecat-sim and agent (in the namespace), the gateway
        assert len(procs) >= 4
        os.kill(cli.pid, signal.SIGKILL)
        cli.popen.wait(10)
        wait_for(lambda: not running(procs), 20, f"no child of the SIGKILLed twin left ({running(procs)})")
        assert leftovers(prefix) == [f"{prefix}h1"]  # its namespace (the veth pair inside) outlived it
    finally:
        cli.kill()
    with Twin({"hosts": {"s1": {"axes": ["a"]}}}):  # any start (here the sim backend) cleans up
        assert leftovers(prefix) == []
