"""The flight recorder end to end: a ``bus-agent`` process (gateway in its own process), a router,
a fault injected through the simulator's key space, then ``drivectl record`` and ``drivectl plot``
as a user runs them. The recording holds the cycles before the fault with the statusword moving
to Fault, and its plot is a PNG."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Iterator

import pytest
import zenoh

from bus_agent.cia402.states import State, decode_statusword
from bus_agent.sim.control import sim_inject
from schemas import keys
from schemas import messages as m
from supervisor.fleet import Fleet
from supervisor.session import zenoh_config
from supervisor.recordings import fetch_recording, read_csv
from supervisor.testbed import Proc, _env, start_cli_agent, start_router

pytestmark = pytest.mark.timeout(180)

HOST = "rec1"


@pytest.fixture(scope="module")
def bed() -> Iterator[str]:
    router, ep = start_router()
    agent: Proc | None = None
    try:
        agent = start_cli_agent(HOST, 3, ep)
        with Fleet(connect=[ep]) as f:
            assert f.wait_for_agents([HOST], 10, drives=3)
        yield ep
    finally:
        if agent is not None:
            agent.stop()
        router.stop()


def drivectl(ep: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", ep, *args],
                          capture_output=True, text=True, timeout=90, env=_env())


def test_recording_around_an_injected_fault(bed: str, tmp_path: Path) -> None:
    r = drivectl(bed, "enable", f"{HOST}/*")
    assert r.returncode == 0, r.stdout + r.stderr
    out = tmp_path / "before.csv"
    r = drivectl(bed, "record", HOST, "--trigger", "last-fault", "--out", str(out))
    assert r.returncode == 1 and "no window frozen by a fault trigger" in r.stdout, r.stdout + r.stderr
    assert not out.exists()
    with zenoh.open(zenoh_config("client", [bed])) as s:
        with Fleet(connect=[bed]) as f:
            # the recording must be able to hold >= 1 s before the fault: on a fast machine the
            # agent may have run less than that since its start, so wait for its cycle count
            def ran_enough(fl: Fleet) -> bool:
                info = fl.agents().get(HOST)
                return info is not None and info.status is not None and info.status.cycles >= 2000
            assert f.wait_until(ran_enough, 30)
            sim_inject(s, HOST, 1, "fault", error_code=0x7500)
            assert f.wait_until(lambda fl: (st := fl.status(f"{HOST}/axis1")) is not None and st.state == "fault", 10)
    csv_path = tmp_path / "fault.csv"
    # Asked at once (the window closes post_s = 1 s after the fault): the agent waits for the
    # window being recorded and answers with it, in one call.
    r = drivectl(bed, "--json", "record", HOST, "--trigger", "last-fault", "--out", str(csv_path))
    assert r.returncode == 0, r.stdout + r.stderr
    table = read_csv(csv_path)
    assert table.meta["reason"] == "fault" and table.meta["axis"] == "axis1"
    assert table.axes == ["axis0", "axis1", "axis2"]
    trigger = int(table.meta["trigger_cycle"])
    cycles = table.column("axis1", "cycle")
    states = [decode_statusword(sw) for sw in table.column("axis1", "statusword")]
    before = [s for c, s in zip(cycles, states) if c < trigger - 2]
    assert len(before) >= 1000, "at least a second of cycles before the fault"
    # The window reaches back past the enable: the way up, then Operation enabled until the fault.
    assert before[0] != State.OPERATION_ENABLED or len(before) >= 4000
    assert all(s == State.OPERATION_ENABLED for s in before[-200:])
    assert State.FAULT in [s for c, s in zip(cycles, states) if c >= trigger]
    assert table.column("axis1", "error_code")[-1] == 0x7500
    assert cycles == list(range(cycles[0], cycles[0] + len(cycles)))  # consecutive cycles
    assert table.column("axis1", "state")[-1] == "fault"
    png = tmp_path / "fault.png"
    r = drivectl(bed, "plot", str(csv_path), "--out", str(png))
    assert r.returncode == 0, r.stdout + r.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_last_seconds_and_bad_requests(bed: str, tmp_path: Path) -> None:
    with zenoh.open(zenoh_config("client", [bed])) as s:
        rec = fetch_recording(s, HOST, "last", 0.5)
        assert rec.reason == "last" and 450 <= rec.n_cycles <= 500 and rec.axes == ["axis0", "axis1", "axis2"]
        assert len(rec.channels["statusword"]) == rec.n_cycles * 3
        # A malformed request is refused with the reason; nothing else happens.
        replies = list(s.get(keys.agent_recording(HOST), payload=b"\x93garbage", timeout=10))
        errs = [r.err.payload.to_string() for r in replies if r.err is not None]
        assert any("invalid recording_request" in e for e in errs), errs
        bad = m.encode(m.RecordingRequest(what="last")).replace(b"last", b"lost")  # valid what, still no window
        replies = list(s.get(keys.agent_recording(HOST), payload=bad, timeout=10))
        assert any(r.err is not None for r in replies)
    r = drivectl(bed, "plot", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "x.png"))
    assert r.returncode == 2 and "missing.csv" in r.stderr
