"""Motion end to end: simulated agents in their own process behind a router, commanded by the Fleet API
and by ``drivectl`` as a subprocess (moves, limits refused, jog, stop and release, a group move
across two agents with prepare and commit, status fields)."""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Iterator

import pytest

from supervisor.fleet import Fleet
from supervisor.testbed import _env, enabled_sim_bed

pytestmark = pytest.mark.timeout(240)

HOSTS = ("m1", "m2")


@pytest.fixture(scope="module")
def bed() -> Iterator[str]:
    # One process, one agent (and Zenoh session) per host.
    with enabled_sim_bed(HOSTS, 2) as ep:
        yield ep


def drivectl(ep: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", ep, "--json", *args],
                          capture_output=True, text=True, timeout=60, env=_env())


def test_fleet_move_done_status_shows_motion_and_limits_are_refused(bed: str) -> None:
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=4)
        res = f.move("m1/axis0", to=20_000, timeout_s=10)
        assert res.ok, res.failures
        assert res.results[0].duration_s > 0
        st = f.fetch_status("m1/axis0")
        s = next(iter(st.values()))
        assert (s.position, s.target_position, s.axis_state, s.motion_request_id) == (20_000, 20_000, "standstill", "")
        bad = f.move("m1/axis0", by=10, velocity=1e9)
        assert [r.outcome for r in bad.results] == ["rejected"]
        assert "exceeds the axis velocity limit" in bad.results[0].error
        started = f.jog("m1/axis1", velocity=-10_000, for_s=0.3)
        assert started.ok, started.failures


def test_drivectl_move_jog_stop_release(bed: str) -> None:
    r = drivectl(bed, "move", "m2/axis0", "--by", "5000", "--velocity", "50000", "--timeout", "10")
    assert r.returncode == 0, r.stdout + r.stderr
    r = drivectl(bed, "stop", "m2/axis0")
    assert r.returncode == 0, r.stdout + r.stderr
    r = drivectl(bed, "move", "m2/axis0", "--to", "0")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "stop" in r.stdout and "rejected" in r.stdout
    assert drivectl(bed, "stop", "--release", "m2/axis0").returncode == 0
    r = drivectl(bed, "jog", "m2/axis0", "--velocity", "20000", "--for", "0.2")
    assert r.returncode == 0, r.stdout + r.stderr
    r = drivectl(bed, "move", "m2/axis0")
    assert r.returncode == 2 and "--to" in r.stdout  # usage error, nothing sent


def test_group_move_across_two_agents_prepares_then_commits(bed: str) -> None:
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=4)
        targets = {"m1/axis0": -30_000.0, "m1/axis1": 5_000.0, "m2/axis1": 60_000.0}
        res = f.group_move(targets, timeout_s=15)
        assert res.ok, res.failures
        assert len(res.results) == 3 and len({round(r.duration_s, 6) for r in res.results}) == 1
        st = f.fetch_status(list(targets))
        # done = at rest within the position window (10 counts by default) of the target: the
        # drive may settle on the last count a cycle after the reply
        assert {str(ref): s.target_position for ref, s in st.items()} == {k: int(v) for k, v in targets.items()}
        assert all(abs(st_pos - targets[ref]) <= 10 for ref, st_pos in ((str(r), s.position) for r, s in st.items())), st
        refused = f.group_move({"m1/axis0": 0.0, "m2/axis1": 1e12})
        assert not refused.ok
        assert {r.outcome for r in refused.results} == {"rejected"}
        st = f.fetch_status(["m1/axis0"])
        assert next(iter(st.values())).position == -30_000  # nothing moved


def test_watch_json_shows_the_axis_state(bed: str) -> None:
    r = subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", bed, "watch", "--json", "m1/axis0",
                        "--duration", "1"], capture_output=True, text=True, timeout=60, env=_env())
    lines = [json.loads(x) for x in r.stdout.splitlines() if x.strip()]
    assert any(x.get("axis_state") == "standstill" for x in lines), r.stdout + r.stderr


def test_home_by_fleet_and_drivectl(bed: str) -> None:
    """Homing in mode 6 end to end: Fleet.home with the switch method, drivectl home --method 37,
    a bad method rejected naming it (exit 1), status shows homed."""
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=4)
        res = f.home("m1/axis1", method=19, timeout_s=20)
        assert res.ok, res.failures
        assert "method 19" in res.results[0].error
        s = next(iter(f.fetch_status(["m1/axis1"]).values()))
        assert s.homed and s.mode_display == 8 and s.axis_state == "standstill"
    r = drivectl(bed, "home", "m2/axis1", "--method", "37", "--timeout", "20")
    assert r.returncode == 0, r.stdout + r.stderr
    r = drivectl(bed, "home", "m2/axis1", "--method", "99")
    assert r.returncode == 1 and "homing method 99" in r.stdout, r.stdout + r.stderr


def test_group_move_whose_commit_fails_on_one_host_stops_the_other(bed: str) -> None:
    """m2's drive faults between prepare and commit (injected in its simulator just before m2's
    commit leaves): m2 refuses the commit, and m1, which had started, is stopped (outcome
    ``aborted``, axis ``stopping``) instead of finishing a synchronized move alone."""
    import time

    from supervisor.simctl import inject

    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=4)
        start = next(iter(f.fetch_status(["m1/axis0"]).values())).position
        real_send = f.send

        def send(op, sel, args=None, timeout_s=5.0):  # type: ignore[no-untyped-def]
            if op == "move" and args and "start_at_ns" in args and any(r.host == "m2" for r in sel.drives):
                inject(f, "fault", "m2/axis0", error_code=0x2310)
                deadline = time.monotonic() + 5.0
                while next(iter(f.fetch_status(["m2/axis0"]).values())).state != "fault":
                    assert time.monotonic() < deadline, "the injected fault never showed"
                    time.sleep(0.02)
            return real_send(op, sel, args, timeout_s)

        f.send = send  # type: ignore[method-assign]  # the group path's sends, the real ones after the fault
        try:
            t0 = time.monotonic()
            res = f.group_move({"m1/axis0": start + 200_000.0, "m2/axis0": 1_000.0}, velocity=20_000.0, timeout_s=20)
            took = time.monotonic() - t0
        finally:
            f.send = real_send  # type: ignore[method-assign]
        outcomes = {r.name: r.outcome for r in res.results}
        assert outcomes["m1/axis0"] == "aborted", res.results
        assert outcomes["m2/axis0"] in ("rejected", "failed"), res.results
        assert "stop" in next(r.error for r in res.results if r.name == "m1/axis0")
        assert took < 8.0  # the 10 s move did not run to its end
        s = next(iter(f.fetch_status(["m1/axis0"]).values()))
        assert s.axis_state == "stopping" and abs(s.position - start) < 200_000
        # put the bed back: release m1's stop, reset and enable m2's drive
        assert f.stop("m1/axis0", release=True).ok
        assert f.fault_reset("m2/axis0").ok
        assert f.enable("m2/axis0").ok
