"""What one cycle steps and what it publishes: the drives at rest skipped, the drive snapshots,
the statistics.

A mixin of :class:`bus_agent.cycle.cycle.Cycle` (cycle thread only). The fast path steps only the
drives whose inputs changed and those not at rest (docs/agent-cycle.md, "Fast paths"); a drive
whose published values did not change keeps its immutable :class:`DriveSnapshot`.
"""

from __future__ import annotations

from typing import Sequence

from bus_agent.bus.base import ALState
from bus_agent.cia402.states import State
from bus_agent.cycle.base import STATS_WINDOW, CycleBase
from bus_agent.cycle.drive import Drive
from bus_agent.cycle.motion import following_error
from bus_agent.runtime import CycleStats, DriveSnapshot

#: The actual values of a lost drive: not published as current (they read 0 and mean nothing).
LOST_ABSENT = ("position", "velocity", "torque")


class OutputMixin(CycleBase):
    """The fast path's choice of drives, the snapshots and the statistics of the :class:`Cycle`."""

    def _work(self, changed: Sequence[int]) -> Sequence[Drive]:
        """The drives to step in a cycle without commands, reflexes or management reports: those
        whose inputs changed (``changed``: slave positions) and those not at rest, in
        configuration order. Cycle thread only."""
        busy = self._busy
        if not changed:
            if not busy:
                return ()
            idx = busy
        else:
            idx = set(busy)
            of_slave = self._drives_of_slave
            for pos in changed:
                idx.update(of_slave.get(pos, ()))
        drives = self.drives
        return [drives[k] for k in sorted(idx)]

    def _at_rest(self, d: Drive, targets_before: tuple[int, int, int]) -> bool:
        """True when a full step of ``d`` (just made, without controller events, its motion idle
        before it) would repeat itself exactly while its inputs do not change and no command,
        reflex or report reaches it: the cycle may then skip it. The controller settled (its
        output depends on the two inputs only), the motion is idle (:attr:`AxisMotion.idle`), the
        targets did not move (the motion observes them), the output stage wrote them as given (a
        limited target still catches up), no command pending, no automatic fault reset running
        (its backoff reads the clock), no emergency text that may change. Cycle thread only."""
        if d.pending is not None or not d.ctrl.settled or not d.motion.idle or not d.stage.settled:
            return False
        if (d.target_position, d.target_velocity, d.target_torque) != targets_before:
            return False
        if d.cfg.policy.auto_reset.enabled and (d.state is State.FAULT or d.auto_attempts):
            return False
        return not (d.inputs.error_code and self._error_texts)

    def _drive_snapshots(self, work: Sequence[Drive] | None = None) -> tuple[DriveSnapshot, ...]:
        """Every drive's snapshot. A drive whose published values did not change since the last
        cycle keeps its DriveSnapshot (the same immutable object), and when no drive changed the
        tuple of the last cycle is returned as it was: building 26-field records for drives at rest
        was the largest share of the cycle's CPU per drive. Only the drives stepped this cycle
        (``work``; None: all) are looked at: the others' values are those of the last cycle.
        Cycle thread only."""
        changed = False
        texts = self._error_texts
        snaps = self._snap_list
        if len(snaps) != len(self.drives):
            snaps = self._snap_list = [d.snapshot for d in self.drives]
        for d in self.drives if work is None else work:
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

    def _update_stats(self) -> None:
        ps = sorted(self._periods)
        n = len(ps)
        self._stats = CycleStats(
            cycles=self.cycles, cycle_us=self.config.cycle_us,
            period_p50_us=ps[n // 2] / 1000, period_p99_us=ps[min(n - 1, (n * 99) // 100)] / 1000,
            period_max_us=self._period_max_ns / 1000, overruns=self.overruns, wkc_errors=self.wkc_errors,
            expected_wkc=self.bus.expected_wkc, **self._dc_stats())

    def _dc_stats(self) -> dict[str, float]:
        if self._dc is None:
            return {}
        offs = sorted(self._dc_offsets[:min(self.cycles, STATS_WINDOW)] or [0])
        n = len(offs)
        return {"dc_offset_p50_us": offs[n // 2] / 1000, "dc_offset_p99_us": offs[min(n - 1, (n * 99) // 100)] / 1000}
