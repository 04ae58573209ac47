"""Lease table (bus_agent.gateway.leases): pure logic, the clock is a parameter."""

from __future__ import annotations

import pytest

from bus_agent.gateway.leases import LeaseEnd, LeaseResult, LeaseTable


def results(decisions):
    return [(d.axis, d.result, d.holder, d.previous) for d in decisions]


def test_grant_renew_and_check():
    t = LeaseTable()
    assert results(t.acquire(["x", "y"], "supA", 2.0, False, now_s=10.0)) == [
        ("x", LeaseResult.GRANTED, "supA", ""), ("y", LeaseResult.GRANTED, "supA", "")]
    assert t.check("x", "supA") == ""
    assert t.check("x", "supB") == "supA"
    assert t.check("x", "") == "supA"          # anonymous commands are refused too
    assert t.check("z", "supB") == ""          # a free drive
    assert results(t.acquire(["x"], "supA", 5.0, False, now_s=11.0)) == [("x", LeaseResult.RENEWED, "supA", "supA")]
    assert t.get("x").expires_s == 16.0
    assert t.holders() == {"x": "supA", "y": "supA"}


def test_other_holder_is_busy_all_or_nothing():
    t = LeaseTable()
    t.acquire(["x"], "supA", 2.0, False, now_s=0.0)
    out = t.acquire(["x", "y"], "supB", 2.0, False, now_s=0.5)
    assert [d.result for d in out] == [LeaseResult.BUSY, LeaseResult.BUSY]
    assert [d.previous for d in out] == ["supA", "supA"]   # both name who blocks
    assert not out[0].ok
    assert t.holders() == {"x": "supA"}                    # y was not half-granted


def test_takeover():
    t = LeaseTable()
    t.acquire(["x"], "supA", 2.0, False, now_s=0.0)
    out = t.acquire(["x", "y"], "supB", 3.0, True, now_s=1.0)
    assert results(out) == [("x", LeaseResult.TAKEN_OVER, "supB", "supA"), ("y", LeaseResult.GRANTED, "supB", "")]
    assert t.check("x", "supA") == "supB"


def test_release():
    t = LeaseTable()
    t.acquire(["x"], "supA", 2.0, False, now_s=0.0)
    assert results(t.release(["x", "y"], "supB")) == [("x", LeaseResult.BUSY, "supA", "supA"),
                                                      ("y", LeaseResult.NOT_LEASED, "", "")]
    assert results(t.release(["x"], "supA")) == [("x", LeaseResult.RELEASED, "", "supA")]
    assert t.holders() == {}


def test_expiry():
    t = LeaseTable()
    t.acquire(["x"], "supA", 1.0, False, now_s=0.0)
    t.acquire(["y"], "supB", 3.0, False, now_s=0.0)
    assert t.next_expiry_s() == 1.0
    assert t.expire(0.99) == []
    ended = t.expire(1.0)
    assert [(e.lease.axis, e.lease.holder, e.why) for e in ended] == [("x", "supA", LeaseEnd.EXPIRED)]
    assert t.holders() == {"y": "supB"}
    assert t.next_expiry_s() == 3.0


def test_renewal_postpones_expiry():
    t = LeaseTable()
    t.acquire(["x"], "supA", 1.0, False, now_s=0.0)
    t.acquire(["x"], "supA", 1.0, False, now_s=0.9)
    assert t.expire(1.5) == []
    assert [e.lease.axis for e in t.expire(1.9)] == ["x"]


def test_holder_lost():
    t = LeaseTable()
    t.acquire(["x", "y"], "supA", 10.0, False, now_s=0.0)
    t.acquire(["z"], "supB", 10.0, False, now_s=0.0)
    ended = t.holder_lost("supA")
    assert sorted(e.lease.axis for e in ended) == ["x", "y"]
    assert all(e.why is LeaseEnd.HOLDER_LOST for e in ended)
    assert t.holders() == {"z": "supB"}
    assert t.holder_lost("nobody") == []


@pytest.mark.parametrize("ttl", [0.0, 0.05, 3601.0, -1.0])
def test_bad_ttl_changes_nothing(ttl):
    t = LeaseTable()
    with pytest.raises(ValueError, match="ttl_s"):
        t.acquire(["x"], "supA", ttl, False, now_s=0.0)
    assert t.holders() == {}


def test_holder_required():
    with pytest.raises(ValueError, match="holder"):
        LeaseTable().acquire(["x"], "", 1.0, False, now_s=0.0)
