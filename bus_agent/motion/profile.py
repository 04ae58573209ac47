"""Drive-generated profiles: the Profile Position set-point handshake (mode 1) and Profile
Velocity jogs (mode 3). Functional core: no clock, no I/O; the axis (bus_agent.motion.axis)
steps one :class:`ProfileRun` per cycle with fresh inputs.

Profile Position (CiA 402 / IEC 61800-7-201): 0x6081 profile velocity, 0x6083 acceleration and
0x6084 deceleration are written by SDO first (only when they change); then the set-point
handshake, acting on the edges of the acknowledge and never assuming it starts at 0:

1. bit 4 (new set-point) low until statusword bit 12 (set-point acknowledge) is low;
2. 0x607A and bit 4 rise in the same cycle, with bit 5 (change set immediately: a new move
   replaces the running one at once);
3. bit 12 rises (the drive took the set-point): bit 4 falls;
4. done when bit 10 (target reached) is set with the position in the axis's window and the
   velocity at rest; bit 13 (following error) fails the move.

Absolute targets only: a relative move (``by``) is turned into an absolute 0x607A from the
position being commanded, because what bit 6 (relative) is relative to differs between drives
(0x60F2 positioning option code). An aborted move gets a stop set-point: the position where
the drive comes to rest with 0x6084 from its current velocity, handed over with the same
handshake (the drive decelerates on its own profile, and no old target is left to resume).

Profile Velocity: 0x60FF is the jog velocity until the jog ends (``for_s``, a software limit
ahead, an abort), then 0; the drive ramps with 0x6083/0x6084.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

__all__ = ["MODE_PP", "MODE_PV", "ProfileRun", "ProfileStep", "profile_sdo_writes", "stop_position",
           "CW_NEW_SETPOINT", "CW_CHANGE_IMMEDIATELY", "SW_TARGET_REACHED", "SW_SETPOINT_ACK", "SW_FOLLOWING_ERROR"]

MODE_PP = 1
MODE_PV = 3
CW_NEW_SETPOINT = 0x0010        # controlword bit 4
CW_CHANGE_IMMEDIATELY = 0x0020  # controlword bit 5
SW_TARGET_REACHED = 1 << 10
SW_SETPOINT_ACK = 1 << 12
SW_FOLLOWING_ERROR = 1 << 13


def _u32(x: float) -> bytes:
    return struct.pack("<I", max(1, min(int(round(x)), 0xFFFFFFFF)))


def profile_sdo_writes(velocity: float, accel: float, decel: float) -> tuple[tuple[int, int, bytes], ...]:
    """0x6081 profile velocity, 0x6083 profile acceleration, 0x6084 profile deceleration (u32)."""
    return ((0x6081, 0, _u32(velocity)), (0x6083, 0, _u32(accel)), (0x6084, 0, _u32(decel)))


def stop_position(position: float, velocity: float, decel: float) -> float:
    """Where an axis at ``velocity`` comes to rest decelerating at ``decel`` (no jerk limit)."""
    if decel <= 0:
        return position
    return position + math.copysign(velocity * velocity / (2.0 * decel), velocity)


@dataclass(frozen=True)
class ProfileStep:
    """What the cycle writes this cycle for a drive-generated profile."""

    controlword_bits: int = 0
    outcome: str = ""   # the run's command ended: done | failed | timeout (once)
    reason: str = ""


class ProfileRun:
    """One PP move (``kind`` "pp", ``target`` in counts) or PV jog ("pv", ``velocity`` counts/s).

    ``replies``: the run answers a command (False for a stop set-point after an abort).
    Phases: ``params`` (SDO writes under way) -> PP: ``wait_ack_low`` -> ``ack`` -> ``moving``;
    PV: ``running`` -> ``stopping``; then ``finished``."""

    def __init__(self, kind: str, *, target: float = 0.0, velocity: float = 0.0, now_s: float, deadline_s: float,
                 end_s: float = math.inf, sdo_writes: tuple[tuple[int, int, bytes], ...] = (),
                 position_window: float, velocity_window: float, replies: bool = True, note: str = "") -> None:
        self.kind = kind
        self.target = target
        self.velocity = velocity
        self.deadline_s = deadline_s
        self.end_s = end_s
        self.sdo_writes = sdo_writes
        self.position_window = position_window
        self.velocity_window = velocity_window
        self.replies = replies
        self.note = note
        self.phase = "params" if sdo_writes else ("wait_ack_low" if kind == "pp" else "running")
        self.started_s = now_s
        self.limit_stop = ""      # PV: the software limit it stopped at
        self._took_at_s = 0.0

    @property
    def target_velocity(self) -> int:
        """0x60FF to write (PV)."""
        return int(round(self.velocity)) if self.kind == "pv" and self.phase in ("params", "running") else 0

    def sdo_done(self, error: str) -> str:
        """The profile parameters were written (``error``: why not). Returns the failure, if any."""
        if self.phase != "params":
            return ""
        if error:
            self.phase = "finished"
            return f"profile parameters refused: {error}"
        self.phase = "wait_ack_low" if self.kind == "pp" else "running"
        return ""

    def stop_jog(self, why: str = "") -> None:
        """PV: 0x60FF to 0 now (``why``: the software limit it stops at)."""
        if self.kind == "pv" and self.phase in ("params", "running"):
            self.phase = "stopping"
            self.limit_stop = why

    def step(self, now_s: float, statusword: int, position: int, velocity: int) -> ProfileStep:
        """One cycle with fresh inputs. Cycle-safe."""
        if self.kind == "pv":
            return self._step_pv(now_s, velocity)
        ack = bool(statusword & SW_SETPOINT_ACK)
        p = self.phase
        if p in ("params", "finished"):
            return ProfileStep()
        if p == "wait_ack_low":
            if ack:  # never assume it starts at 0: an acknowledge still high from before
                if now_s >= self.deadline_s:
                    return self._end("timeout", f"set-point acknowledge (statusword bit 12) stuck high: "
                                     f"the set-point {self.target:.0f} was not sent")
                return ProfileStep()
            self.phase = "ack"  # 0x607A and bit 4 rise together (the cycle writes the target now)
            return ProfileStep(CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY)
        if p == "ack":
            if ack:  # the rising edge: the drive took the set-point
                self.phase = "moving"
                self._took_at_s = now_s
                return ProfileStep()
            if now_s >= self.deadline_s:
                return self._end("timeout", f"set-point {self.target:.0f} not acknowledged (statusword bit 12)")
            return ProfileStep(CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY)
        # moving
        if statusword & SW_FOLLOWING_ERROR:
            return self._end("failed", f"following error (statusword bit 13 = 1, 0x6041 = 0x{statusword:04X})")
        in_window = abs(position - self.target) <= self.position_window and abs(velocity) <= self.velocity_window
        if statusword & SW_TARGET_REACHED and in_window:
            return self._end("done", self.note)
        if now_s >= self.deadline_s:
            return self._end("timeout", f"not in position within the timeout ({self.target:.0f} counts)")
        return ProfileStep()

    def _step_pv(self, now_s: float, velocity: int) -> ProfileStep:
        if self.phase == "running" and now_s >= self.end_s:
            self.phase = "stopping"
        if self.phase == "stopping" and abs(velocity) <= self.velocity_window:
            if self.limit_stop:
                return self._end("aborted", f"stopped at the software limit {self.limit_stop}")
            return self._end("done", "jog ended" + (f"; {self.note}" if self.note else ""))
        if self.phase == "stopping" and now_s >= self.deadline_s + 1.0:
            return self._end("timeout", "not at rest after the jog")
        return ProfileStep()

    def _end(self, outcome: str, reason: str) -> ProfileStep:
        self.phase = "finished"
        return ProfileStep(0, outcome, reason)
