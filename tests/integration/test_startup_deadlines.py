"""Every blocking start-up step of ``bus-agent --ifname`` has a deadline, and SIGTERM ends the
agent within 2 s in any step (issue 23, item 9), against ``ecat-sim`` over a veth pair.

A slave with a malformed SII (``bad_sii``: a category whose length sends SOEM's category walk back
to its own header) makes SOEM loop for ever: in config_init (the loop before the GENERAL
category; the call releases the interpreter's lock), or in config_map (the loop before the PDO
categories, which SOEM reads when its own CoE reading of the PDO sizes got no answer: ``mute_sdo``
of 0x1C00:00; config_map holds the lock, so no Python code of the agent runs). Before this was
fixed the agent spun at 100 % of a core and ignored SIGTERM.
"""

from __future__ import annotations

import signal
import sys
import time

import pytest

from bus_agent.sim.child import ChildProcess, free_port, wait_for
from bus_agent.startup_guard import GUARD_MARGIN_S

pytestmark = [pytest.mark.root, pytest.mark.timeout(90)]

SOEM_CALL_S = 3.0
SOEM_STEP = "SOEM reading the PDO sizes of slave 0"


def _agent(ifname: str, tmp_path) -> ChildProcess:
    cfg = tmp_path / "agent.toml"
    cfg.write_text(f'host = "sii"\nifname = "{ifname}"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n'
                   f"[startup]\nsoem_call_s = {SOEM_CALL_S}\n")
    return ChildProcess("bus-agent", [sys.executable, "-m", "bus_agent.cli", "--config", str(cfg),
                                      "--log-level", "DEBUG"], ready_marker="bus-agent ready")


def _in_step(agent: ChildProcess, text: str, timeout_s: float = 30.0) -> float:
    """Wait until the agent logs that it began the start-up step containing ``text``."""
    wait_for(lambda: any("start-up step" in line and text in line for line in agent.lines), timeout_s,
             f"start-up step {text!r}:\n{agent.output()}")
    return time.monotonic()


def _config_map_loops(control) -> None:
    assert control.request("bad_sii", slave=0, before="pdo")["ok"]
    assert control.request("mute_sdo", slave=0, index=0x1C00, subindex=0, skip=0, count=1)["ok"]


def _ended(agent: ChildProcess, timeout_s: float) -> float:
    t0 = time.monotonic()
    try:
        agent.popen.wait(timeout_s)
    except Exception:
        raise AssertionError(f"the agent still runs {timeout_s:g} s later:\n{agent.output()}") from None
    return time.monotonic() - t0


def _drive_never_enabled(control) -> None:
    slave = control.request("status")["slaves"][0]
    assert slave["drive_state"] != "operation_enabled", slave


def test_config_map_looping_on_a_malformed_sii_ends_at_its_deadline(ecat_segment, tmp_path):
    ifname, control = ecat_segment(1)
    _config_map_loops(control)
    agent = _agent(ifname, tmp_path)
    try:
        t0 = _in_step(agent, SOEM_STEP)
        _ended(agent, SOEM_CALL_S + GUARD_MARGIN_S + 10.0)
        assert agent.popen.returncode == -signal.SIGKILL, agent.output()
        assert time.monotonic() - t0 <= SOEM_CALL_S + GUARD_MARGIN_S + 1.0, agent.output()
        agent._reader.join(5)
        assert any(f"{SOEM_STEP} ('SimDrive402') (CoE, else its SII)" in line
                   and f"did not return within its deadline ({SOEM_CALL_S:g} s)" in line
                   and "ended by its start-up guard" in line for line in agent.lines), agent.output()
        _drive_never_enabled(control)
    finally:
        agent.kill()


def test_sigterm_while_config_map_loops_ends_the_agent_within_2_s(ecat_segment, tmp_path):
    ifname, control = ecat_segment(1)
    _config_map_loops(control)
    agent = _agent(ifname, tmp_path)
    try:
        _in_step(agent, SOEM_STEP)
        time.sleep(1.0)  # SOEM's 700 ms wait for the muted upload, then the loop
        agent.popen.send_signal(signal.SIGTERM)
        assert _ended(agent, 10.0) < 2.0, agent.output()
        agent._reader.join(5)
        assert "after a stop signal" in agent.output(), agent.output()
        _drive_never_enabled(control)
    finally:
        agent.kill()


def test_sigterm_while_config_init_loops_ends_the_agent_within_2_s(ecat_segment, tmp_path):
    ifname, control = ecat_segment(1)
    assert control.request("bad_sii", slave=0, before="general")["ok"]
    agent = _agent(ifname, tmp_path)
    try:
        _in_step(agent, "config_init")
        time.sleep(1.0)
        agent.popen.send_signal(signal.SIGTERM)
        assert _ended(agent, 10.0) < 2.0, agent.output()
        agent._reader.join(5)
        assert any("config_init" in line and "after a stop signal" in line for line in agent.lines), agent.output()
    finally:
        agent.kill()


def test_sigterm_between_sdo_transfers_abandons_start_up_in_order(ecat_segment, tmp_path):
    """A step Python runs through (uploads without answer, 700 ms each; SOEM does not read 0x6502
    itself): the agent ends start-up itself, closes the bus and exits 0, naming the step."""
    ifname, control = ecat_segment(1)
    assert control.request("mute_sdo", slave=0, index=0x6502, subindex=0, skip=0, count=3)["ok"]
    agent = _agent(ifname, tmp_path)
    try:
        _in_step(agent, "reading (and per policy writing) its PDO mapping by SDO")
        wait_for(lambda: any("0x6502:00" in line and "no answer" in line for line in agent.lines), 10,
                 "the first upload of 0x6502 without answer")  # the second is under way now
        time.sleep(0.2)
        agent.popen.send_signal(signal.SIGTERM)
        assert _ended(agent, 10.0) < 2.0, agent.output()
        agent._reader.join(5)
        assert agent.popen.returncode == 0, agent.output()
        assert any("stop signal during start-up step" in line and "PDO mapping by SDO" in line
                   and "no drive was enabled" in line for line in agent.lines), agent.output()
        assert control.request("status")["slaves"][0]["al_state"] in ("init", "preop"), agent.output()
    finally:
        agent.kill()
