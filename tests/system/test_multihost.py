"""The full stack across a real (virtual) network: hosts as network namespaces (root).

Bed (``tests/system/multihost.py``): namespaces h1, h2 and sup on one bridge (10.213.7.0/24,
never routed outside). In h1 and h2: ``ecat-sim`` with 3 drives on ``ecs0``, ``drives-router``
on the host's address (h2's connects to h1's), ``bus-agent --ifname ecm0`` (pysoem, real
EtherCAT frames) connected to its own router, with group ``xg = h1/axis0 + h2/axis0`` in both
agents' TOML. Supervisors (``supervisor.Fleet`` children, and ``drivectl``) run in sup,
connected to h1's router. Drive states are read on the drive side (ecat-sim ``status``).

The tests run in file order on one bed; each states what it needs from the previous one.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest
import zenoh

from bus_agent.sim.netns import NetnsError, multihost_plan
from bus_agent.gateway.zenoh_config import DEFAULT_LINK_LEASE_MS, make_zenoh_config
from tests.conftest import require, require_root
from bus_agent.sim.child import free_port, wait_for
from tests.system.multihost import ROOT, MultiHostRun, Proc, SupervisorProc

pytestmark = [pytest.mark.timeout(150)]

DRIVES = 3
GROUP = ["h1/axis0", "h2/axis0"]
LEASE_TTL_S = 2.0
OPERATION_ENABLED = "operation_enabled"
#: A killed agent is reported gone within this (safety bound: link lease 3 s, plus a loaded host).
DEPARTURE_BOUND_S = 10.0


@pytest.fixture(scope="module")
def run() -> MultiHostRun:
    require_root()
    require(shutil.which("ip") is not None, "iproute2 (`ip`)", "install iproute2")
    with MultiHostRun(hosts=2, drives=DRIVES, groups={"xg": GROUP}).running() as bed:
        yield bed


@pytest.fixture(scope="module")
def sup(run: MultiHostRun) -> SupervisorProc:
    return run.start_supervisor("sup", "h1", "sup1")


@pytest.mark.root
@pytest.mark.slow
def test_discovery_of_both_agents_and_all_drives_across_hosts(run, sup):
    got = sup.call("wait_agents", hosts=["h1", "h2"], drives=2 * DRIVES, timeout_s=15.0)
    assert got["ok"], got
    assert sorted(got["hosts"]) == ["h1", "h2"]
    assert sorted(got["roster"]) == sorted(f"{h}/axis{i}" for h in ("h1", "h2") for i in range(DRIVES))
    # The bed is real: every slave is in OP behind its agent, nothing enabled unless asked.
    for h in ("h1", "h2"):
        slaves = run.controls[h].slaves()
        assert [s["al_state"] for s in slaves] == ["op"] * DRIVES, slaves
        assert OPERATION_ENABLED not in [s["drive_state"] for s in slaves]


@pytest.mark.root
@pytest.mark.slow
def test_drivectl_two_phase_enable_of_every_drive_reaches_operation_enabled(run, sup):
    proc = run.drivectl("sup", "h1", "enable", "*/*")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for h in ("h1", "h2"):
        # drivectl returns when the agents answered done; the drive side must agree.
        wait_for(lambda: run.controls[h].drive_states() == [OPERATION_ENABLED] * DRIVES, 2.0,
                 f"every drive of {h} in operation_enabled (drive side)")


@pytest.mark.root
@pytest.mark.slow
def test_cross_host_group_reflex_without_supervisor(run, sup):
    assert run.controls["h2"].drive_states()[0] == OPERATION_ENABLED, "needs the enable test before"
    reply = run.controls["h1"].request("fault", slave=0, error_code=0x7305)
    assert reply["ok"], reply
    # h2's agent sees h1/axis0's status turn fault through the two routers and quick-stops its member.
    wait_for(lambda: run.controls["h2"].drive_states()[0] != OPERATION_ENABLED, 2.0,
             "h2/axis0 leaving operation_enabled after the fault on h1/axis0")
    assert run.controls["h2"].drive_states()[0] in ("quick_stop_active", "switch_on_disabled")
    assert run.controls["h1"].drive_states()[0] == "fault"
    # Drives outside the group keep running.
    assert run.controls["h1"].drive_states()[1:] == [OPERATION_ENABLED] * (DRIVES - 1)
    assert run.controls["h2"].drive_states()[1:] == [OPERATION_ENABLED] * (DRIVES - 1)


@pytest.mark.root
@pytest.mark.slow
def test_killed_agent_is_reported_gone_and_the_sm_watchdog_stops_its_drives(run, sup):
    agent = run.agents["h2"]
    killed_at = time.monotonic()
    agent.kill()
    # The supervisor (in sup, behind h1's router) sees h2's liveliness token vanish.
    # A safety bound, not a latency figure: the supervisor must learn within the link lease (3 s)
    # that it lost control; generous for a loaded host.
    wait_for(lambda: sup.event_times("departure", "h2"), DEPARTURE_BOUND_S, "the supervisor reporting h2 gone")
    # Nobody writes process data any more: the ESCs' SM watchdog (100 ms) drops OP (0x001B)
    # and the drives' communication-loss reaction takes them out of operation_enabled.
    wait_for(lambda: all(s["al_state"] == "safeop" and s["al_status_code"] == 0x001B
                         for s in run.controls["h2"].slaves()), 2.0, "SM watchdog on every h2 slave")
    assert OPERATION_ENABLED not in run.controls["h2"].drive_states()
    assert sup.event_times("departure", "h2")[0] - killed_at < DEPARTURE_BOUND_S
    # h1 is unaffected apart from the group member (already in fault).
    assert run.controls["h1"].drive_states()[1:] == [OPERATION_ENABLED] * (DRIVES - 1)


@pytest.mark.root
@pytest.mark.slow
def test_cut_link_ends_in_a_defined_stop_of_leased_drives(run, sup):
    leased = [f"h1/axis{i}" for i in range(1, DRIVES)]
    assert run.controls["h1"].drive_states()[1:] == [OPERATION_ENABLED] * (DRIVES - 1), "needs the tests before"
    # A supervisor on h2's side of the cable holds h1's running drives.
    remote = run.start_supervisor("h2", "h2", "sup2")
    assert remote.call("wait_agents", hosts=["h1"], drives=DRIVES, timeout_s=10.0)["ok"]
    lease = remote.call("lease", selectors=leased, ttl_s=LEASE_TTL_S)
    assert lease["ok"], lease
    wait_for(lambda: all(sup.call("drives")[d]["lease_holder"] == "sup2" for d in leased), 2.0,
             "the lease visible in h1's drive status")
    run.link("h2", up=False)
    try:
        # Renewals stop reaching h1: the ttl runs out (or h1 sees sup2's token vanish when the
        # link lease ends) and the lease reaction stops the drives: quick stop, then disable.
        deadline_s = DEFAULT_LINK_LEASE_MS / 1000 + LEASE_TTL_S + 1.0
        wait_for(lambda: all(s != OPERATION_ENABLED for s in run.controls["h1"].drive_states()[1:]), deadline_s,
                 "h1's leased drives leaving operation_enabled after the cut")
        wait_for(lambda: run.controls["h1"].drive_states()[1:] == ["switch_on_disabled"] * (DRIVES - 1), 3.0,
                 "h1's leased drives disabled (quick stop, then disable)")
        # The supervisor on h1's side still sees h1, now without a lease holder.
        wait_for(lambda: all(sup.call("drives")[d]["lease_holder"] == "" for d in leased), 2.0, "lease ended")
    finally:
        run.link("h2", up=True)


# ---- pieces that need no root: the bed's plan and drives-router on loopback --------------------

def test_multihost_plan_names_and_addresses():
    bed = multihost_plan("mh", 2, extra=("sup",))
    assert bed.switch_netns == "mhsw" and bed.cidr == "10.213.7.0/24"
    assert [(h.name, h.netns, h.address, h.port, h.ecat_master, h.ecat_sim) for h in bed.hosts] == [
        ("h1", "mhh1", "10.213.7.1", "ph1", "ecm0", "ecs0"),
        ("h2", "mhh2", "10.213.7.2", "ph2", "ecm0", "ecs0"),
        ("sup", "mhsup", "10.213.7.101", "psup", None, None)]
    assert bed.host("h2").exec_argv("true") == ["ip", "netns", "exec", "mhh2", "true"]
    with pytest.raises(NetnsError, match="no host 'h3'"):
        bed.host("h3")


@pytest.mark.parametrize("kwargs, match", [
    (dict(prefix="1x"), "prefix"), (dict(prefix="toolongprefix"), "prefix"),
    (dict(subnet="192.168.1"), "subnet"), (dict(subnet="10.300.1"), "subnet"),
    (dict(hosts=0), "hosts"), (dict(extra=("h1",)), "extra"), (dict(extra=("sw",)), "extra"),
])
def test_multihost_plan_rejects_bad_input(kwargs, match):
    args = dict(prefix="mh", hosts=2, subnet="10.213.7", extra=())
    args.update(kwargs)
    with pytest.raises(NetnsError, match=match):
        multihost_plan(args.pop("prefix"), args.pop("hosts"), **args)


def test_drives_router_relays_between_clients_and_stops_cleanly_on_sigterm(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = Proc("drives-router", [sys.executable, "-m", "bus_agent.router", "--config",
                                    str(ROOT / "deploy" / "router.json5"), "--listen", ep], ready_marker="drives-router ready")
    try:
        router.expect_ready(20)
        assert f"listen={ep}" in router.lines[0]
        # Two clients meet only through the router.
        a = zenoh.open(make_zenoh_config("client", (), (ep,)))
        b = zenoh.open(make_zenoh_config("client", (), (ep,)))
        try:
            got: list[bytes] = []
            sub = b.declare_subscriber("drives/@test/x", lambda s: got.append(s.payload.to_bytes()))
            wait_for(lambda: (a.put("drives/@test/x", b"hi"), got)[1], 5.0, "a sample through the router")
            sub.undeclare()
        finally:
            a.close()
            b.close()
        assert router.stop() == 0
    finally:
        router.kill()


def test_drives_router_rt_priority_puts_every_zenoh_thread_under_sched_fifo():
    """--rt-priority: the router's threads (zenoh's runtime threads inherit the policy) run under
    SCHED_FIFO at that priority; it still relays and stops cleanly (root)."""
    require_root()
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = Proc("drives-router", [sys.executable, "-m", "bus_agent.router", "--listen", ep, "--rt-priority", "7"],
                  ready_marker="drives-router ready")
    try:
        router.expect_ready(20)
        assert "rt_priority=7" in router.lines[0]
        a = zenoh.open(make_zenoh_config("client", (), (ep,)))
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{router.popen.pid}/task")]
            policies = {tid: (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority) for tid in tids}
            assert len(tids) > 3 and set(policies.values()) == {(os.SCHED_FIFO, 7)}, policies
        finally:
            a.close()
        assert router.stop() == 0
    finally:
        router.kill()


@pytest.mark.parametrize("argv, code, match", [
    (["--listen", "nonsense"], 2, "not a zenoh locator"),
    (["--config", "/nonexistent/router.json5"], 2, "router config"),
    (["--insecure", "--listen", "tcp/192.0.2.254:7447"], 3, "cannot open"),  # TEST-NET address: not on this host
    (["--listen", "tcp/192.0.2.254:7447"], 2, "--insecure"),  # off loopback without --pki: refused first
    (["--rt-priority", "100"], 2, "must be 0 (off) or a SCHED_FIFO priority 1..99"),
])
def test_drives_router_bad_input_is_a_clear_error(argv, code, match):
    proc = subprocess.run([sys.executable, "-m", "bus_agent.router", *argv], capture_output=True, text=True,
                          timeout=30, cwd=ROOT)
    assert proc.returncode == code, proc.stderr
    assert match in proc.stderr
