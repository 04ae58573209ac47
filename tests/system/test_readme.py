"""The README's demo commands, its supervisor script and ``deploy/agent.example.toml`` run as
written, against a real ``bus-agent --sim 4`` (only the endpoint is changed to a free port)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Iterator

import pytest

from bus_agent.sim.child import ChildProcess, free_port
from supervisor.fleet import Fleet
from supervisor.testbed import _env

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()


def _block(after: str, lang: str) -> str:
    """The first ```lang code block after the line containing ``after``."""
    tail = README[README.index(after):]
    m = re.search(rf"```{lang}\n(.*?)```", tail, re.S)
    assert m, f"no ```{lang} block after {after!r} in README.md"
    return m.group(1)


@pytest.fixture(scope="module")
def demo() -> Iterator[str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    agent = ChildProcess("demo", [sys.executable, "-m", "bus_agent.cli", "--sim", "4", "--listen", ep,
                                  "--log-level", "WARNING"], ready_marker="bus-agent ready")
    try:
        agent.expect_ready(60)
        yield ep
    finally:
        agent.stop()


def test_demo_commands_run_as_written(demo: str) -> None:
    lines = [ln.split("  #")[0].strip() for ln in _block("With the demo running", "sh").splitlines()]
    commands = [shlex.split(ln) for ln in lines if ln.startswith(".venv/bin/drivectl")]
    assert len(commands) >= 5
    outputs = []
    with Fleet(connect=[demo]) as fleet:
        assert fleet.wait_for_agents(1, 20, drives=4)
        for argv in commands:
            extra = ["--duration", "2"] if argv[1] == "watch" else []
            for _attempt in range(3):
                # A loaded host can stall the demo's cycle past the simulated slaves' SM watchdog
                # (100 ms): they drop out and the agent brings them back. Wait for that, and
                # repeat a command refused only because of it; anything else fails the test.
                assert fleet.wait_until(lambda f: all(not st.lost and st.al_state == "op"
                                                      for st in f.drives().values()), 60)
                r = subprocess.run([sys.executable, "-m", "supervisor.cli", *argv[1:], *extra, "--connect", demo],
                                   capture_output=True, text=True, timeout=60, env=_env())
                if r.returncode == 0 or "lost" not in r.stdout:
                    break
            assert r.returncode == 0, (argv, r.stdout, r.stderr)
            outputs.append((argv, r.stdout))
    # the status right after the injected fault shows its meaning
    after_fault = [out for argv, out in outputs if argv[1:] == ["status", "*/axis1"]]
    assert after_fault and "continuous over-current" in after_fault[0]


def test_supervisor_script_reports_a_refused_enable(demo: str) -> None:
    script = _block("A supervisor script", "python").replace("tcp/127.0.0.1:7447", demo)
    inject = ("from supervisor.fleet import Fleet\nfrom supervisor.simctl import inject\n"
              f"with Fleet(connect=[{demo!r}]) as f:\n"
              "    f.wait_for_agents(1, 10, drives=4)\n"
              "    inject(f, 'fault', '*/axis2', error_code=0x3210)\n"
              "    assert f.wait_until(lambda f: any(st.state == 'fault' for st in f.drives().values()), 10)\n")
    r = subprocess.run([sys.executable, "-c", inject + script], capture_output=True, text=True, timeout=120,
                       env=_env(), cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(r"axis2 rejected .*fault", r.stdout), r.stdout  # printed from report.failures
    assert "nothing sent" in r.stdout
    reset = subprocess.run([sys.executable, "-m", "supervisor.cli", "--connect", demo, "fault-reset", "*/axis2"],
                           capture_output=True, text=True, timeout=60, env=_env())
    assert reset.returncode == 0, reset.stdout + reset.stderr


def test_agent_example_toml_runs_with_sim_as_it_says(tmp_path: Path) -> None:
    text = (ROOT / "deploy" / "agent.example.toml").read_text()
    assert "bus-agent --config deploy/agent.example.toml --sim 2" in text
    cfg = tmp_path / "agent.toml"
    cfg.write_text(text)  # unedited, as the file says
    agent = ChildProcess("example", [sys.executable, "-m", "bus_agent.cli", "--config", str(cfg), "--sim", "2",
                                     "--listen", f"tcp/127.0.0.1:{free_port()}"], ready_marker="bus-agent ready")
    try:
        agent.expect_ready(60)
        assert "host=h1 drives=x,y backend=sim" in agent.output()
    finally:
        assert agent.stop() == 0
