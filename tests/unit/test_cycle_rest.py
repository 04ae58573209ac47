"""The cycle's fast path for drives at rest gives exactly what stepping every drive gives.

Two cycles over two identical SimBus segments with the same injected clock, one with
``Cycle.fast_paths`` (drives whose inputs did not change and that are at rest are skipped), one
stepping every drive every cycle, get the same random sequences of commands (state machine,
halt, motion, modes), faults, lost and returned slaves, working counter errors and remote group
triggers (in the next cycle, or at once in an express exchange). Every cycle both must publish the same snapshot (drives, events, statistics), answer
the same outcomes, and write the same outputs to the drives; at the end their flight recordings
are the same. And the fast path must have skipped work, or it tests nothing.
"""

from __future__ import annotations

from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from bus_agent.motion.config import MotionConfig
from tests.unit.motion_rig import Rig

N = 3
AXES = tuple(f"axis{i}" for i in range(N))
MOTION = MotionConfig(max_velocity=100_000, max_acceleration=1_000_000, max_jerk=20_000_000,
                      min_position=-1_000_000, max_position=1_000_000)
GROUPS = {"line": ["h1/axis0", "h1/axis1", "h2/far"]}

_axes = st.lists(st.sampled_from(AXES), min_size=1, max_size=N, unique=True).map(tuple)
_command = st.one_of(
    st.tuples(st.sampled_from(["enable", "disable", "fault_reset", "quick_stop", "shutdown", "stop"]), _axes,
              st.just({})),
    st.tuples(st.just("halt"), _axes, st.builds(lambda on: {"on": on}, st.booleans())),
    st.tuples(st.just("move"), _axes, st.builds(lambda x: {"to": x}, st.integers(-200_000, 200_000))),
    st.tuples(st.just("jog"), _axes, st.builds(lambda v: {"velocity": v, "for_s": 0.05},
                                               st.integers(-50_000, 50_000))),
    st.tuples(st.just("set_mode"), _axes, st.builds(lambda m: {"mode": m}, st.sampled_from([8, 9]))),
)
_action = st.one_of(
    st.tuples(st.just("ticks"), st.integers(1, 80)),
    st.tuples(st.just("ticks"), st.integers(1, 80)),
    st.tuples(st.just("command"), _command),
    st.tuples(st.just("command"), _command),
    st.tuples(st.just("fault"), st.integers(0, N - 1), st.sampled_from([0x2310, 0x7305])),
    st.tuples(st.just("unplug"), st.integers(0, N - 1)),
    st.tuples(st.just("plug"), st.integers(0, N - 1)),
    st.tuples(st.just("wkc"), st.integers(0, N - 1), st.booleans()),
    st.tuples(st.just("trigger"),),
    st.tuples(st.just("express"),),
)


def _outputs(r: Rig) -> list[tuple]:
    return [tuple(int(r.model(i).read(idx, 0)) for idx in (0x6040, 0x607A, 0x60FF, 0x6071, 0x6060)) for i in range(N)]


@settings(max_examples=40, deadline=None, phases=(Phase.explicit, Phase.reuse, Phase.generate))
@given(st.lists(_action, min_size=1, max_size=25))
def test_skipping_drives_at_rest_equals_stepping_every_drive(actions):
    fast, full = (Rig(N, motion=MOTION, groups=GROUPS) for _ in range(2))
    full.cycle.fast_paths = False
    got: dict[str, tuple[list, list]] = {}
    cycles = 0

    def tick() -> None:
        nonlocal cycles
        fast.tick()
        full.tick()
        cycles += 1
        assert fast.cycle.latest == full.cycle.latest, f"cycle {cycles}"
        assert _outputs(fast) == _outputs(full), f"cycle {cycles}"
        for rid, (a, b) in got.items():
            assert a == b, f"cycle {cycles}: outcomes of {rid}"

    try:
        for _ in range(5):
            tick()
        actions = [("command", ("enable", AXES, {}))] + actions + [("ticks", 300)]
        for a in actions:
            if a[0] == "ticks":
                for _ in range(a[1]):
                    tick()
            elif a[0] == "command":
                op, axes, args = a[1]
                got[f"{op}{len(got)}"] = (fast.send(op, axes, args, timeout_s=0.5), full.send(op, axes, args, timeout_s=0.5))
                tick()
            elif a[0] in ("trigger", "express"):
                for r in (fast, full):
                    r.cycle.trigger_group("line", "h2/far fault 0x2310")
                    if a[0] == "express":  # applied between two cycles, with its own exchange
                        r.cycle.express(r.clock.ns + 300_000)
                tick()
            else:
                for r in (fast, full):
                    {"fault": lambda: r.bus.inject_fault(a[1], a[2]), "unplug": lambda: r.bus.unplug(a[1]),
                     "plug": lambda: r.bus.plug(a[1]), "wkc": lambda: r.bus.set_wkc_fault(a[1], a[2])}[a[0]]()
                tick()
        ra, rb = fast.cycle.recorder, full.cycle.recorder
        assert ra is not None and rb is not None and ra.written == rb.written
        assert ra._drv == rb._drv and ra._cyc == rb._cyc
        assert full.cycle.drives_stepped == cycles * N
        assert fast.cycle.drives_stepped < full.cycle.drives_stepped  # the last 300 cycles at least are at rest
    finally:
        for r in (fast, full):
            r.cycle.stop(ordered=False)


def test_drives_at_rest_are_not_stepped_and_a_change_or_command_steps_them():
    r = Rig(N, motion=MOTION)
    try:
        r.tick(5)
        r.enable()
        r.tick(20)
        before = r.cycle.drives_stepped
        r.tick(100)
        assert r.cycle.drives_stepped == before  # all three at rest: nothing stepped
        r.bus.inject_fault(1, 0x2310)
        r.tick(1)
        assert r.cycle.drives_stepped == before + 1  # the faulted drive's inputs changed: stepped
        assert r.status("axis1").state in ("fault_reaction_active", "fault")
        got = r.send("halt", "axis0", {"on": True})
        r.tick(1)
        assert got and got[0].outcome == "done"
        r.tick(50)
        still = r.cycle.drives_stepped
        r.tick(10)
        assert r.cycle.drives_stepped == still
        moved = r.send("move", "axis2", {"to": 10_000})
        r.run_until(lambda: bool(moved))
        assert moved[0].outcome == "done" and r.status("axis2").position == 10_000
        assert r.status("axis0").halt and r.status("axis1").state == "fault"
    finally:
        r.cycle.stop(ordered=False)
