"""``move --sync`` is one group move whatever selects the drives (issue 23 #4): simulated agents
in their own process behind a router, commanded by ``drivectl`` and the Fleet API.

A selector zenoh cannot say in one key expression (a class ``axis[01]``, a list, several hosts)
used to become one query per drive, so each axis started and arrived on its own (exit 0). Now
every synchronized move goes through the group path: one query per host naming its axes,
prepare and commit across hosts; or it is refused as a whole, nothing moving. The agents' own
flight recordings (every cycle's 0x6064) judge the arrivals.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Iterator

import pytest
import zenoh

from supervisor.fleet import Fleet
from supervisor.recordings import fetch_recording
from supervisor.session import zenoh_config
from supervisor.testbed import _env, enabled_sim_bed

pytestmark = pytest.mark.timeout(240)

HOSTS = ("s1", "s2")


@pytest.fixture(scope="module")
def bed() -> Iterator[str]:
    with enabled_sim_bed(HOSTS, 3) as ep:
        yield ep


def drivectl(ep: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", ep, "--json", *args],
                          capture_output=True, text=True, timeout=60, env=_env())


def arrivals(ep: str, host: str, target: int, axes: list[str]) -> dict[str, tuple[int, int]]:
    """Per axis (first cycle, its wall ns) at ``target`` after the last cycle away from it, from
    the agent's flight recording of the last 8 s."""
    with zenoh.open(zenoh_config("client", [ep])) as s:
        rec = fetch_recording(s, host, "last", 8.0)
    n = len(rec.axes)
    out = {}
    for axis in axes:
        j = rec.axes.index(axis)
        pos = rec.channels["position"][j::n]
        away = max(i for i, p in enumerate(pos) if p != target)  # the last cycle still moving
        assert away + 1 < len(pos), f"{host}/{axis} never reached {target}"
        out[axis] = (rec.channels["cycle"][away + 1], rec.channels["time_ns"][away + 1])
    return out


def test_class_selector_on_part_of_a_host_arrives_together(bed: str) -> None:
    """``move 's1/axis[01]' --sync``: two of s1's three axes, from different distances, one group."""
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=6)
        assert f.move("s1/axis0", to=30_000, timeout_s=15).ok
        assert f.move("s1/axis1", to=0, timeout_s=15).ok
    r = drivectl(bed, "move", "s1/axis[01]", "--to", "60000", "--sync", "--timeout", "20")
    assert r.returncode == 0, r.stdout + r.stderr
    out = json.loads(r.stdout)
    results = {x["axis"]: x for x in out["final"]}
    assert set(results) == {"axis0", "axis1"}, out  # axis2 is not part of it
    assert results["axis0"]["duration_s"] == pytest.approx(results["axis1"]["duration_s"], abs=1e-6), out
    arr = arrivals(bed, "s1", 60_000, ["axis0", "axis1"])
    cycles = [c for c, _ in arr.values()]
    print(f"s1/axis[01] --sync: arrival cycles {arr}")
    # One plan sampled by one cycle: the same cycle, or the next (the drive settles on the last count).
    assert max(cycles) - min(cycles) <= 2, arr
    # Relative (--by, the host's axes named in the query): one group too; axis2 stays out of it.
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=6)
        before = next(iter(f.fetch_status(["s1/axis2"]).values())).position
        res = f.move("s1/axis[01]", by=-10_000, sync=True, timeout_s=20)
        assert res.ok and [r.axis for r in res.results] == ["axis0", "axis1"], res
        st = f.fetch_status(["s1/axis0", "s1/axis1", "s1/axis2"])
        assert {str(k): v.target_position for k, v in st.items()} == {
            "s1/axis0": 50_000, "s1/axis1": 50_000, "s1/axis2": before}, st


def test_class_selector_across_hosts_prepares_and_commits(bed: str) -> None:
    """``s[12]/axis2``: one axis on each host (two per-drive queries before), one group."""
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=6)
        assert f.move("s1/axis2", to=0, timeout_s=15).ok
        assert f.move("s2/axis2", to=40_000, timeout_s=15).ok
        res = f.move("s[12]/axis2", to=-20_000, sync=True, timeout_s=20)
        assert res.ok, res.failures
        assert len({round(r.duration_s, 6) for r in res.results}) == 1, res.results
    a1 = arrivals(bed, "s1", -20_000, ["axis2"])["axis2"][1]
    a2 = arrivals(bed, "s2", -20_000, ["axis2"])["axis2"][1]
    print(f"s[12]/axis2 --sync: arrival spread {(a2 - a1) / 1e6:.3f} ms")
    # Started at one committed wall time and one common duration: within a few cycles and the
    # scheduling slack of a shared 2-core machine (as test_motion_multihost); unsynchronized the
    # 20000 and 60000 count moves arrive hundreds of ms apart.
    assert abs(a2 - a1) <= 60e6, (a1, a2)


def test_sync_refused_as_a_whole(bed: str) -> None:
    """One drive that cannot move refuses the whole group: exit 1, the reason, nothing moves."""
    with Fleet(connect=[bed]) as f:
        f.wait_for_agents(HOSTS, 10, drives=6)
        assert f.move("s1/axis0", to=5_000, timeout_s=15).ok
        assert f.move("s2/axis0", to=5_000, timeout_s=15).ok
        assert f.stop("s2/axis0").ok  # motion refused on s2/axis0 until released
        try:
            r = drivectl(bed, "move", "s[12]/axis0", "--by", "10000", "--sync", "--timeout", "15")
            assert r.returncode == 1, r.stdout + r.stderr
            out = json.loads(r.stdout)
            assert {x["outcome"] for x in out["final"]} == {"rejected"}, out
            s1 = next(x for x in out["final"] if x["host"] == "s1")
            assert "group move refused" in s1["error"] and "s2/axis0" in s1["error"], s1
            st = f.fetch_status(["s1/axis0", "s2/axis0"])
            assert {str(k): v.position for k, v in st.items()} == {"s1/axis0": 5_000, "s2/axis0": 5_000}
        finally:
            assert f.stop("s2/axis0", release=True).ok
    # A drive no live agent reports (an expected host offline): refused before anything is sent.
    with Fleet(connect=[bed], expected={"hosts": {"s1": {"axes": ["axis0", "axis1", "axis2"]},
                                                  "s9": {"axes": ["axis0"]}}}) as f:
        f.wait_for_agents(HOSTS, 10, drives=6)
        res = f.move("s1/axis0", "s9/axis0", to=0, sync=True, timeout_s=10)
        assert [r.outcome for r in res.results] == ["rejected", "rejected"]
        assert all("s9/axis0: no live agent reports this drive" in r.error for r in res.results), res.results
        assert next(iter(f.fetch_status(["s1/axis0"]).values())).position == 5_000
