"""``drivectl sim`` by axis name against ``ecat-sim`` (the virtual EtherCAT segment behind a real
``bus-agent --ifname``): the same verbs as on ``bus-agent --sim``, with ``--segment``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from bus_agent.sim.child import ChildProcess, free_port
from supervisor.fleet import Fleet
from supervisor.testbed import _env

pytestmark = [pytest.mark.root, pytest.mark.timeout(180)]

HOST = "sz"


def test_sim_verbs_by_axis_name_on_ecat_sim(ecat_segment) -> None:
    sim_ep = f"tcp/127.0.0.1:{free_port()}"
    ifname, control = ecat_segment(2, "generic", "--zenoh-listen", sim_ep)
    segment = control.request("ping")["segment"]
    agent_ep = f"tcp/127.0.0.1:{free_port()}"
    agent = ChildProcess("bus-agent", [sys.executable, "-m", "bus_agent.cli", "--ifname", ifname, "--host", HOST,
                                       "--listen", agent_ep, "--log-level", "WARNING"], ready_marker="bus-agent ready")

    def drivectl(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "supervisor.cli", "--mode", "peer", "-c", agent_ep, "-c", sim_ep,
                               *args], capture_output=True, text=True, timeout=60, env=_env())

    try:
        agent.expect_ready(40)
        r = drivectl("--json", "sim", "fault", f"{HOST}/axis1", "0x8611", "--segment", segment)
        assert r.returncode == 0, r.stdout + r.stderr
        assert json.loads(r.stdout)["results"][0] == {"drive": f"{HOST}/axis1", "segment": segment, "slave": 1,
                                                       "detail": json.loads(r.stdout)["results"][0]["detail"]}
        with Fleet(connect=[agent_ep]) as f:
            assert f.wait_until(lambda f: (st := f.status(f"{HOST}/axis1")) is not None and st.state == "fault"
                                and st.error_text == "following error", 15)
            assert drivectl("sim", "unplug", f"{HOST}/axis0", "--segment", segment).returncode == 0
            assert f.wait_until(lambda f: f.status(f"{HOST}/axis0").lost, 15)
            assert drivectl("sim", "plug", f"{HOST}/axis0", "--segment", segment).returncode == 0
            assert f.wait_until(lambda f: not f.status(f"{HOST}/axis0").lost
                                and f.status(f"{HOST}/axis0").al_state == "op", 30)
        slaves = control.request("status")["slaves"]
        assert slaves[1]["drive_state"] == "fault"
        # without --segment the host name is tried: no simulator by that name, and the error says what to give
        r = drivectl("--timeout", "1", "sim", "plug", f"{HOST}/axis0")
        assert r.returncode == 1 and "--segment" in r.stdout, r.stdout + r.stderr
    finally:
        agent.stop(20)
        agent.kill()
