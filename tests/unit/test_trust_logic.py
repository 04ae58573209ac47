"""Pure parts of issue 9: the error code table, "did you mean", the host name conflict tracker,
enable blockers as results."""

from __future__ import annotations

import pytest

from bus_agent.gateway.hostclaim import ConflictTracker
from schemas.error_codes import ERROR_CLASSES, ERROR_CODES, describe
from schemas.messages import DriveStatus
from supervisor.orchestration import enable_blockers
from supervisor.selectors import DriveRef, unknown_selector_problems


@pytest.mark.parametrize("code, text", [
    (0x2310, "continuous over-current"), (0x3210, "DC link over-voltage"), (0x4310, "excess drive temperature"),
    (0x7500, "communication"), (0x8611, "following error"), (0x8130, "life guard error or heartbeat error"),
    (0x2399, "current, device output side (0x2399)"), (0x4999, "temperature (0x4999)"),
    (0xFF01, "manufacturer-specific error (0xFF01)"), (0, ""),
])
def test_describe(code: int, text: str) -> None:
    assert describe(code) == text


def test_every_code_has_a_text_within_the_status_field() -> None:
    assert all(describe(c) and len(describe(c)) <= 200 for c in range(1, 0x10000))
    assert all(0 <= c <= 0xFFFF for c in ERROR_CODES) and set(ERROR_CLASSES) == set(range(16))


U = [DriveRef("h1", "axis0"), DriveRef("h1", "axis1"), DriveRef("h2", "axis1")]


@pytest.mark.parametrize("sel, needle", [
    ("axis1", "'*/axis1'"), ("h1/axis9", "'h1/axis1'"), ("h3/axis0", "no host 'h3'"), ("hh1/axis0", "'h1/axis0'"),
    ("h*/axis7", "matches no known drive"), ("@gantri", "@gantry"),
])
def test_unknown_selectors_get_hints(sel: str, needle: str) -> None:
    problems = unknown_selector_problems([sel], U, {"gantry": ["h1/axis0"]})
    assert len(problems) == 1 and needle in problems[0], problems


@pytest.mark.parametrize("sel", ["**", "h1", "h1/*", "*/axis1", "h?/axis[01]", "h1/axis0", "@gantry"])
def test_known_selectors_pass(sel: str) -> None:
    assert unknown_selector_problems([sel], U, {"gantry": ["h1/axis0"]}) == []


def test_conflict_tracker_begins_holds_and_ends() -> None:
    t = ConflictTracker("h1", "me", hold_s=3.0)
    assert not t.seen("me", 0.0) and t.text == ""      # our own status is no conflict
    assert t.seen("other", 1.0) and "other" in t.text and "h1" in t.text
    assert not t.seen("other", 2.0)                     # still the same conflict
    assert not t.expire(4.0) and t.text                 # 2 s silent: held
    assert t.expire(5.1) and t.text == ""               # 3.1 s silent: over


def _st(axis: str, state: str, code: int = 0, lost: bool = False) -> DriveStatus:
    return DriveStatus(host="h1", axis=axis, seq=1, time_ns=0, cycle=0, state=state, statusword=0, controlword=0,
                       goal="disabled", halt=False, mode=8, mode_display=8, position=0, velocity=0, torque=0,
                       error_code=code, lost=lost)


def test_enable_blockers_are_results() -> None:
    refs = [DriveRef("h1", "a"), DriveRef("h1", "b"), DriveRef("h1", "c"), DriveRef("h9", "x")]
    st = {refs[0]: _st("a", "fault", 0x2310), refs[1]: _st("b", "switch_on_disabled", lost=True),
          refs[2]: _st("c", "switch_on_disabled")}
    out = enable_blockers(refs, refs[:3], st)
    assert [(r.axis, r.outcome, r.error_code) for r in out] == [("a", "rejected", 0x2310), ("b", "rejected", 0),
                                                              ("x", "missing", 0)]
    out = enable_blockers(refs[2:3], refs[:3], st, {"h1": "two agents"})
    assert [(r.axis, r.outcome) for r in out] == [("c", "rejected")] and "two agents" in out[0].error
