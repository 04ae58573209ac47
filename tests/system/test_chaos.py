"""The chaos soak in the suite: a short fixed-seed run of ``python -m bench.chaos`` over a real
twin (router and three agents in their own processes, links cut, agents and the router killed and
restarted, simulator faults, malformed commands), which must find no violation, and its
``--self-test``, which must show every monitor able to fail. The longer runs are in run_all."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from bench.common import ROOT

pytestmark = [pytest.mark.timeout(300)]

SEED = 7
SECONDS = 40


def test_self_test_shows_every_monitor_able_to_fail():
    p = subprocess.run([sys.executable, "-m", "bench.chaos", "--self-test"], cwd=ROOT, capture_output=True,
                       text=True, timeout=60)
    out = json.loads(p.stdout)
    assert p.returncode == 0 and out["ok"], out
    assert all(m["fails_when_broken"] and m["passes_when_kept"] for m in out["monitors"].values())


def test_short_fixed_seed_soak_finds_no_violation(tmp_path):
    out = tmp_path / "chaos.json"
    p = subprocess.run([sys.executable, "-m", "bench.chaos", "--seconds", str(SECONDS), "--seed", str(SEED),
                        "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=280)
    r = json.loads(out.read_text())
    assert r["harness_errors"] == [], r["harness_errors"]
    c = r["counts"]
    # the schedule happened: commands, malformed ones, and every kind of injection
    assert c["commands"] >= 80 and c["malformed"] >= 3, c
    assert set(c["injections"]) == {"fault", "unplug", "wkc_fault", "cut", "agent_restart", "router_restart"}, c
    assert r["monitors"]["one_terminal_reply"]["checked"] >= 50, r["monitors"]
    assert r["monitors"]["wire_limits"]["checked"] > 0 and r["monitors"]["status_seq_rising"]["checked"] > 0
    found = [(v["monitor"], v["what"], v["detail"].get("drive") or v["detail"].get("member"), v["detail"].get("count"))
             for v in r["violations"]]
    assert r["violations_total"] == 0, f"{r['violations_total']} violations (replay: {r['replay']}): {found}"
    assert p.returncode == 0, p.stderr[-3000:]
