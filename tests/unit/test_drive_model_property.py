"""Property: any controlword sequence follows the CiA 402 transition graph and never raises."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.cia402.states import State, decode_statusword
from bus_agent.bus.pdo import DriveOutputs
from bus_agent.sim.drive_model import PROFILES, DriveModel

S = State
#: (from, to) pairs of transitions 1..16 (2 also from not ready for the indy7 profile).
ALLOWED = {
    (S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED),   # 1
    (S.NOT_READY_TO_SWITCH_ON, S.READY_TO_SWITCH_ON),   # indy7 (seed 004)
    (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON),       # 2
    (S.READY_TO_SWITCH_ON, S.SWITCHED_ON),              # 3
    (S.SWITCHED_ON, S.OPERATION_ENABLED),               # 4
    (S.OPERATION_ENABLED, S.SWITCHED_ON),               # 5
    (S.SWITCHED_ON, S.READY_TO_SWITCH_ON),              # 6
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED),       # 7
    (S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON),        # 8
    (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED),        # 9
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED),              # 10
    (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE),         # 11
    (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED),        # 12
    (S.FAULT_REACTION_ACTIVE, S.FAULT),                 # 14
    (S.FAULT, S.SWITCH_ON_DISABLED),                    # 15
    (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED),         # 16
} | {(s, S.FAULT_REACTION_ACTIVE) for s in S if s not in (S.UNKNOWN, S.FAULT_REACTION_ACTIVE, S.FAULT)}  # 13

interesting_cw = st.sampled_from([0x0000, 0x0002, 0x0006, 0x0007, 0x000F, 0x0080, 0x008F, 0x010F, 0x001F])
step = st.tuples(
    st.one_of(interesting_cw, st.integers(0, 0xFFFF)),             # controlword
    st.sampled_from([0, 1, 3, 4, 6, 8, 9, 10, -5, 127]),           # modes of operation (some refused)
    st.integers(-(2**31), 2**31 - 1),                              # target position
    st.integers(-(2**31), 2**31 - 1),                              # target velocity
    st.sampled_from([0.0, 0.0005, 0.001, 0.004, 0.1]),             # dt
    st.sampled_from([None] * 12 + [0x2310, 0x8611]),               # occasional injected fault
)


@settings(max_examples=300, deadline=None)
@given(profile=st.sampled_from(["generic", "indy7"]), option=st.integers(0, 8),
       steps=st.lists(step, min_size=1, max_size=60))
def test_random_controlwords_follow_the_graph(profile: str, option: int, steps: list) -> None:
    m = DriveModel(PROFILES[profile])
    m.write(0x605A, 0, option)
    prev = m.state
    for cw, mode, pos, vel, dt, fault in steps:
        if fault is not None:
            m.inject_fault(fault)
            assert (prev, m.state) in ALLOWED or prev is m.state
            prev = m.state
        m.apply_outputs(DriveOutputs(controlword=cw, modes_of_operation=mode,
                                     target_position=pos, target_velocity=vel))
        m.step(dt)
        now = m.state
        if now is not prev:
            assert (prev, now) in ALLOWED, f"{prev} -> {now} on 0x{cw:04X}"
            if now is S.OPERATION_ENABLED:
                # only from Switched on (4) or back from Quick stop active with 0x605A 5..8 (16)
                assert prev is S.SWITCHED_ON or (prev is S.QUICK_STOP_ACTIVE and option >= 5)
        assert decode_statusword(m.statusword) is now
        assert m.read(0x6061, 0) in (0, 1, 3, 4, 6, 8, 9, 10)
        prev = now
