"""Lost and found by construction (issue 23 items 1 and 2): a returned slave is found only once
the working counter proves its process data, and a lost drive's state is ``unknown`` with none
of its old inputs published as current. The cycle on SimBus with a fake clock, and the pure
:class:`FoundConfirmation`."""

from __future__ import annotations

from bus_agent.bus.base import ALState, SlaveALStatus
from bus_agent.cia402.states import State
from bus_agent.cycle.found import FOUND_CONFIRM_CYCLES, FoundConfirmation
from tests.unit.test_cycle import Harness

OP = SlaveALStatus(ALState.OP, False, 0)
SAFEOP_ERR = SlaveALStatus(ALState.SAFEOP, True, 0x001B)
NONE = SlaveALStatus(ALState.NONE, False, 0)


def test_a_returned_slave_is_found_after_the_counter_proves_it_for_several_cycles():
    f = FoundConfirmation()
    f.returned(1, epoch=1)
    al = [OP, OP]
    for _ in range(FOUND_CONFIRM_CYCLES - 1):
        assert f.step(6, 6, {1}, al) == []
    assert f.step(6, 6, {1}, al) == [1]
    assert not f  # found once
    assert f.step(6, 6, {1}, al) == []


def test_a_wrong_counter_starts_the_proof_again():
    f = FoundConfirmation()
    f.returned(0, epoch=1)
    al = [OP, OP]
    for _ in range(FOUND_CONFIRM_CYCLES - 1):
        f.step(6, 6, {0}, al)
    assert f.step(3, 6, {0}, al) == []   # its process data did not arrive: count again
    for _ in range(FOUND_CONFIRM_CYCLES - 1):
        assert f.step(6, 6, {0}, al) == []
    assert f.step(6, 6, {0}, al) == [0]


def test_an_al_state_not_op_is_never_found():
    f = FoundConfirmation()
    f.returned(0, epoch=1)
    for _ in range(3 * FOUND_CONFIRM_CYCLES):
        assert f.step(6, 6, {0}, [SAFEOP_ERR, OP]) == []


def test_other_lost_slaves_count_only_when_they_cannot_add_to_the_counter():
    al = [OP, NONE, OP]
    f = FoundConfirmation()
    f.returned(0, epoch=1)
    # slave 1 still lost and silent: the counter proves slave 0 when it is 9 - 3
    found = [f.step(6, 9, {0, 1}, al) for _ in range(FOUND_CONFIRM_CYCLES)]
    assert found[-1] == [0]
    # slave 1 lost but in SAFE-OP (it may add 1): nothing can be proven
    f.returned(2, epoch=1)
    al = [OP, SAFEOP_ERR, OP]
    for _ in range(3 * FOUND_CONFIRM_CYCLES):
        assert f.step(6, 9, {1, 2}, al) == []


def test_cancel_forgets_a_waiting_slave():
    f = FoundConfirmation()
    f.returned(0, epoch=1)
    f.cancel(0)
    assert not f.waiting(0)
    assert all(f.step(3, 3, {0}, [OP]) == [] for _ in range(2 * FOUND_CONFIRM_CYCLES))


def test_stale_process_data_is_never_published_as_found_and_a_lost_drive_is_unknown():
    """The soak's case: wkc_fault on an enabled drive for 1 s. Its AL state reads OP again as
    soon as the management thread acknowledges the SM watchdog error, but its process data does
    not arrive: it stays lost (state unknown, no old inputs) until the fault ends, and is then
    found with the drive's real state (fault 0x8130), never operation_enabled."""
    hh = Harness(n=2).open()
    try:
        rid = hh.cmd("enable", "axis0", "axis1")
        hh.until(hh.done(rid, 2))
        hh.bus.set_wkc_fault(1, True)
        snap = hh.until(lambda s: s.drives[1].lost, 500)
        seen_lost = []
        for _ in range(1000):  # 1 s of cycles with the fault on
            snap = hh.tick()
            d = snap.drives[1]
            assert d.lost, "found while its process data does not arrive"
            assert d.state == "unknown"
            assert d.last_known_state == "operation_enabled"
            assert (d.statusword, d.position, d.velocity, d.torque, d.error_code) == (0, 0, 0, 0, 0)
            assert set(d.absent) == {"position", "velocity", "torque"} and d.objects == ()
            assert d.error_text.startswith("lost: ")
            seen_lost.append(d)
        assert snap.drives[0].state == "operation_enabled" and not snap.drives[0].lost
        hh.bus.set_wkc_fault(1, False)
        snap = hh.until(lambda s: not s.drives[1].lost, 1000)
        found = [e for e in snap.events if e.kind == "found" and e.axis == "axis1"]
        assert found and f"{FOUND_CONFIRM_CYCLES} cycles" in found[0].detail
        d = snap.drives[1]
        # the drive's own state, from fresh inputs: it faulted when its outputs stopped
        assert d.state == "fault" and d.error_code == 0x8130, (d.state, hex(d.error_code))
        assert d.last_known_state == "" and d.goal == "disabled"
        assert hh.state(1) == State.FAULT
    finally:
        hh.cycle.stop(ordered=False)  # the fake clock stands still in stop(): no deadline to wait for


def test_a_command_to_a_lost_drive_answers_state_unknown():
    hh = Harness(n=2).open()
    try:
        rid = hh.cmd("enable", "axis0", "axis1")
        hh.until(hh.done(rid, 2))
        hh.bus.unplug(1)
        hh.until(lambda s: s.drives[1].lost, 200)
        r2 = hh.cmd("enable", "axis1")
        hh.until(hh.done(r2))
        o = hh.outcomes[r2][0]
        assert o.outcome == "rejected" and o.state == "unknown" and o.error_code == 0
    finally:
        hh.cycle.stop(timeout_s=1.0)
