"""The Fleet's reply collector (``supervisor.commands._Collector``): one reply kept per drive, and
the waiting caller woken once per host that has answered for all its addressed drives."""

from __future__ import annotations

from schemas.messages import CommandReply
from supervisor.commands import _Collector
from supervisor.selectors import DriveRef


def _reply(host: str, axis: str, outcome: str = "done") -> CommandReply:
    return CommandReply(request_id="r", host=host, op="enable", outcome=outcome, axis=axis)


def test_wakes_once_per_completed_host_and_keeps_the_first_reply() -> None:
    refs = [DriveRef("h1", "a"), DriveRef("h1", "b"), DriveRef("h2", "a")]
    col = _Collector(frozenset(refs))
    assert col.add(refs[0], _reply("h1", "a")) is False          # h1 still owes b
    assert col.add(refs[0], _reply("h1", "a", "failed")) is False  # a repeat: ignored
    assert col.replies[refs[0]].outcome == "done"
    assert col.add(refs[1], _reply("h1", "b")) is True            # h1 complete
    assert col.add(DriveRef("h3", "x"), _reply("h3", "x")) is False  # not addressed: kept, no wake
    assert col.add(refs[2], _reply("h2", "a")) is True
    assert set(col.replies) == {*refs, DriveRef("h3", "x")}
    assert col.left == {"h1": 0, "h2": 0}


def test_agent_level_refs_count_per_host() -> None:
    col = _Collector(frozenset({DriveRef("h1", ""), DriveRef("h2", "")}))
    assert col.add(DriveRef("h1", ""), _reply("h1", "")) is True
    assert col.add(DriveRef("h2", ""), _reply("h2", "")) is True


def test_a_departing_agent_wakes_the_commands_waiting_for_it() -> None:
    import threading

    from schemas import keys
    from supervisor.fleet import Fleet

    fleet = Fleet(connect=["tcp/127.0.0.1:1"], name="t")   # not opened: only its view is used
    fleet._view.host_alive(keys.alive("h1"), True)
    col = _Collector(frozenset({DriveRef("h1", "a")}))
    fleet._commands.collectors.add(col)
    waiting, woken = threading.Event(), []

    def waiter() -> None:
        with col.cv:
            waiting.set()
            woken.append(col.cv.wait(10))

    t = threading.Thread(target=waiter)
    t.start()
    assert waiting.wait(10)
    with col.cv:  # taken only once the waiter is inside wait()
        pass
    fleet._view.host_alive(keys.alive("h1"), False)
    t.join(10)
    assert woken == [True] and fleet.hosts() == []
