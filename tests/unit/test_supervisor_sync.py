"""A synchronized move has one path (supervisor.motion.sync_move): ``Fleet.send``, which sends a
selection's queries as planned, refuses a ``sync`` move that does not name its axes per host
(planned per drive it would start as several groups). No session: refused before any I/O."""

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
