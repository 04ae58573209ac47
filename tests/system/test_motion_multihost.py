"""A synchronized move across two hosts that are network namespaces (root).

Bed (``tests/system/multihost.py``): namespaces h1, h2 and sup on one bridge; in h1 and h2
``ecat-sim`` with two drives, a ``drives-router`` and ``bus-agent`` (pysoem, real EtherCAT
frames). A ``supervisor.Fleet`` in sup runs ``group_move`` over both hosts: prepare (each agent
plans and returns its axes' minimum duration), then commit (the longest duration and one
wall-clock start time a margin ahead, to both agents at once).

The agents' own stamps judge it: each agent's flight recording (every cycle's wall time, the
0x607A it wrote and the 0x6064 its drives reported) gives per axis the first cycle whose target
moved and the first cycle at the target. The two hosts share the kernel's clock here, so the
figures are the agents' own scheduling (real hosts add their clock offset: chrony/PTP).
"""

from __future__ import annotations

import shutil

import pytest

from supervisor.motion import START_MARGIN_S
from tests.conftest import require, require_root
from tests.system.multihost import MultiHostRun

pytestmark = [pytest.mark.timeout(180)]

HOSTS = ("h1", "h2")
CYCLE_S = 0.001
#: A host's scheduling stalls on the shared 2-core machine (both hosts, their simulators and
#: routers on 2 vCPUs): the figures are printed, and on a quiet machine they are within a cycle
#: or two, but a CI run once saw one host arrive 43 ms after the other. The test checks the
#: mechanism, not the timing (bench_motion measures the arrival spread): a host that started on
#: receipt of the commit instead of at the committed time would be START_MARGIN_S (250 ms) off,
#: and the durations are checked equal, so 50 ms still tells a broken synchronization apart.
SCHEDULING_SLACK_S = 0.050
TARGETS = {"h1/axis0": 30_000.0, "h1/axis1": -15_000.0, "h2/axis0": 45_000.0, "h2/axis1": 5_000.0}


#: The agents' cycle threads run at SCHED_FIFO 10, as deployed (docs/deployment.md): since the
#: targets keep the axis limits on the wire (issue 23), a host whose unprioritized cycle loses
#: frame slots on the loaded machine arrives late by what its limits cannot make up (60-614 ms
#: at load 8-28 without it; 0.2-1.1 ms with it), where the wall-clock sampling before kept the
#: arrival by stepping over the limits.
AGENT_ARGS = ("--rt-priority", "10")


@pytest.fixture(scope="module")
def run() -> MultiHostRun:
    require_root()
    require(shutil.which("ip") is not None, "iproute2 (`ip`)", "install iproute2")
    with MultiHostRun(hosts=2, drives=2, agent_args=AGENT_ARGS).running() as bed:
        yield bed


@pytest.mark.root
@pytest.mark.slow
def test_cross_host_group_move_starts_and_arrives_together(run):
    sup = run.start_supervisor("sup", "h1", "sup1")
    assert sup.call("wait_agents", hosts=list(HOSTS), drives=4, timeout_s=15.0)["ok"]
    assert sup.call("enable", selectors=["*/*"])["ok"]
    res = sup.call("group_move", timeout_s=60.0, targets=TARGETS, move_timeout_s=30.0)
    assert res["ok"], res
    assert len(set(res["durations"].values())) == 1, res  # one common duration on both hosts
    start: dict[str, float] = {}
    arrive: dict[str, float] = {}
    for h in HOSTS:
        rec = sup.call("recording", timeout_s=40.0, host=h, last_s=8.0)
        for axis, rows in rec.items():  # rows: (wall s, 0x607A written, 0x6064 reported)
            ref = f"{h}/{axis}"
            t0 = rows[0][1]
            start[ref] = next(t for t, target, _ in rows if target != t0)
            arrive[ref] = next(t for t, _, pos in rows if t > start[ref] and pos == int(TARGETS[ref]))
    start_spread = max(start.values()) - min(start.values())
    arrive_spread = max(arrive.values()) - min(arrive.values())
    print(f"cross-host synchronized move: start spread {start_spread * 1e3:.3f} ms, "
          f"arrival spread {arrive_spread * 1e3:.3f} ms (agents' own stamps)")
    # Both started at the committed wall-clock time, a margin after the call (not on receipt of
    # the commit, which comes earlier) ...
    assert min(start.values()) >= res["called_s"] + START_MARGIN_S - CYCLE_S, (res["called_s"], start)
    # ... each at the first of its cycles at or after it (the agents' cycles are not phase-aligned:
    # up to one cycle apart) and arrives one common duration later; plus scheduling slack.
    assert start_spread <= 2 * CYCLE_S + SCHEDULING_SLACK_S, start
    assert arrive_spread <= 3 * CYCLE_S + SCHEDULING_SLACK_S, arrive
