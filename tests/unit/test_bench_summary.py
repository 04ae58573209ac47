"""The benchmark summary (bench/summary.py, bench/run_all.py): only this invocation's runs show
figures; failed and skipped runs show none; stale JSON is marked; targets decide honestly."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from bench import run_all
from bench import summary as s
from bench import summary_fleet as sf

FAKE = textwrap.dedent('''
    import json, sys
    args = sys.argv[1:]
    out = args[args.index("--out") + 1]
    mode = args[0]
    if mode == "ok":
        json.dump({"time": "now", "loadavg": [1.5, 1, 1], "value": 7}, open(out, "w"))
    elif mode == "fail":
        json.dump({"time": "now", "value": 666}, open(out, "w"))  # figures of a failed run
        sys.exit(3)
    # "silent": exit 0 without writing anything
''')


def figures(r):
    return {"value": r["value"]}


def headline(r):
    return f"value {r['value']}"


def targets(r):
    return [s.Target("value", r["value"], "<= 10", r["value"] <= 10)]


def bench(name: str, mode: str) -> run_all.Benchmark:
    return run_all.Benchmark(name, f"fake {mode}", "fake_bench", (mode,), (mode,), False, figures, headline, targets)


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "fake_bench.py").write_text(FAKE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "mods"))
    out = tmp_path / "results"
    out.mkdir()
    return out


def rows_of(summary: dict) -> dict[str, dict]:
    return {r["name"]: r for r in summary["rows"]}


def test_only_this_invocations_runs_show_figures(fake: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("good", "bad", "silent", "skipped"):  # figures left on disk by an earlier invocation
        (fake / f"bench_{name}.json").write_text(json.dumps({"time": "earlier", "value": 1}))
    root_bench = run_all.Benchmark("skipped", "needs root", "fake_bench", ("ok",), ("ok",), True, figures, headline,
                                   targets)
    monkeypatch.setattr(run_all, "BENCHMARKS", (bench("good", "ok"), bench("bad", "fail"), bench("silent", "silent"),
                                                root_bench))
    monkeypatch.setattr(run_all.os, "geteuid", lambda: 1000)
    summary = run_all.collect(quick=False, only=None, summarize_only=False, out=fake)
    rows = rows_of(summary)
    assert rows["good"]["status"] == "ok"
    assert rows["good"]["figures"] == {"value": 7} and rows["good"]["targets"][0]["target_met"] is True
    assert rows["good"]["loadavg"] == [1.5, 1, 1] and rows["good"]["run"]["finished"].endswith("Z")
    assert rows["bad"]["status"] == "failed (exit 3)"
    assert rows["silent"]["status"] == "failed: exit 0 but no JSON written by this run"
    assert rows["skipped"]["status"] == "skipped: needs root"
    for name in ("bad", "silent", "skipped"):
        assert "figures" not in rows[name] and "targets" not in rows[name], rows[name]
    assert summary["targets"] == {"met": 1, "not_met": 0, "undecided": 0}
    assert summary["time"].endswith("Z") and len(summary["loadavg_start"]) == 3 and len(summary["loadavg_end"]) == 3
    table = s.render_markdown(summary)
    assert "| bad: fake fail | failed (exit 3) |" in table and "666" not in table
    assert "| value 7 | value: 7 (target <= 10): met |" in table


def test_rows_not_run_are_stale_with_their_time_and_do_not_count(fake: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (fake / "bench_old.json").write_text(json.dumps({"time": "2026-11-22T02:22:00", "value": 99}))
    monkeypatch.setattr(run_all, "BENCHMARKS", (bench("old", "ok"), bench("never", "ok"), bench("new", "ok")))
    summary = run_all.collect(quick=False, only={"new"}, summarize_only=False, out=fake)
    rows = rows_of(summary)
    assert rows["old"]["status"] == "stale" and rows["old"]["time"] == "2026-11-22T02:22:00"
    assert rows["old"]["run"]["json_written"].endswith("Z")
    assert rows["old"]["targets"][0]["target_met"] is False  # shown, but not counted
    assert rows["never"]["status"] == "not run" and "figures" not in rows["never"]
    assert rows["new"]["status"] == "ok"
    assert summary["targets"] == {"met": 1, "not_met": 0, "undecided": 0}
    assert "| old: fake ok | stale |" in s.render_markdown(summary)


def test_main_exit_status_and_unknown_names(fake: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(run_all, "BENCHMARKS", (bench("good", "ok"), bench("bad", "fail")))
    monkeypatch.setattr(run_all, "RESULTS", fake)
    assert run_all.main(["--only", "good"]) == 0
    assert run_all.main(["--only", "bad"]) == 1
    assert rows_of(json.loads((fake / "summary.json").read_text()))["good"]["status"] == "stale"
    with pytest.raises(SystemExit):
        run_all.main(["--only", "nope"])


def _agent(bare: dict, gp: dict, bare_overruns: int, gp_overruns: int) -> dict:
    def phase(j: dict, o: int) -> dict:
        return {"jitter_us": j, "period_us": {"max": 1000 + j["max"]}, "overruns": o, "cycles": 1000,
                "wkc_errors": 0, "cpu_pct": 10.0}
    return {"phases": {"bare": phase(bare, bare_overruns), "gateway_process": phase(gp, gp_overruns)}, "ratios": {}}


def test_agent_jitter_targets_at_p999_and_max_with_absolute_figures() -> None:
    t = s.agent_targets(_agent({"p99": 0.0, "p999": 10.0, "max": 100.0}, {"p99": 3.0, "p999": 12.0, "max": 200.0}, 0, 0))
    assert [x.name.split(",")[0] for x in t] == ["jitter p99.9", "jitter max", "overruns with the gateway process under load"]
    assert t[0].measured == {"gateway_process": 12.0, "bare": 10.0, "ratio": 1.2} and t[0].met is True
    assert t[1].measured["ratio"] == 2.0 and t[1].met is False
    assert t[2].met is True


def test_agent_no_ratio_against_a_zero_baseline() -> None:
    t = s.agent_targets(_agent({"p99": 0.0, "p999": 0.0, "max": 5.0}, {"p99": 0.1, "p999": 0.4, "max": 5.0}, 0, 0))
    assert t[0].measured["ratio"] is None and t[0].met is None and "no ratio" in t[0].note


@pytest.mark.parametrize("bare_o, gp_o, met", [(0, 0, True), (0, 2, False), (5, 2, None), (5, 0, True)])
def test_agent_overrun_target_is_undecided_when_the_host_stalled(bare_o: int, gp_o: int, met: bool | None) -> None:
    j = {"p99": 1.0, "p999": 2.0, "max": 3.0}
    (*_, overruns) = s.agent_targets(_agent(j, j, bare_o, gp_o))
    assert overruns.met is met
    assert ("host stalls" in overruns.note) is (met is None)


def _sup(**fanin) -> dict:
    base = {"commands_ok": True, "drives_seen": 64, "state_changes_seen": 384, "missed_by_seq": 0,
            "supervisor_missed_by_seq": 0}
    ok_round = {"enable": {"ok": True}, "disable": {"ok": True}}
    return {"sizes": [{"agents": 4, "drives": 64, "cycle_us": 1000, "rounds": [ok_round], "fanin": {**base, **fanin}}]}


@pytest.mark.parametrize("change, met", [
    ({}, True),
    ({"commands_ok": False}, False),
    ({"state_changes_seen": 127}, False),   # fewer than 2 per drive
    ({"drives_seen": 63}, False),
    ({"missed_by_seq": 1}, False),
    ({"supervisor_missed_by_seq": 1}, False),
])
def test_fanin_target_needs_commands_ok_state_changes_and_nothing_missed(change: dict, met: bool) -> None:
    t = {x.name: x for x in sf.supervisor_targets(_sup(**change))}
    rounds, fanin = t["4x16: enable/disable rounds ok"], t["4x16: status fan-in"]
    assert rounds.met is True and rounds.measured == "1/1"
    assert fanin.met is met


@pytest.mark.parametrize("departure, met", [
    ({"killed_agents": 4, "reported": 4, "first_ms": 5.0, "last_ms": 40.0}, True),
    ({"killed_agents": 4, "reported": 3, "first_ms": 5.0, "last_ms": 40.0}, False),
    ({"killed_agents": 4, "reported": 4, "first_ms": 5.0, "last_ms": 3500.0}, False),
    ({"killed_agents": 4, "reported": 0, "first_ms": None, "last_ms": None}, False),
])
def test_departure_target_all_killed_agents_within_the_link_lease(departure: dict, met: bool) -> None:
    data = _sup()
    data["sizes"][0]["departure"] = departure
    gone = {x.name: x for x in sf.supervisor_targets(data)}["4x16: killed agents reported gone (ms)"]
    assert gone.met is met
    assert "killed agents reported gone" in sf.supervisor_headline(data)


def test_a_json_the_row_cannot_read_is_a_failure_without_figures() -> None:
    row = s.build_row("x", "fake", s.OK, {"time": "now"}, figures, targets, None, headline)
    assert row["status"] == "failed: JSON not readable (KeyError: 'value')"
    assert "figures" not in row and "targets" not in row


@pytest.mark.parametrize("overhead_s, bare_ms, met", [(0.004, 0.5, True), (0.006, 0.5, False), (None, 0.5, None)])
def test_supervisor_enable_overhead_target_is_ten_bare_gets(overhead_s: float | None, bare_ms: float,
                                                             met: bool | None) -> None:
    data = _sup()
    data["sizes"][0].update(enable_overhead_s_median=overhead_s, get_rtt_bare={"p50_ms": bare_ms, "p99_ms": 1.0})
    t = {x.name: x for x in sf.supervisor_targets(data)}["4x16: two-phase enable overhead / bare get (p50)"]
    assert t.met is met and t.limit == "<= 10 x"


def _enable(drives: int, ratio: float, failures: int = 0) -> dict:
    return {"drives": drives, "enable_latency": {"n_failures": failures, "latency": {"p50_ms": 9.0},
                                                  "ratios": {"beyond_cycles_p50_over_bare_get_p50": ratio}}}


@pytest.mark.parametrize("drives, ratio, met", [(16, 2.9, True), (16, 3.1, False), (64, 3.9, True), (64, 4.2, False)])
def test_enable_latency_targets_are_3x_for_16_and_4x_for_64_drives(drives: int, ratio: float, met: bool) -> None:
    beyond, failures = s.enable_targets(_enable(drives, ratio))
    assert beyond.met is met and failures.met is True
    assert s.enable_targets(_enable(drives, ratio, failures=1))[1].met is False
    assert f"enable of {drives} drives" in s.enable_headline(_enable(drives, ratio))


def test_enable_headline_gives_the_time_beyond_the_cycle_when_measured() -> None:
    r = _enable(16, 5.0)
    assert "time in the cycle" not in s.enable_headline(r)
    r["enable_latency"]["beyond_cycle_time"] = {"p50_ms": 2.5, "p99_ms": 4.0}
    assert "beyond the time in the cycle 2.5/4.0 ms" in s.enable_headline(r)


@pytest.mark.parametrize("p50, p99, met", [(1.9, 2.9, (True, True)), (2.1, 2.9, (False, True)),
                                           (1.5, 3.5, (True, False))])
def test_reflex_targets_p50_2ms_p99_3ms(p50: float, p99: float, met: tuple) -> None:
    data = {"fault_to_leave": {"n": 10, "p50_ms": p50, "p99_ms": p99}, "n_failures": 0,
            "fault_to_reflex": {"p50_ms": 1.0, "p99_ms": 2.0}, "bare_put": {"p50_ms": 0.5, "p99_ms": 1.0}}
    t50, t99, failures = sf.reflex_targets(data)
    assert (t50.met, t99.met) == met and failures.met is True
    assert "bare put" in sf.reflex_headline(data)
    assert sf.reflex_targets({"fault_to_leave": {"n": 0}, "n_failures": 3})[0].met is None


def _agent_dc(bare_p99: float, agent_p99: float, offset: dict | None) -> dict:
    def phase(p99: float, off: dict | None) -> dict:
        return {"jitter_us": {"p99": p99, "p999": 2 * p99, "max": 4 * p99}, "overruns": 0, "cycles": 1000,
                "wkc_errors": 0, "cpu_pct": 10.0, **({"dc_offset_us": off} if off else {})}
    return {"drives": 16, "profile": "omron1s:dc-required", "cycle_us": 1000,
            "phases": {"bare": phase(bare_p99, {"p1": 100.0, "p50": 200.0, "p99": 300.0}),
                       "agent": phase(agent_p99, offset)}, "ratios": {}}


@pytest.mark.parametrize("agent_p99, offset, met", [
    (12.0, {"p1": 400.0, "p50": 500.0, "p99": 700.0}, [True, True, True]),
    (13.0, {"p1": 200.0, "p50": 500.0, "p99": 700.0}, [False, False, False]),
    (12.0, None, [True, True, None]),
])
def test_agent_dc_targets_jitter_ratio_and_offset_window(agent_p99: float, offset: dict | None, met: list) -> None:
    data = _agent_dc(10.0, agent_p99, offset)
    t = s.agent_dc_targets(data)
    assert [x.met for x in t] == met
    assert t[0].name == "DC jitter p99.9, agent / bare (us)"
    assert t[0].measured == {"agent": 2 * agent_p99, "bare": 20.0, "ratio": round(agent_p99 / 10.0, 2)}
    assert t[2].limit == "within 250..750 us"
    assert "frame-to-SYNC0 p50/p99" in s.agent_dc_headline(data)
    assert s.agent_dc_figures(data)["phases"]["agent"]["dc_offset_us"] == offset


def test_twin_targets_read_the_ten_host_size_and_every_stop() -> None:
    run = {"sizes": {"3": {"twin": {"ready_s": 2.0, "cpu_pct_twin_process": 0.5, "left_after_stop": 0}, "bare": {}},
                     "10": {"twin": {"ready_s": 12.5, "cpu_pct_twin_process": 2.0, "left_after_stop": 1},
                            "bare": {"ready_s": 5.0}}}}
    ready, own, left = sf.twin_targets(run)
    assert (ready.measured, ready.met) == (12.5, False)
    assert (own.measured, own.met) == (2.0, True)
    assert (left.measured, left.met) == (1, False)
    assert [t.met for t in sf.twin_targets({"sizes": {"3": {"twin": {}, "bare": {}}}})] == [None, None, None]
    assert "10 hosts: ready 12.5 s (bare processes 5.0 s)" in sf.twin_headline(run)


def test_motion_row_targets_and_headline():
    ph = {k: {"jitter_us": {"p50": 0.1, "p99": 1.0, "p999": j, "max": 2 * j}, "overruns": 0, "cycles": 1000,
              "cpu_pct": 50.0, "cpu_us_per_cycle": 500.0} for k, j in (("bare", 10.0), ("idle", 11.0), ("motion", 12.0))}
    ph["motion"]["moves_not_done"] = 0
    r = {"phases": ph, "step_cost": {"axes": 16, "added_us_per_axis": 1.2}, "query_to_applied": {"p50_ms": 0.9},
         "query_to_first_target": {"ms_p50": 5.0}, "sync_arrival": {"spread_cycles_max": 2}}
    met = {t.name: t.met for t in s.motion_targets(r)}
    assert met["jitter p99.9, motion / bare (us)"] is True and met["jitter max, motion / bare (us)"] is True
    assert met["synchronized move of every axis: arrival spread (cycles)"] is False
    assert met["move query to the cycle applying it, p50"] is True and met["moves not done in the motion phase"] is True
    assert "1.2 us per moving axis" in s.motion_headline(r) and s.motion_figures(r)["phases"]["motion"]["moves_not_done"] == 0


def test_cycle_row_targets_include_the_tick_at_rest_and_tolerate_a_run_without_it():
    ph = {k: {"jitter_us": {"p50": 0.1, "p99": 1.0, "p999": j, "max": 2 * j}, "overruns": 0, "cycle_cpu_pct": c,
              "cpu_pct_of_period": c, "cpu_us_per_cycle": 10 * c} for k, j, c in (("bare", 10.0, 20.0), ("agent", 11.0, 23.0))}
    ticks = {"us": {"bare_exchange": 10.0, "bus_exchange": 18.0, "tick_rest": 45.0, "tick_full": 340.0,
                    "tick_one_moving": 75.0}, "rest_beyond_bare_us_per_drive": 0.55, "moving_drive_us": 26.0}
    size = {"phases": ph, "beyond_bare_us_per_drive": 0.47, "jitter_p999_over_bare": 1.1, "ticks": ticks}
    r = {"sizes": {"64": size}, "codec": {"ratio_default": 1.02}}
    met = {t.name: t.met for t in s.cycle_targets(r)}
    assert met["64 drives at rest: one tick's CPU beyond the bare exchange, per drive"] is True
    assert met["64 drives: cycle thread CPU per cycle, % of the 1 ms period"] is True
    assert "45.0 us at rest (every drive stepped: 340.0 us" in s.cycle_headline(r)
    size["ticks"]["rest_beyond_bare_us_per_drive"] = 1.5
    assert {t.name: t.met for t in s.cycle_targets(r)}["64 drives at rest: one tick's CPU beyond the bare exchange, per drive"] is False
    del size["ticks"]  # an older result: no tick figures, no tick target
    assert not any("tick" in t.name for t in s.cycle_targets(r)) and "one tick" not in s.cycle_headline(r)


def test_chaos_targets_are_zero_violations_and_zero_harness_errors() -> None:
    run = {"seed": 1, "seconds": 60.0, "backend": "sim",
           "counts": {"commands": 200, "malformed": 15, "faults_injected": 30, "injections": {"fault": 10, "cut": 2}},
           "monitors": {"one_terminal_reply": {"checked": 180, "skipped": 20, "violations": 0},
                        "lost_state_unknown": {"checked": 40, "skipped": 0, "violations": 3}},
           "violations_total": 3, "harness_errors": []}
    violations, harness = sf.chaos_targets(run)
    assert (violations.measured, violations.met, violations.note) == (3, False, "lost_state_unknown 3")
    assert (harness.measured, harness.met) == (0, True)
    assert "violations: lost_state_unknown 3" in sf.chaos_headline(run)
    assert sf.chaos_figures(run)["monitors"]["one_terminal_reply"] == {"checked": 180, "skipped": 20, "violations": 0}
    clean = {**run, "monitors": {"one_terminal_reply": run["monitors"]["one_terminal_reply"]}, "violations_total": 0}
    assert sf.chaos_targets(clean)[0].met is True and "violations: none" in sf.chaos_headline(clean)


def test_opcua_targets_read_the_worst_round_the_rest_cpu_and_misses() -> None:
    run = {"drives": 1024, "fault_to_client_ms": {"n": 20, "p50": 17.0, "max": 510.0},
           "fault_to_subscriber_ms": {"p50": 3.0, "max": 14.0}, "server_cpu_idle_pct": 20.0,
           "server_cpu_us_per_status": 260.0, "missed": 0, "client_over_subscriber_p50": 5.7,
           "publishing_interval_ms": 20}
    change, cpu, per_status, missed = sf.opcua_targets(run)
    assert (change.measured, change.met) == (510.0, False)  # over the 500 ms
    assert cpu.met is True and per_status.met is False and missed.met is True
    assert [t.met for t in sf.opcua_targets({})] == [None, None, None, None]
    assert "fault to OPC UA client p50/max 17.0/510.0 ms" in sf.opcua_headline(run)
    assert sf.opcua_figures(run)["client_over_subscriber_p50"] == 5.7


def test_the_recorder_benchmark_feeds_the_recorder_what_it_reads_of_a_drive():
    """bench_recorder's stand-in drives follow recorder.RecordedDrive (they lacked ``out`` once and
    the benchmark crashed while the suite stayed green)."""
    from bench.bench_recorder import record_call_ns

    assert record_call_ns(4, calls=50, repeats=1) > 0
