"""What the cycle publishes of its drives: one immutable :class:`DriveSnapshot` each.

:class:`Snapshots` (cycle thread only) builds the drives' part of each ``CycleSnapshot``. A drive
whose published values did not change keeps its immutable :class:`DriveSnapshot`, and the drives
the fast path skipped are not looked at (docs/agent-cycle.md, "Fast paths").
"""

from __future__ import annotations

from typing import Sequence

from bus_agent.bus.base import ALState
from bus_agent.cycle.drive import Drive, Segment
from bus_agent.cycle.motion import following_error
from bus_agent.runtime import DriveSnapshot

#: The actual values of a lost drive: not published as current (they read 0 and mean nothing).
LOST_ABSENT = ("position", "velocity", "torque")


class Snapshots:
    """The drive snapshots of the last cycle, rebuilt only for the drives whose values changed."""

    def __init__(self, seg: Segment, error_texts: dict[int, tuple[int, str]]) -> None:
        self._seg = seg
        self._error_texts = error_texts  # the bus's last emergency text per slave
        self._drive_snaps: tuple[DriveSnapshot, ...] = ()
        self._snap_list: list[DriveSnapshot | None] = []   # each drive's snapshot, by Drive.index

    def drive_snapshots(self, work: Sequence[Drive] | None = None) -> tuple[DriveSnapshot, ...]:
        """Every drive's snapshot. A drive whose published values did not change since the last
        cycle keeps its DriveSnapshot (the same immutable object), and when no drive changed the
        tuple of the last cycle is returned as it was: building 26-field records for drives at rest
        was the largest share of the cycle's CPU per drive. Only the drives stepped this cycle
        (``work``; None: all) are looked at: the others' values are those of the last cycle.
        Cycle thread only."""
        changed = False
        texts = self._error_texts
        drives = self._seg.drives
        snaps = self._snap_list
        if len(snaps) != len(drives):
            snaps = self._snap_list = [d.snapshot for d in drives]
        for d in drives if work is None else work:
            i = d.inputs
            c = d.ctrl
            m = d.motion
            key = (d.state, i.statusword, d.controlword, c.goal, c.halt, c.mode, i.modes_of_operation_display,
                   i.position_actual, i.velocity_actual, i.torque_actual, i.error_code,
                   texts.get(d.slave) if i.error_code else None, d.al, d.lost, d.absent, d.object_names, i.extra,
                   d.dc, m.axis_state, m.homed, d.out.target_position, m.request_id, d.stage.clamps,
                   d.lost_reason if d.lost else "")
            if d.lost:
                if d.snapshot is None or key != d.snapshot_key:
                    d.snapshot = self._lost_snapshot(d)
                    d.snapshot_key = key
                    snaps[d.index] = d.snapshot
                    changed = True
                continue
            if d.snapshot is None or key != d.snapshot_key:
                # positional, in DriveSnapshot's field order (26 keywords cost 2.7 x the call;
                # tests/unit/test_fast_paths.py pins the order)
                d.snapshot = DriveSnapshot(
                    d.axis, d.slave, d.state.value, i.statusword,                      # axis slave state statusword
                    d.controlword, c.goal.value, c.halt, c.mode,                       # controlword goal halt mode
                    i.modes_of_operation_display, i.position_actual,                  # mode_display position
                    i.velocity_actual, i.torque_actual, i.error_code,                  # velocity torque error_code
                    self._error_text(d.slave, i.error_code),                           # error_text
                    d.al.state.wire_name if d.al.state in ALState else "none", d.lost,  # al_state lost
                    d.absent, d.object_names, i.extra, d.dc,                           # absent object_names objects dc
                    m.axis_state.value, m.homed, d.out.target_position,                # axis_state homed target_position
                    following_error(d), m.request_id, d.stage.clamps)                 # following_error motion_request_id target_clamps
                d.snapshot_key = key
                snaps[d.index] = d.snapshot
                changed = True
        last = self._drive_snaps
        if changed or len(last) != len(snaps):
            last = self._drive_snaps = tuple(snaps)  # type: ignore[arg-type]
        return last

    def _lost_snapshot(self, d: Drive) -> DriveSnapshot:
        """A lost drive's snapshot: its state is ``unknown`` and its last known state goes in
        ``last_known_state``; the inputs of its slave are old, so none is published as current
        (statusword, mode display, error code and mapped objects 0 or empty, the actual values
        reported ``absent``); ``error_text`` says why it was lost."""
        c = d.ctrl
        m = d.motion
        return DriveSnapshot(
            d.axis, d.slave, "unknown", 0, d.controlword, c.goal.value, c.halt, c.mode, 0, 0, 0, 0, 0,
            d.lost_reason, d.al.state.wire_name if d.al.state in ALState else "none", True,
            LOST_ABSENT, (), (), d.dc, m.axis_state.value, m.homed, d.out.target_position, 0, m.request_id,
            d.stage.clamps, d.state.value)

    def _error_text(self, slave: int, error_code: int) -> str:
        """The text of the bus's last emergency of ``slave`` when it is about this error code."""
        t = self._error_texts.get(slave) if error_code else None
        return t[1] if t is not None and t[0] == error_code else ""
