"""`bus-agent` start-up errors: a clear message and a documented non-zero exit code."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(60)


def run(*args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "bus_agent.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=ROOT, env=env)


def test_no_backend_is_a_usage_error():
    r = run()
    assert r.returncode == 2 and "--sim N" in r.stderr


def test_bad_config_file_names_the_key(tmp_path):
    cfg = tmp_path / "a.toml"
    cfg.write_text('host = "h1"\nsim_drives = 2\ncycle_us = 5\n')
    r = run("--config", str(cfg))
    assert r.returncode == 2 and "cycle_us" in r.stderr
    r = run("--config", str(tmp_path / "missing.toml"))
    assert r.returncode == 2 and "cannot read" in r.stderr


def test_identity_mismatch_stops_start_up(tmp_path):
    cfg = tmp_path / "id.toml"
    cfg.write_text(textwrap.dedent("""
        host = "idm"
        sim_drives = 2
        [[drives]]
        slave = 0
        identity = { vendor_id = 0x12345678, product_code = 1 }
    """))
    r = run("--config", str(cfg), "--listen", "tcp/127.0.0.1:0")
    assert r.returncode == 3, r.stderr
    assert "identity" in r.stderr and "0x12345678" in r.stderr and "bus-agent ready" not in r.stdout


def test_bad_endpoint_is_a_start_up_error():
    r = run("--sim", "1", "--host", "badep", "--listen", "127.0.0.1:7447")
    assert r.returncode == 3 and "locator" in r.stderr


def test_a_burst_of_sigterm_still_ends_in_an_ordered_stop():
    """Two stop signals close together (a forwarded SIGTERM and a process-group kill, as
    `timeout make demo` sends) must not hang the agent: a handler that takes a lock (Event.set)
    deadlocked when the second signal arrived while the first one's handler held it."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "bus_agent.cli", "--sim", "2", "--host", "burst",
                          "--listen", "tcp/127.0.0.1:0"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    try:
        assert p.stdout is not None
        lines = []
        for line in p.stdout:
            lines.append(line)
            if line.startswith("bus-agent ready"):
                break
        assert any(ln.startswith("bus-agent ready") for ln in lines), "".join(lines)
        end = time.monotonic() + 0.15  # signals for 150 ms: some land inside a handler
        while time.monotonic() < end:
            os.kill(p.pid, signal.SIGTERM)
        out, _ = p.communicate(timeout=20)
        assert p.returncode == 0, out
        assert "bus-agent stopped host=burst" in out and "signal SIGTERM: shutting down" in out
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
