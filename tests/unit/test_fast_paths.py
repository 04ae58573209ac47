"""The cycle's fast paths give the same results as the full work they skip.

- ``DriveController`` reusing a settled step (``reuse_settled``) against one that always steps in
  full, over random command and statusword sequences that repeat inputs often;
- the statusword lookup table against the standard's (mask, value) patterns.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.cia402.controller import ControllerConfig, DriveController, Goal
from bus_agent.cia402.states import STATUSWORD_OF_STATE, STATUSWORD_PATTERNS, State, decode_statusword
from tests.unit.test_mapping_codec import _byte_aligned, _objects

# a few statuswords per state (bit 4 and bits 8+ vary), so that inputs repeat often
_sw = st.builds(lambda low, extra: low | extra, st.sampled_from(sorted(STATUSWORD_OF_STATE.values())),
                st.sampled_from([0x0000, 0x0010, 0x0210, 0x0610]))
_step = st.tuples(st.just("step"), st.one_of(_sw, st.integers(0, 0xFFFF)),
                  st.sampled_from([None, None, 0, 8, 9]), st.sampled_from([0.0, 0.001, 0.001, 0.05, 0.3, 6.0]))
_repeat = st.tuples(st.just("repeat"), st.integers(1, 30), st.sampled_from([0.001, 0.1, 2.0]))
_cmd = st.one_of(
    st.tuples(st.just("goal"), st.sampled_from(list(Goal))),
    st.tuples(st.just("halt"), st.booleans()),
    st.tuples(st.just("mode"), st.sampled_from([1, 3, 8, 9, 10])),
    st.tuples(st.just("reset")),
)
_configs = st.builds(ControllerConfig, transition_timeout_s=st.sampled_from([0.2, 1.0]),
                     mode_timeout_s=st.sampled_from([0.2, 1.0]), fault_reset_retries=st.integers(1, 3),
                     fault_reset_low_s=st.sampled_from([0.0, 0.01]), fault_reset_high_s=st.sampled_from([0.0, 0.05]),
                     not_ready_grace_s=st.sampled_from([0.0, 0.1]))


def _view(c: DriveController) -> tuple:
    return (c.state, c.goal, c.goal_phase, c.halt, c.mode, c.mode_pending, c.fault_reset_active, c.statusword)


@settings(max_examples=150, deadline=None)
@given(_configs, st.sampled_from([None, frozenset({8, 9}), frozenset({1, 3, 8, 9, 10})]),
       st.lists(st.one_of(_step, _step, _repeat, _cmd), min_size=1, max_size=80))
def test_a_settled_step_reused_equals_a_full_step(config, modes, actions):
    fast = DriveController(config, supported_modes=modes)
    full = DriveController(config, supported_modes=modes)
    full.reuse_settled = False
    t = 0.0
    last = (0, 0)
    for a in actions:
        if a[0] in ("step", "repeat"):
            if a[0] == "step":
                sw, md, dt = a[1], a[2], a[3]
                last = (sw, fast.mode if md is None else md)
                steps = 1
            else:
                steps, dt = a[1], a[2]
            for _ in range(steps):
                t += dt
                assert fast.step(*last, t) == full.step(*last, t)
                assert _view(fast) == _view(full)
        elif a[0] == "goal":
            fast.set_goal(a[1], t)
            full.set_goal(a[1], t)
        elif a[0] == "halt":
            fast.set_halt(a[1])
            full.set_halt(a[1])
        elif a[0] == "mode":
            fast.request_mode(a[1], t)
            full.request_mode(a[1], t)
        else:
            fast.request_fault_reset(t)
            full.request_fault_reset(t)


def test_a_settled_controller_reuses_its_output_and_any_command_drops_it():
    c = DriveController(ControllerConfig(), mode=8)
    c.set_goal(Goal.ENABLED, 0.0)
    t = 0.0
    for sw in (0x0250, 0x0231, 0x0233, 0x0237):
        t += 0.001
        c.step(sw, 8, t)
    out = c.step(0x0237, 8, t + 0.001)  # goal reached in the step before: settled now
    assert out.events == () and out.controlword == 0x000F
    assert c.step(0x0237, 8, t + 10.0) is out          # same inputs, any time: the same output
    assert c.step(0x0233, 8, t + 10.0) is not out      # new inputs: a full step (goal lost)
    c2 = DriveController(ControllerConfig(), mode=8)
    c2.set_goal(Goal.DISABLED, 0.0)
    first = c2.step(0x0250, 8, 0.0)
    assert first.events  # goal reached, mode confirmed
    again = c2.step(0x0250, 8, 0.001)
    assert c2.step(0x0250, 8, 0.002) is again
    c2.set_halt(True)
    halted = c2.step(0x0250, 8, 0.003)
    assert halted is not again and halted.controlword & 0x0100
    c2.request_mode(9, 0.004)
    assert c2.step(0x0250, 8, 0.005).mode_of_operation == 9


def test_the_statusword_table_equals_the_standards_patterns():
    for sw in range(0x10000):
        expected = next((s for mask, value, s in STATUSWORD_PATTERNS if sw & mask == value), State.UNKNOWN)
        assert decode_statusword(sw) is expected


# ---- the cycle's snapshots: rebuilt only for drives whose values changed ---------------------------

#: Every DriveSnapshot field the cycle fills, in order. A new field must also be added to the change
#: key in Snapshots.drive_snapshots (bus_agent/cycle/output.py; else a change of it alone would not be published), and the cycle
#: builds the record positionally in this order: update all three.
SNAPSHOT_FIELDS = ("axis", "slave", "state", "statusword", "controlword", "goal", "halt", "mode", "mode_display",
                   "position", "velocity", "torque", "error_code", "error_text", "al_state", "lost", "absent",
                   "object_names", "objects", "dc", "axis_state", "homed", "target_position", "following_error",
                   "motion_request_id", "target_clamps", "last_known_state")


def test_the_snapshot_fields_are_the_ones_the_change_key_covers():
    import dataclasses

    from bus_agent.runtime import DriveSnapshot

    assert tuple(f.name for f in dataclasses.fields(DriveSnapshot)) == SNAPSHOT_FIELDS


def test_a_drive_at_rest_keeps_its_snapshot_and_a_change_builds_a_new_one():
    from tests.unit.test_cycle import Harness

    h = Harness(n=3).open()
    try:
        rid = h.cmd("enable", "axis0", "axis1", "axis2")
        h.until(h.done(rid, 3))
        first = h.ticks(3)
        second = h.tick()
        assert second is not first and second.cycle == first.cycle + 1
        assert second.drives is first.drives            # nothing changed: the same tuple
        rid = h.cmd("halt", "axis1", on=True)
        third = h.until(h.done(rid))
        assert third.drives[1] is not first.drives[1] and third.drives[1].halt is True
        assert third.drives[0] is first.drives[0] and third.drives[2] is first.drives[2]
        h.bus.inject_fault(2, 0x2310)
        faulted = h.until(lambda s: s.drives[2].state == "fault")
        assert faulted.drives[2].error_code == 0x2310 and faulted.drives[0] is first.drives[0]
        # every published value equals a snapshot built from scratch of the same cycle
        assert h.cycle.snapshots.drive_snapshots(h.cycle.drives) is faulted.drives
        for d in h.cycle.drives:
            d.snapshot = None
        assert h.cycle.snapshots.drive_snapshots(h.cycle.drives) == faulted.drives
        # the positional build names each value right: the fields from their sources, by name
        d, snap = h.cycle.drives[2], faulted.drives[2]
        i = d.inputs
        assert (snap.axis, snap.slave, snap.state, snap.statusword, snap.controlword, snap.goal, snap.mode,
                snap.mode_display, snap.position, snap.error_code, snap.al_state, snap.axis_state) == (
            d.axis, d.slave, d.state.value, i.statusword, d.controlword, d.ctrl.goal.value, d.ctrl.mode,
            i.modes_of_operation_display, i.position_actual, i.error_code, "op", d.motion.axis_state.value)
    finally:
        h.cycle.stop(timeout_s=1.0)


# ---- the codec: one pass over the whole process image -------------------------------------------


def _random_layouts(data, n: int):
    layouts = []
    for _ in range(n):
        tx = data.draw(_objects(False))
        tx.insert(data.draw(st.integers(0, len(tx))), (0x6041, 0, 16))
        layouts.append(_byte_aligned(tx))
    return layouts


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_the_segment_decoder_equals_each_drives_own_decode(data):
    import random
    from types import SimpleNamespace

    from bus_agent.bus.codec import DriveCodec, segment_decoder
    from bus_agent.bus.mapping import mapping_of
    from bus_agent.bus.pdo import DriveInputs, mapping_entry

    layouts = _random_layouts(data, data.draw(st.integers(1, 5)))
    codecs = [DriveCodec(mapping_of([(0x1600, [mapping_entry(0x6040, 0, 16)])],
                                    [(0x1A00, [mapping_entry(*e) for e in tx])])) for tx in layouts]
    rng = random.Random(data.draw(st.integers(0, 2**32)))
    sources = [SimpleNamespace(input=rng.randbytes(c.in_size)) for c in codecs]
    # records that held other values before: every field is written (0 where not mapped)
    records = [DriveInputs(7, 7, 7, 7, 7, 7, (7,)) for _ in codecs]
    segment_decoder(codecs, records, sources)()
    for c, src, rec in zip(codecs, sources, records):
        alone = DriveInputs()
        c.decode_into(alone, src.input)
        assert rec == alone
    with pytest.raises(ValueError):
        segment_decoder(codecs, records, sources, attr="input; import os")


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_the_change_tracking_decoder_reports_and_decodes_exactly_the_changed_slaves(data):
    import random
    from types import SimpleNamespace

    from bus_agent.bus.codec import DriveCodec, segment_decoder
    from bus_agent.bus.mapping import mapping_of
    from bus_agent.bus.pdo import DriveInputs, mapping_entry

    layouts = _random_layouts(data, data.draw(st.integers(1, 5)))
    codecs = [DriveCodec(mapping_of([(0x1600, [mapping_entry(0x6040, 0, 16)])],
                                    [(0x1A00, [mapping_entry(*e) for e in tx])])) for tx in layouts]
    rng = random.Random(data.draw(st.integers(0, 2**32)))
    sources = [SimpleNamespace(input=rng.randbytes(c.in_size)) for c in codecs]
    records = [DriveInputs() for _ in codecs]
    decode = segment_decoder(codecs, records, sources, changes=True)
    assert decode() == list(range(len(codecs)))  # the first call decodes every slave
    for _ in range(5):
        changed = sorted(set(data.draw(st.lists(st.integers(0, len(codecs) - 1), max_size=len(codecs)))))
        for k in changed:  # new bytes (a flipped bit, so they differ)
            b = bytearray(sources[k].input)
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            sources[k].input = bytes(b)
        assert decode() == changed
        for c, src, rec in zip(codecs, sources, records):
            alone = DriveInputs()
            c.decode_into(alone, src.input)
            assert rec == alone
    assert decode() == []


def test_decode_into_writes_every_field_of_a_reused_record():
    from bus_agent.bus.codec import DriveCodec
    from bus_agent.bus.mapping import mapping_of
    from bus_agent.bus.pdo import DriveInputs, mapping_entry

    c = DriveCodec(mapping_of([(0x1600, [mapping_entry(0x6040, 0, 16)])],
                              [(0x1A00, [mapping_entry(0x6041, 0, 16), mapping_entry(0x60FD, 0, 32)])]))
    rec = DriveInputs(1, 2, 3, 4, 5, 6, (7,))
    c.decode_into(rec, bytes([0x37, 0x02, 1, 0, 0, 0]))
    assert rec == DriveInputs(0x0237, 0, 0, 0, 0, 0, (1,))
    assert c.absent_inputs == ("position", "velocity", "torque", "mode_display", "error_code")


# ---- the spin before each deadline ----------------------------------------------------------------


class _TickingClock:
    """A fake monotonic clock that moves 1 us per read (so a spin ends) and by what sleep asks
    plus ``over`` ns (how late the kernel wakes the thread)."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000
        self.over = 0

    def __call__(self) -> int:
        self.ns += 1000
        return self.ns

    def sleep(self, s: float) -> None:
        self.ns += int(s * 1e9) + self.over


def test_the_spin_adapts_to_how_late_the_sleep_wakes():
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import SPIN_MIN_NS, SPIN_NS, Cycle

    clock = _TickingClock()
    cyc = Cycle(SimBus(1), AgentConfig(host="h1", sim_drives=1), clock_ns=clock, sleep=clock.sleep,
                manage_gc=False, switch_interval_s=None)

    def wait(cycles: int) -> list[int]:
        late = []
        for _ in range(cycles):
            deadline = clock.ns + 1_000_000
            cyc.timing.wait_until(deadline)
            late.append(clock.ns - deadline)
        cyc.timing.adapt_spin()
        return late

    cyc.spin_at_rest = True                             # the spin itself (the drive is off here)
    assert cyc.spin_ns is None                          # adaptive by default
    assert cyc.timing.spin_auto_ns == SPIN_NS                 # until sleeps were measured
    clock.over = 20_000
    assert max(wait(50)) < 5_000                        # woken 20 us late, spun 150 us: on time
    assert SPIN_MIN_NS <= cyc.timing.spin_auto_ns <= 20_000 + 30_000 + 5_000
    clock.over = 0
    wait(2000)                                          # a whole window of punctual sleeps
    assert SPIN_MIN_NS <= cyc.timing.spin_auto_ns <= SPIN_MIN_NS + 5_000  # the fake clock ticks 1 us a read
    clock.over = 400_000                                # a loaded host: the spin goes back up
    wait(10)
    assert cyc.timing.spin_auto_ns == SPIN_NS
    cyc.spin_ns = 100_000                               # fixed (benchmarks)
    clock.over = 0
    deadline = clock.ns + 1_000_000
    cyc.timing.wait_until(deadline)
    assert 0 <= clock.ns - deadline < 5_000


def test_the_loop_spins_only_while_a_drive_is_switched_on_asked_up_or_moving():
    """Every drive off (and no SYNC0): the wait before a deadline only sleeps, so a late wake-up
    shows; from an enable command on (goal up, then Switched on, Operation enabled) it spins
    again, and after a disable it stops; ``spin_at_rest`` spins always."""
    from bus_agent.bus.sim_bus import SimBus
    from bus_agent.config import AgentConfig
    from bus_agent.cycle.cycle import Cycle
    from bus_agent.runtime import DriveCommand

    clock = _TickingClock()
    cyc = Cycle(SimBus(2, clock=lambda: clock.ns / 1e9), AgentConfig(host="h1", sim_drives=2), clock_ns=clock,
                sleep=clock.sleep, manage_gc=False, switch_interval_s=None)
    cyc.spin_ns = 150_000
    cyc.open()
    clock.over = 40_000  # every sleep wakes 40 us late

    def late() -> int:
        deadline = clock.ns + 1_000_000
        cyc.timing.wait_until(deadline)
        return clock.ns - deadline

    def run(cmd: str) -> list[bool]:
        done: list = []
        assert cyc.submit(DriveCommand(request_id=cmd, op=cmd, axes=("axis1",), on_outcome=done.append))
        spun = []
        for _ in range(300):
            cyc.tick()
            spun.append(late() < 5_000)
            if done:
                break
        assert [o.outcome for o in done] == ["done"], done
        return spun

    for _ in range(5):
        cyc.tick()
    assert late() >= 40_000                              # both drives off: no spin
    assert all(run("enable"))                            # from the command on: the spin
    assert late() < 5_000 and cyc.controllers.armed == {1}          # axis1 in Operation enabled
    run("disable")
    cyc.tick()
    assert late() >= 40_000 and not cyc.controllers.armed          # off again
    cyc.spin_at_rest = True
    assert late() < 5_000
    cyc.stop(ordered=False)


def test_the_cycle_thread_gets_its_name_and_timer_slack():
    import threading

    from bus_agent.cycle.realtime import name_thread, set_timer_slack_ns

    seen: list = []

    def run() -> None:
        seen.append(name_thread("cycle-test") and set_timer_slack_ns(1))
        seen.append(open(f"/proc/self/task/{threading.get_native_id()}/comm").read().strip())

    t = threading.Thread(target=run)
    t.start()
    t.join()
    assert seen == [True, "cycle-test"]
