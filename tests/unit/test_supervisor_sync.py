"""A synchronized move has one path (supervisor.motion.sync_move): ``Fleet.send``, which sends a
selection's queries as planned, refuses a ``sync`` move that does not name its axes per host
(planned per drive it would start as several groups). No session: refused before any I/O. A commit
that fails on one host stops the hosts already moving (over a stand-in of the Fleet: pure logic)."""

from __future__ import annotations

import pytest

from supervisor.fleet import Fleet
from supervisor.selectors import DriveRef


def test_send_refuses_a_sync_move_that_names_no_axes():
    f = Fleet(connect=["tcp/127.0.0.1:1"])  # never opened: the refusal comes first
    sel = f.selection_of([DriveRef("h1", "a0"), DriveRef("h1", "a2")])
    assert len(sel.plan.pairs) == 2  # one query per drive: two groups if sent as is
    with pytest.raises(ValueError, match="one group"):
        f.send("move", sel, {"to": 1.0, "sync": True})


# ---- a commit that fails on one host stops the rest of the group (supervisor.motion._commit) ----


class _Bed:
    """The Fleet as the group path sees it (roster, selection, send): host b refuses its commit,
    host a moves until something stops it (or 5 s pass: the test then fails)."""

    def __init__(self, refuse_commit: bool, raise_commit: bool = False) -> None:
        import threading

        self.refuse_commit = refuse_commit or raise_commit
        self.raise_commit = raise_commit
        self.sent: list[tuple[str, tuple[DriveRef, ...], dict]] = []
        self.stopped = threading.Event()
        self.refs = [DriveRef("a", "x"), DriveRef("a", "y"), DriveRef("b", "x")]

    def roster(self):
        return list(self.refs)

    def conflicts(self):
        return {}

    def selection_of(self, refs, *, per_host=False):
        return tuple(refs)

    def send(self, op, sel, args=None, timeout_s=5.0):
        from supervisor.results import CommandResult, DriveResult

        args = dict(args or {})
        self.sent.append((op, tuple(sel), args))
        if op == "stop":
            self.stopped.set()
            return CommandResult("stop", "s", tuple(DriveResult(r.host, r.axis, "done") for r in sel))
        if args.get("prepare"):
            return CommandResult("move", "p", tuple(DriveResult(r.host, r.axis, "done", duration_s=0.5) for r in sel))
        host = sel[0].host
        if host == "b" and self.raise_commit:
            raise RuntimeError("session closed")
        if host == "b" and self.refuse_commit:
            return CommandResult("move", "c", (DriveResult("b", "x", "rejected", error="not enabled"),))
        if host == "a" and self.refuse_commit:
            arrived = not self.stopped.wait(5.0)
            outcome = "done" if arrived else "aborted"
            return CommandResult("move", "c", tuple(DriveResult(r.host, r.axis, outcome) for r in sel))
        return CommandResult("move", "c", tuple(DriveResult(r.host, r.axis, "done") for r in sel))


def test_a_commit_refused_on_one_host_stops_the_hosts_already_moving():
    from supervisor.motion import group_move

    bed = _Bed(refuse_commit=True)
    res = group_move(bed, {"a/x": 1.0, "a/y": 2.0, "b/x": 3.0}, timeout_s=10.0, margin_s=0.0)  # type: ignore[arg-type]
    stops = [s for s in bed.sent if s[0] == "stop"]
    assert [set(s[1]) for s in stops] == [{DriveRef("a", "x"), DriveRef("a", "y")}]  # once, the rest only
    assert {r.name: r.outcome for r in res.results} == {"a/x": "aborted", "a/y": "aborted", "b/x": "rejected"}
    assert not res.ok


def test_a_commit_that_raises_on_one_host_stops_the_others_then_is_raised():
    from supervisor.motion import group_move

    bed = _Bed(refuse_commit=False, raise_commit=True)
    with pytest.raises(RuntimeError, match="session closed"):
        group_move(bed, {"a/x": 1.0, "a/y": 2.0, "b/x": 3.0}, timeout_s=10.0, margin_s=0.0)  # type: ignore[arg-type]
    assert [set(s[1]) for s in bed.sent if s[0] == "stop"] == [{DriveRef("a", "x"), DriveRef("a", "y")}]


def test_a_group_move_that_commits_everywhere_sends_no_stop():
    from supervisor.motion import group_move

    bed = _Bed(refuse_commit=False)
    res = group_move(bed, {"a/x": 1.0, "a/y": 2.0, "b/x": 3.0}, timeout_s=10.0, margin_s=0.0)  # type: ignore[arg-type]
    assert res.ok and not [s for s in bed.sent if s[0] == "stop"]
    commits = [s for s in bed.sent if s[0] == "move" and not s[2].get("prepare")]
    assert len(commits) == 2 and len({(s[2]["duration_s"], s[2]["start_at_ns"]) for s in commits}) == 1
