"""`bus-agent` start-up errors: a clear message and a documented non-zero exit code."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
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
