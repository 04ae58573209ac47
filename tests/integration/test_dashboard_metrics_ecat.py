"""The dashboard's DC offset and following error metrics against a real agent on ``ecat-sim`` (root).

A router, the whole agent (``bus-agent --ifname``: pysoem, cycle, gateway process) on a veth pair
to ``ecat-sim`` with a DC drive that maps 0x60F4 (``omron1s:dc-required``, SYNC0 started by
``[dc] mode = "auto"``) and a generic drive that does not, and ``drives-dashboard`` as its own
process. Both drives jog in CSP; the omron drive's 0x607F is lowered by a start-up SDO so it lags
its target and reports a following error of its own. ``/metrics``, parsed with the Prometheus
client's parser, carries the DC offset of the agent and the following error of both drives
(``0x60F4`` and ``agent`` sources), with values the agent published.
"""

from __future__ import annotations

import json
import sys
import threading
import urllib.request
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from bus_agent.sim.child import ChildProcess, free_port, wait_for
from schemas.messages import AgentStatus, DriveStatus
from supervisor.fleet import Fleet
from supervisor.testbed import start_dashboard, start_router

pytestmark = [pytest.mark.root, pytest.mark.timeout(150)]

HOST = "dcm"
#: The omron drive's speed limit (0x607F) and the jog: it falls behind by 1000 counts/s for the
#: 6 s of the jog, inside its following error window (0x6065, raised so that late cycles on a
#: loaded machine do not fault it).
VMAX = 5000
JOG = 6000.0
JOG_S = 6.0
WINDOW = 1_000_000
CONFIG = f"""
host = "{HOST}"

[[drives]]
slave = 0
[[drives.sdo]]
index = 0x607F
subindex = 0
type = "u32"
value = {VMAX}
[[drives.sdo]]
index = 0x6065
subindex = 0
type = "u32"
value = {WINDOW}

[[drives]]
slave = 1
"""


def _scrape(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "/metrics", timeout=10) as r:
        return {f.name: f for f in text_string_to_metric_families(r.read().decode())}


def _samples(fams: dict[str, Any], name: str, *keys: str) -> dict[tuple[str, ...], float]:
    fam = fams.get(name)
    return {tuple(s.labels[k] for k in keys): s.value for s in fam.samples} if fam is not None else {}


def test_dc_offset_and_following_error_metrics_against_a_dc_drive(ecat_segment, tmp_path) -> None:
    ifname, control = ecat_segment(2, "omron1s:dc-required,generic")
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f'ifname = "{ifname}"\n' + CONFIG)
    router, ep = start_router()
    agent = dash = None
    try:
        agent = ChildProcess("bus-agent", [sys.executable, "-m", "bus_agent.cli", "--config", str(cfg), "--listen", f"tcp/127.0.0.1:{free_port()}",
                                           "--connect", ep], ready_marker="bus-agent ready")
        agent.expect_ready(60)
        dash, url = start_dashboard(ep)
        published: dict[tuple[str, str], set[int]] = {("axis0", "0x60F4"): set(), ("axis1", "agent"): set()}
        offsets: set[tuple[float, float]] = set()

        def on_status(st: DriveStatus) -> None:
            if st.lost:
                return  # a lost drive publishes no inputs (its objects are empty)
            if st.host == HOST and st.axis == "axis0":
                published[("axis0", "0x60F4")].add(st.objects["following_error_actual_value"])
            elif st.host == HOST and st.axis == "axis1":
                published[("axis1", "agent")].add(st.following_error)

        def on_agent(st: AgentStatus) -> None:
            if st.host == HOST:
                offsets.add((st.dc_offset_p50_us, st.dc_offset_p99_us))

        with Fleet(connect=[ep]) as fleet:
            fleet.on("status", on_status)
            fleet.on("agent", on_agent)
            assert fleet.wait_for_agents([HOST], 20, drives=2), agent.output()
            wait_for(lambda: (a := fleet.agents().get(HOST)) is not None and a.status is not None, 20,
                     "the agent's status")
            assert dict(fleet.agents()[HOST].status.dc) == {"axis0": "sync0", "axis1": "none"}
            # DC: the agent's offset, as it published it, in seconds; no following error at rest
            # but the drive's own 0x60F4 (the generic drive is disabled: unknown).
            def dc_matches() -> bool:
                dc = _samples(_scrape(url), "drives_dc_offset_seconds", "host", "quantile")
                got = (round(dc.get((HOST, "0.5"), -1) * 1e6, 3), round(dc.get((HOST, "0.99"), -1) * 1e6, 3))
                return got in {(round(a, 3), round(b, 3)) for a, b in offsets}
            wait_for(dc_matches, 20, "the agent's DC offset on /metrics")
            fams = _scrape(url)
            dc = _samples(fams, "drives_dc_offset_seconds", "host", "quantile")
            assert 0.0 < dc[(HOST, "0.5")] < 0.001 and 0.0 < dc[(HOST, "0.99")] < 0.001, dc  # within the 1 ms cycle
            assert set(_samples(fams, "drives_drive_following_error_increments", "axis", "source")) == \
                {("axis0", "0x60F4")}

            res = fleet.command("enable", fleet.select(f"{HOST}/*"), timeout_s=20.0)
            assert res.ok, res.to_dict()
            jog: list[Any] = []
            t = threading.Thread(target=lambda: jog.append(fleet.jog(f"{HOST}/*", velocity=JOG, for_s=JOG_S,
                                                                     timeout_s=30.0)))
            t.start()
            seen: dict[tuple[str, str], float] = {}

            def moving_and_published() -> bool:
                fe = _samples(_scrape(url), "drives_drive_following_error_increments", "axis", "source")
                for ref, v in fe.items():
                    if abs(v) > abs(seen.get(ref, 0)) and int(v) in published.get(ref, ()):
                        seen[ref] = v
                # the omron drive lags its target at its 0x607F limit: its error grows past 100
                return set(seen) == set(published) and abs(seen[("axis0", "0x60F4")]) > 100
            try:
                wait_for(moving_and_published, 20, "a following error of both drives as published (omron's > 100)")
            except AssertionError as e:
                t.join(40)
                raise AssertionError(f"{e}; seen {seen}; jog {jog[0].to_dict() if jog else None}; published "
                                     f"{ {k: sorted(v)[-5:] for k, v in published.items()} }") from None
            finally:
                t.join(40)
            assert jog and jog[0].ok, jog[0].to_dict() if jog else "no jog result"
        body = json.loads(urllib.request.urlopen(url + "/api/fleet", timeout=10).read())
        host = next(h for h in body["hosts"] if h["host"] == HOST)
        assert 0.0 < host["dc_offset_p50_us"] < 1000.0
        rows = {d["axis"]: d for d in body["drives"] if d["host"] == HOST}
        assert isinstance(rows["axis0"]["following_error"], int) and isinstance(rows["axis1"]["following_error"], int)
    finally:
        for p in (dash, agent):
            if p is not None:
                p.stop()
        router.stop()
