"""A cycle on SimBus with an injected clock, for motion tests (no root, no threads): commands in,
ticks, and the targets each simulated drive actually received (0x607A / 0x60FF read back from the
drive model after every exchange)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from bus_agent.bus.sim_bus import SimBus
from bus_agent.config import AgentConfig, DriveConfig
from bus_agent.cycle.cycle import Cycle
from bus_agent.motion.config import MotionConfig
from bus_agent.runtime import DriveCommand, Outcome

PERIOD_NS = 1_000_000


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


@dataclass
class Wire:
    """Per drive: (time_s, 0x607A, 0x60FF, 0x6064, state, 0x6040) as the drive saw them, every cycle."""

    rows: list[tuple[float, int, int, int, str, int]] = field(default_factory=list)

    @property
    def targets(self) -> list[int]:
        return [r[1] for r in self.rows]


class Rig:
    def __init__(self, n: int = 1, motion: MotionConfig | None = None, mode: int = 8, profile: Any = "generic",
                 **cfg: Any) -> None:
        self.clock = Clock()
        self.bus = SimBus(n, profile, clock=lambda: self.clock.ns / 1e9)
        motion = motion or MotionConfig()
        drives = tuple(DriveConfig(slave=i, mode=mode, motion=motion) for i in range(n))
        self.cycle = Cycle(self.bus, AgentConfig(host="h1", sim_drives=n, drives=drives, **cfg),
                           clock_ns=self.clock, wall_ns=lambda: self.clock.ns, manage_gc=False,
                           switch_interval_s=None)
        self.cycle.open()
        self.wire = [Wire() for _ in range(n)]
        self.axes = tuple(f"axis{i}" for i in range(n))
        self._seq = 0

    def model(self, i: int):
        return self.bus._slaves[i].model

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.clock.ns += PERIOD_NS
            self.cycle.tick()
            for i, w in enumerate(self.wire):
                m = self.model(i)
                w.rows.append((self.clock.ns / 1e9, int(m.read(0x607A, 0)), int(m.read(0x60FF, 0)),
                               int(m.read(0x6064, 0)), m.state.value, int(m.read(0x6040, 0))))

    def send(self, op: str, axes: tuple[str, ...] | str | None = None, args: dict | None = None,
             timeout_s: float = 5.0) -> list[Outcome]:
        """Submit a command (applied at the next tick); returns the list its outcomes arrive in."""
        got: list[Outcome] = []
        self._seq += 1
        axes = (axes,) if isinstance(axes, str) else (axes or self.axes)
        assert self.cycle.submit(DriveCommand(request_id=f"r{self._seq}-{op}", op=op, axes=axes, args=args or {},
                                              timeout_s=timeout_s, received_ns=self.clock.ns, on_outcome=got.append))
        return got

    def run_until(self, pred: Callable[[], bool], max_cycles: int = 20_000) -> int:
        for k in range(max_cycles):
            if pred():
                return k
            self.tick()
        raise AssertionError(f"condition not met within {max_cycles} cycles")

    def enable(self, axes: tuple[str, ...] | None = None) -> None:
        got = self.send("enable", axes)
        self.run_until(lambda: len(got) == len(axes or self.axes))
        assert all(o.outcome == "done" for o in got), got

    def do(self, op: str, axes: tuple[str, ...] | str | None = None, args: dict | None = None,
           timeout_s: float = 5.0, max_cycles: int = 20_000) -> list[Outcome]:
        """Send and tick until every addressed axis answered."""
        got = self.send(op, axes, args, timeout_s)
        n = 1 if isinstance(axes, str) else len(axes or self.axes)
        self.run_until(lambda: len(got) >= n, max_cycles)
        return got

    def status(self, axis: str = "axis0"):
        snap = self.cycle.latest
        assert snap is not None
        return next(d for d in snap.drives if d.axis == axis)
