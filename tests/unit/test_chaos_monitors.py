"""The chaos soak's pure parts: the seeded schedule and the monitors (bench/chaos)."""

from __future__ import annotations

import dataclasses
from array import array

import pytest

from bus_agent.gateway.requests import RequestError, parse_command

from bench.chaos.limits import check_limits
from bench.chaos.monitors import MONITORS, group_reflex, no_unrequested_enable, one_reply
from bench.chaos.schedule import FLAWS, INJECTION_WEIGHTS, make_schedule, schedule_json
from bench.chaos.selftest import CASES, _cmd, _ev, _st, _t, _trace, self_test
from bench.chaos.trace import Injection, Recording
from bench.chaos.wire import malformed, pack, request, unpack


def test_every_monitor_fails_on_its_broken_trace_and_passes_on_its_kept_one():
    out = self_test()
    assert set(out["monitors"]) == set(MONITORS) == set(CASES)
    for name, m in out["monitors"].items():
        assert m["fails_when_broken"], name
        assert m["passes_when_kept"], (name, m["kept_reports"])
    assert out["ok"]


def test_the_same_seed_gives_the_same_schedule_and_another_seed_another():
    a, b, c = make_schedule(5, 30), make_schedule(5, 30), make_schedule(6, 30)
    assert schedule_json(5, 30, a) == schedule_json(5, 30, b)
    assert a != c
    kinds = [s.kind for s in a if s.lane == "inject"]
    assert set(kinds[:len(INJECTION_WEIGHTS)]) == set(INJECTION_WEIGHTS)  # every kind early
    assert all(s.at_s < 30 for s in a) and [s.at_s for s in a] == sorted(s.at_s for s in a)


def test_every_flaw_builds_a_payload_the_agent_must_refuse_and_the_well_formed_one_passes():
    # the agent's own pure parser: the soak's payloads are written by hand, this checks they are
    # malformed for the reason named (and that the same request without the flaw is accepted)
    for flaw in FLAWS:
        op, payload = malformed(flaw, "rid-1")
        key = f"drives/@v1/h1/drive/a/cmd/{op}"
        if flaw == "move_to_and_by":  # well-typed: the motion layer rejects it per drive ("exactly one of")
            assert {"to", "by"} <= set(parse_command(payload, key, "h1", ["a"]).args)
            continue
        with pytest.raises(RequestError):
            parse_command(payload, key, "h1", ["a"])
    parsed = parse_command(pack(request("rid-1", "enable")), "drives/@v1/h1/drive/*/cmd/enable", "h1", ["a", "b"])
    assert parsed.axes == ("a", "b") and unpack(pack(request("x", "enable")))["type"] == "command_request"


def test_a_reply_lost_while_the_host_was_cut_off_is_not_judged():
    tr = _trace()
    tr.commands = [_cmd("r1", "enable", ("h2/a",), 0, 9000, [])]
    assert one_reply(tr).violations
    tr.injections = [Injection("cut", "h2", _t(100), _t(100), _t(4000))]
    r = one_reply(tr)
    assert not r.violations and r.skipped == 1


def test_an_enable_pending_when_the_drive_went_down_covers_the_rise_only_if_it_was_done():
    tr = _trace()
    tr.statuses = [_st(0, "h1/a", 1, "switch_on_disabled"), _st(50, "h1/a", 2, "quick_stop_active"),
                   _st(60, "h1/a", 3, "operation_enabled")]
    tr.commands = [_cmd("e1", "enable", ("h1/a",), 45, 70, [("h1/a", "done")])]
    assert not no_unrequested_enable(tr).violations
    tr.commands = [_cmd("e1", "enable", ("h1/a",), 45, 70, [("h1/a", "rejected")])]
    assert no_unrequested_enable(tr).violations


def test_a_local_reflex_in_a_later_cycle_is_a_violation():
    tr = _trace()
    tr.statuses = [_st(0, r, 1, "operation_enabled", goal="enabled") for r in ("h1/a", "h1/b", "h2/a")]
    tr.events = [_ev(100, "h1/a", "lost", cycle=100), _ev(101, "h1/b", "reflex", cycle=101),
                 _ev(103, "h2/a", "reflex", cycle=7)]
    (v,) = group_reflex(tr).violations
    assert v.detail["member"] == "h1/b" and v.what == "no reflex in the same cycle"


def test_limits_judge_only_cycles_the_drive_follows_and_each_cycle_once():
    tr = _trace()
    n = 6
    tp = [0, 0, 0, 5000, 5000, 5000]  # a jump while the drive is disabled: not on the wire for it
    chans = {"time_ns": array("q", range(n)), "statusword": array("q", [0x0250] * n),
             "controlword": array("q", [0x0006] * n), "mode_display": array("q", [8] * n),
             "target_position": array("q", tp), "target_velocity": array("q", [0] * n)}
    tr.recordings = [Recording(0, "h2", 1000, n, ("a",), chans)]
    r = check_limits(tr)
    assert r.checked == 0 and not r.violations
    chans["statusword"] = array("q", [0x0237] * n)
    chans["controlword"] = array("q", [0x000F] * n)
    tr.recordings = [Recording(0, "h2", 1000, n, ("a",), chans)] * 2
    r = check_limits(tr)
    assert r.violations and r.violations[0].detail["count"] == 1  # the same cycles fetched twice: judged once


def test_a_fault_of_a_drive_simulated_in_its_agent_ends_when_that_agent_is_killed():
    from bench.chaos.monitors import no_stale_found
    tr = _trace()
    tr.injections = [Injection("fault", "h1/a", _t(0), _t(0), _t(0)),
                     Injection("agent_restart", "h1", _t(100), _t(100), _t(900))]
    tr.statuses = [_st(1000, "h1/a", 3, "operation_enabled", goal="enabled")]
    assert not no_stale_found(tr).violations  # the new agent's drive never had the fault
    tr.sim_in_agent = False  # ecat-sim outlives the agent: its drive is still in fault
    assert no_stale_found(tr).violations


def test_a_remote_reflex_late_by_its_hosts_own_stall_is_not_a_violation():
    from bench.chaos.trace import AgentInfo
    tr = _trace()
    tr.statuses = [_st(0, r, 1, "operation_enabled", goal="enabled") for r in ("h1/a", "h1/b", "h2/a")]
    tr.events = [_ev(100, "h1/a", "fault", cycle=100), _ev(100, "h1/b", "reflex", cycle=100),
                 _ev(220, "h2/a", "reflex", cycle=900)]
    (v,) = group_reflex(tr).violations
    assert v.detail["member"] == "h2/a" and v.detail["next_reflex_after_ms"] == 120.0
    tr.agents = [AgentInfo(_t(1100), "h2", 7, "i1", "running", period_max_us=100_000.0)]  # h2's cycle stalled 100 ms
    r = group_reflex(tr)
    assert not r.violations and r.figures["late_by_stall"] == 1


def test_a_fault_ends_with_a_power_cycle_and_a_saved_trace_is_judged_alike():
    import json

    from bench.chaos.__main__ import trace_json
    from bench.chaos.monitors import no_stale_found, run_monitors
    from bench.chaos.trace import trace_from_json
    tr = _trace()
    tr.sim_in_agent = False
    tr.injections = [Injection("fault", "h1/a", _t(0), _t(0), _t(0))]
    tr.statuses = [_st(1000, "h1/a", 3, "operation_enabled", goal="enabled")]
    assert no_stale_found(tr).violations
    tr.injections.append(Injection("unplug", "h1/a", _t(200), _t(200), _t(600)))  # plugged back: power-cycled
    assert not no_stale_found(tr).violations
    tr.commands = [_cmd("e1", "enable", ("h1/a",), 10, 60, [("h1/a", "rejected")])]
    again = trace_from_json(json.loads(json.dumps(trace_json(tr))))
    assert again.limits == {}  # no recordings in a saved trace: nothing for the limits
    again.limits = tr.limits
    assert again == tr
    assert {n: len(r.violations) for n, r in run_monitors(again).items()} == \
        {n: len(r.violations) for n, r in run_monitors(tr).items()}


def test_a_remote_reflex_counts_from_the_origins_bad_status_on_the_wire():
    tr = _trace()
    tr.statuses = [_st(0, r, 1, "operation_enabled", goal="enabled") for r in ("h1/a", "h1/b", "h2/a")]
    tr.events = [_ev(100, "h1/a", "fault", cycle=100), _ev(100, "h1/b", "reflex", cycle=100),
                 _ev(420, "h2/a", "reflex", cycle=900)]
    assert group_reflex(tr).violations
    late = _st(100, "h1/a", 2, "fault")
    tr.statuses.append(dataclasses.replace(late, t_ns=_t(400)))  # h1's gateway published it 300 ms late
    r = group_reflex(tr)
    assert not r.violations and r.figures["origin_on_wire_ms"]["max"] == 300.0
