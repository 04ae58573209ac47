"""The flight recorder (bus_agent/cycle/recorder.py): the ring, windows frozen around triggers,
explicit requests, and the cycle recording every drive into it (SimBus, fake clock, no sleeps)."""

from __future__ import annotations

import gc
import threading
import tracemalloc
from types import SimpleNamespace

import pytest

from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.cia402.states import State, decode_statusword
from bus_agent.config import AgentConfig, ConfigError, RecorderConfig
from bus_agent.cycle.recorder import CYCLE_CODES, DRIVE_CODES, Recorder, RecordingUnavailable
from bus_agent.runtime import CycleEvent
from schemas import messages as m

from test_cycle import Harness  # tests/unit is on sys.path (rootdir-relative imports)


def drives(n: int, base: int = 0) -> list[SimpleNamespace]:
    return [SimpleNamespace(inputs=DriveInputs(statusword=0x0237, position_actual=base + i, velocity_actual=-i,
                                               torque_actual=i, modes_of_operation_display=8, error_code=0),
                            controlword=0x000F, out=DriveOutputs(target_position=base + i, target_velocity=0, target_torque=0))
            for i in range(n)]


def test_channels_are_the_contract_s():
    assert set(CYCLE_CODES) | set(DRIVE_CODES) == set(m.RECORDING_CHANNELS)
    assert {k for k, (scope, _) in m.RECORDING_CHANNELS.items() if scope == "drive"} == set(DRIVE_CODES)


def test_last_seconds_from_the_ring_wraps_and_keeps_order():
    rec = Recorder(["a", "b"], cycle_us=1000, seconds=0.1, pre_s=0.02, post_s=0.01)
    assert rec.size == 100
    for c in range(1, 251):
        rec.record(c, c * 1_000_000, 1_000_000, 6, drives(2, base=c * 10), ())
    data = rec.fetch("last", last_s=0.05)
    assert data.n_cycles == 50 and data.first_cycle == 201
    assert data.channels["cycle"] == list(range(201, 251))
    assert data.channels["position"][:4] == [2010, 2011, 2020, 2021]  # cycle-major: a, b, a, b
    whole = rec.fetch("last", last_s=10.0)
    assert whole.n_cycles == rec.size - 1 and whole.channels["cycle"][-1] == 250
    msg = m.Recording(host="h1", **{k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(whole).items()})
    assert m.decode(m.encode(msg)) == msg  # what the recorder returns is a valid recording


def test_fault_freezes_a_window_before_and_after_kept_while_the_ring_turns():
    rec = Recorder(["a"], cycle_us=1000, seconds=0.1, pre_s=0.02, post_s=0.01)
    with pytest.raises(RecordingUnavailable, match="no window frozen by a fault trigger"):
        rec.fetch("fault")
    for c in range(1, 60):
        evs = (CycleEvent(axis="a", kind="fault", detail="error code 0x2310"),) if c == 40 else ()
        rec.record(c, c, 1, 3, drives(1), evs)
    rec.freeze_closed()
    frozen = rec.fetch("fault")
    assert frozen.trigger_cycle == 40 and frozen.axis == "a" and "0x2310" in frozen.detail
    assert frozen.channels["cycle"] == list(range(40 - 20, 40 + 11))  # 20 cycles before, the trigger, 10 after
    for c in range(60, 400):  # the ring turns several times: the frozen copy stays
        rec.record(c, c, 1, 3, drives(1), ())
    assert rec.fetch("any") == frozen
    with pytest.raises(RecordingUnavailable, match="reflex"):
        rec.fetch("reflex")


def test_second_trigger_inside_an_open_window_belongs_to_it():
    rec = Recorder(["a", "b"], cycle_us=1000, seconds=0.1, pre_s=0.02, post_s=0.01)
    for c in range(1, 60):
        evs = ()
        if c == 30:
            evs = (CycleEvent(axis="a", kind="fault"),)
        elif c == 31:
            evs = (CycleEvent(axis="b", kind="reflex"),)
        rec.record(c, c, 1, 3, drives(2), evs)
    rec.freeze_closed()
    assert rec.fetch("any").reason == "fault"
    with pytest.raises(RecordingUnavailable):
        rec.fetch("reflex")


def test_explicit_request_is_answered_when_its_window_is_complete():
    rec = Recorder(["a"], cycle_us=1000, seconds=0.1, pre_s=0.02, post_s=0.01)
    rec.start()
    for c in range(1, 101):  # some history before the request
        rec.record(c, c, 1, 3, drives(1), ())
    stop = threading.Event()
    result: list = []
    asker = threading.Thread(target=lambda: result.append(rec.fetch("now", timeout_s=30.0)))
    asker.start()
    while asker.is_alive() and c < 100_000:  # the cycle: record until the asker has its window
        c += 1
        rec.record(c, c, 1, 3, drives(1), ())
        if c % 50 == 0:
            asker.join(0.001)
    stop.set()
    asker.join(30)
    rec.stop()
    data = result[0]
    assert data.reason == "request" and data.n_cycles == 31
    assert data.channels["cycle"][-1] == data.trigger_cycle + 10


def test_record_allocates_nothing_per_cycle():
    rec = Recorder([f"x{i}" for i in range(16)], cycle_us=1000, seconds=1.0, pre_s=0.2, post_s=0.1)
    ds = drives(16, base=100)
    for c in range(1, 2000):  # warm up: every slot written once
        rec.record(c, c, 1, 48, ds, ())
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for c in range(2000, 7000):
        rec.record(c, c, 1, 48, ds, ())
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename")
                if s.traceback[0].filename.endswith("recorder.py"))
    # A few counters (ints) are rebound; anything kept per cycle would be >= 5000 x 28 bytes.
    assert grown < 1024, f"recorder kept {grown} bytes over 5000 cycles"
    assert rec.memory_bytes == 1000 * (8 * 3 + 4) + 1000 * 16 * (2 + 2 + 8 * 3 + 4 + 4 + 2 + 2 + 1)


def _traced(rec: Recorder, drives, events, first: int, n: int) -> tuple[int, int]:
    """(bytes kept by recorder.py, peak traced bytes above the start) over ``n`` record calls."""
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    for c in range(first, first + n):
        rec.record(c, c * 1_000_000, 1_000_000, 48, drives, events)
    peak = tracemalloc.get_traced_memory()[1]
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    kept = sum(s.size_diff for s in after.compare_to(before, "filename")
               if s.traceback[0].filename.endswith("recorder.py"))
    return kept, peak - base


def test_record_of_the_cycle_s_own_drives_keeps_nothing_and_builds_nothing_up():
    # The cycle's real drive records (bus_agent.cycle.drive.Drive with the inputs its bus decoded,
    # after an enable: controllers and motion stepping), not stand-ins: whatever others add to
    # them, record() must still only read their fields. A non-trigger event walks the trigger scan.
    h = Harness(n=16).open()
    rid = h.cmd("enable", *(f"axis{i}" for i in range(16)))
    h.until(h.done(rid))
    ds = h.cycle.drives
    assert len(ds) == 16 and all(d.state is State.OPERATION_ENABLED for d in ds)
    rec = Recorder([d.axis for d in ds], cycle_us=1000, seconds=1.0, pre_s=0.2, post_s=0.1)
    events = (CycleEvent(axis="axis0", kind="transition"),)
    for c in range(1, 2000):  # warm up: every slot written once
        rec.record(c, c * 1_000_000, 1_000_000, 48, ds, events)
    kept_short, peak_short = _traced(rec, ds, events, 2000, 500)
    kept, peak = _traced(rec, ds, events, 3000, 5000)
    assert not rec.error and rec.written == 1999 + 500 + 5000
    # Nothing stays per cycle (anything would be >= 5000 x 28 bytes), and nothing builds up while
    # it runs: ten times the cycles, the same peak (CPython's transient int results come and go).
    assert kept < 1024 and kept_short < 1024, (kept, kept_short)
    assert peak <= peak_short + 256, (peak, peak_short)


def test_value_beyond_its_channel_stops_recording_not_the_caller():
    rec = Recorder(["a"], cycle_us=1000, seconds=0.1, pre_s=0.02, post_s=0.01)
    d = drives(1)
    d[0].out.target_position = 2**70
    rec.record(1, 1, 1, 3, d, ())
    assert "recording stopped at cycle 1" in rec.error
    with pytest.raises(RecordingUnavailable, match="recording stopped"):
        rec.fetch("last")


def test_recorder_config_is_validated():
    with pytest.raises(ConfigError, match="recorder"):
        AgentConfig(host="h1", sim_drives=1, recorder=RecorderConfig(seconds=2.0, pre_s=2.0, post_s=1.0))
    off = AgentConfig(host="h1", sim_drives=1).with_overrides(record_s=0.0)
    assert off.recorder.seconds == 0.0


def test_cycle_records_an_injected_fault_with_the_cycles_before_it():
    h = Harness(n=3, recorder=RecorderConfig(seconds=2.0, pre_s=0.5, post_s=0.2)).open()
    rid = h.cmd("enable", "axis0", "axis1", "axis2")
    h.until(h.done(rid))
    h.ticks(600)
    h.bus.inject_fault(1, 0x2310)
    h.until(lambda s: s.drives[1].state == "fault")
    h.ticks(250)
    rec = h.cycle.recorder
    assert rec is not None
    rec.freeze_closed()
    data = h.cycle.recording("fault")
    assert data.axis == "axis1" and data.axes == ("axis0", "axis1", "axis2")
    n = len(data.axes)
    states = [decode_statusword(sw) for sw in data.channels["statusword"][1::n]]  # axis1's column
    trigger = data.trigger_cycle - data.first_cycle
    assert trigger >= 400  # half a second of history before the fault
    assert all(s == State.OPERATION_ENABLED for s in states[:trigger - 5])
    assert State.FAULT in states[trigger:]
    assert data.channels["error_code"][1::n][-1] == 0x2310 and data.channels["error_code"][1::n][0] == 0
    periods = data.channels["period_ns"]
    assert set(periods) == {1_000_000}  # the fake clock: every period exactly 1 ms
    last = h.cycle.recording("last", last_s=0.1)
    assert last.n_cycles == 100 and last.channels["cycle"][-1] == h.cycle.cycles


def test_fetch_of_a_trigger_kind_waits_for_the_window_still_recording():
    """``record --trigger last-fault`` right after a fault: the window whose after part is still
    being recorded is the answer (not "none yet", nor an older fault's window)."""
    rec = Recorder(["a"], cycle_us=1000, seconds=0.2, pre_s=0.02, post_s=0.05)
    rec.start()
    try:
        c = 0

        def run(n: int, fault_at: int = 0) -> None:
            nonlocal c
            for _ in range(n):
                c += 1
                evs = (CycleEvent(axis="a", kind="fault", detail=f"fault at {c}"),) if c == fault_at else ()
                rec.record(c, c, 1, 3, drives(1), evs)

        run(100, fault_at=30)   # an older fault, frozen
        rec.freeze_closed()
        run(10, fault_at=105)   # a new fault: its window is open (50 cycles after it to record)
        result: list = []
        asker = threading.Thread(target=lambda: result.append(rec.fetch("fault", timeout_s=30.0)))
        asker.start()
        asker.join(0.2)
        assert asker.is_alive(), "answered before the open window was frozen"
        while asker.is_alive() and c < 10_000:
            run(10)
            asker.join(0.005)
        asker.join(30)
        data = result[0]
        assert data.trigger_cycle == 105 and data.detail == "fault at 105"
        assert data.channels["cycle"][-1] == 105 + 50
        # Nothing pending: an older kind answers at once, a kind never seen says so at once.
        assert rec.fetch("fault").trigger_cycle == 105
        with pytest.raises(RecordingUnavailable, match="no window frozen by a reflex trigger"):
            rec.fetch("reflex", timeout_s=30.0)
    finally:
        rec.stop()


def test_fetch_waiting_for_a_window_is_bounded_with_the_reason():
    rec = Recorder(["a"], cycle_us=1000, seconds=0.2, pre_s=0.02, post_s=0.05)
    for c in range(1, 20):  # the cycle stops right after the fault: the window never closes
        rec.record(c, c, 1, 3, drives(1), (CycleEvent(axis="a", kind="fault"),) if c == 10 else ())
    with pytest.raises(RecordingUnavailable, match=r"fault window \(trigger at cycle 10\) was not frozen within"):
        rec.fetch("fault", timeout_s=0.05)
