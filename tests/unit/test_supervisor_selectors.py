"""Selectors, query planning and result aggregation: pure, no Zenoh."""

from __future__ import annotations

import pytest

from schemas.messages import CommandReply
from supervisor.results import MISSING, CommandResult, DriveResult, aggregate, final_results, single
from supervisor.selectors import DriveRef, SelectorError, parse_selector, plan_queries, resolve

R = DriveRef
ROSTER = [R(h, a) for h in ("h1", "h2", "h10") for a in ("axis1", "axis2", "x")]


def sel(*s: str, groups=None) -> list[str]:
    return [str(r) for r in resolve(s, ROSTER, groups)]


@pytest.mark.parametrize(
    "selector, expected",
    [
        ("h1/x", ["h1/x"]),
        ("h1/*", ["h1/axis1", "h1/axis2", "h1/x"]),
        ("h1", ["h1/axis1", "h1/axis2", "h1/x"]),
        ("*/x", ["h1/x", "h10/x", "h2/x"]),
        ("h?/axis?", ["h1/axis1", "h1/axis2", "h2/axis1", "h2/axis2"]),
        ("h*/axis2", ["h1/axis2", "h10/axis2", "h2/axis2"]),
        ("h1*/x", ["h1/x", "h10/x"]),
        ("h[12]/x", ["h1/x", "h2/x"]),
        ("h1/**", ["h1/axis1", "h1/axis2", "h1/x"]),
        ("**/x", ["h1/x", "h10/x", "h2/x"]),
    ],
)
def test_selector_matches(selector: str, expected: list[str]) -> None:
    assert sel(selector) == sorted(expected)


def test_all_selects_everything_and_union_dedupes() -> None:
    assert sel("**") == sorted(map(str, ROSTER))
    assert sel("h1/x", "*/x", "h1/x") == ["h1/x", "h10/x", "h2/x"]


def test_groups_and_unknown_group() -> None:
    groups = {"gantry": ["h1/x", "h2/x"], "ghost": ["h9/y"]}
    assert sel("@gantry", groups=groups) == ["h1/x", "h2/x"]
    # a member that is not in the roster is still selected: it will be reported missing
    assert sel("@ghost", groups=groups) == ["h9/y"]
    with pytest.raises(SelectorError, match="unknown group 'nope'.*gantry"):
        sel("@nope", groups=groups)


def test_concrete_name_outside_roster_is_kept() -> None:
    assert sel("h9/x") == ["h9/x"]


@pytest.mark.parametrize(
    "bad",
    ["", "   ", "a/b/c", "h1/", "/x", "h 1/x", "h1/x#", "h1/@v1", "@", "@bad/name", "h1/$x", "-h/x", "h1/x/"],
)
def test_bad_selectors_are_refused(bad: str) -> None:
    with pytest.raises(SelectorError):
        resolve([bad], ROSTER)


def test_wildcard_matching_nothing_is_an_error_unless_allowed() -> None:
    with pytest.raises(SelectorError, match="matches no known drive"):
        resolve(["h7*/x"], ROSTER)
    assert resolve(["h7*/x"], ROSTER, allow_empty=True) == []
    with pytest.raises(SelectorError, match="no selector"):
        resolve([], ROSTER)


def test_plan_one_query_for_expressible_selectors() -> None:
    drives = resolve(["**"], ROSTER)
    assert plan_queries([parse_selector("**")], drives).keyexprs("enable") == ["drives/@v1/*/drive/*/cmd/enable"]
    p = plan_queries(["h*/axis2"], resolve(["h*/axis2"], ROSTER))
    assert p.keyexprs("shutdown") == ["drives/@v1/h$*/drive/axis2/cmd/shutdown"]
    # '**' absorbs everything else
    p = plan_queries(["h1/x", "**"], resolve(["h1/x", "**"], ROSTER))
    assert p.pairs == (("*", "*"),)


def test_plan_question_mark_and_groups_address_exactly_the_selection() -> None:
    host_axes = {"h1": ["axis1", "axis2", "x"], "h2": ["axis1", "axis2", "x"]}
    drives = resolve(["h?/axis?"], ROSTER)
    p = plan_queries(["h?/axis?"], drives, host_axes)
    # never a wildcard over a host where unselected axes live
    assert sorted(p.pairs) == [("h1", "axis1"), ("h1", "axis2"), ("h2", "axis1"), ("h2", "axis2")]
    groups = {"g": ["h1/axis1", "h1/axis2", "h1/x", "h2/x"]}
    drives = resolve(["@g"], ROSTER, groups)
    p = plan_queries(["@g"], drives, host_axes)
    assert sorted(p.pairs) == [("h1", "*"), ("h2", "x")]
    # without the agent's own axis list, no host-wide wildcard is guessed
    p = plan_queries(["@g"], drives, {})
    assert ("h1", "*") not in p.pairs and len(p.pairs) == 4


def _reply(host: str, axis: str, outcome: str = "done", state: str = "switched_on", **kw) -> CommandReply:
    return CommandReply(request_id="r1", host=host, op="switch_on", outcome=outcome, axis=axis, state=state, **kw)


def test_aggregate_reports_missing_with_reason() -> None:
    addressed = [R("h1", "x"), R("h2", "x"), R("h3", "x"), R("h4", "x")]
    replies = {R("h1", "x"): _reply("h1", "x"),
               R("h2", "x"): _reply("h2", "x", "failed", "fault", error_code=0x7500, reason="drive faulted")}
    res = aggregate("switch_on", "r1", addressed, replies, gone_hosts=["h3"], timeout_s=2.0, elapsed_s=2.1)
    by = {r.name: r for r in res.results}
    assert by["h1/x"].ok and by["h1/x"].state == "switched_on"
    assert by["h2/x"].outcome == "failed" and by["h2/x"].error_code == 0x7500
    assert by["h3/x"].outcome == MISSING and "gone" in by["h3/x"].error
    assert by["h4/x"].outcome == MISSING and "no reply within 2 s" in by["h4/x"].error
    assert not res.ok
    assert res.counts() == {"done": 1, "failed": 1, MISSING: 2}
    assert [r.name for r in res.failures] == ["h2/x", "h3/x", "h4/x"]


def test_aggregate_keeps_unexpected_replies_and_agent_errors() -> None:
    res = aggregate("enable", "r1", [R("h1", "x")], {R("h5", "y"): _reply("h5", "y")},
                    errors=["args: bad"], timeout_s=1.0)
    assert res.results[0].outcome == MISSING and "args: bad" in res.results[0].error
    assert [r.name for r in res.unexpected] == ["h5/y"]
    assert res.to_dict()["unexpected"][0]["host"] == "h5"


def test_all_done_is_ok_and_final_results_take_the_last_step() -> None:
    a = CommandResult("switch_on", "r1", (DriveResult("h1", "x", "done"), DriveResult("h2", "x", "failed")))
    b = CommandResult("disable", "r2", (DriveResult("h1", "x", "done", "switch_on_disabled"),))
    assert not a.ok and b.ok
    final = {r.name: r for r in final_results([("switch_on", a), ("rollback", b)])}
    assert final["h1/x"].state == "switch_on_disabled" and final["h2/x"].outcome == "failed"
    rep = single("disable", b)
    assert rep.ok and rep.to_dict()["final"][0]["axis"] == "x"
    assert CommandResult("enable", "r3", ()).ok  # nothing addressed: nothing failed
