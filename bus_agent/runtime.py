"""The boundary between the cycle (EtherCAT side) and the gateway (Zenoh side).

Commands cross *in* through the cycle's bounded inbox, already validated, and are applied at a
cycle start; every addressed axis later gets exactly one terminal :class:`Outcome` through the
command's ``on_outcome`` callback, called from the cycle thread (it must only enqueue).
State crosses *out* as one immutable :class:`CycleSnapshot` per cycle. The cycle never calls
Zenoh, msgpack or blocking logs; the gateway never touches the bus or the controllers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping


@dataclass(frozen=True)
class Outcome:
    """Terminal answer for one axis (or for the agent when ``axis`` is '')."""

    axis: str
    outcome: str  # schemas.messages.OUTCOMES: done, failed, timeout, rejected, busy, aborted
    state: str = "unknown"  # schemas.messages.DRIVE_STATES
    error_code: int = 0
    reason: str = ""
    elapsed_s: float = 0.0
    cycles: int = 0
    duration_s: float = 0.0  # motion: the planned profile duration (move prepare: the minimum)


@dataclass(frozen=True)
class DriveCommand:
    """A validated drive command for axes of this host (ops: schemas.messages.DRIVE_OPS minus
    lease/release, which the gateway handles itself)."""

    request_id: str
    op: str
    axes: tuple[str, ...]
    args: Mapping[str, Any] = field(default_factory=dict)
    timeout_s: float = 5.0
    supervisor: str = ""
    received_ns: int = 0  # time.monotonic_ns() at receipt
    on_outcome: Callable[[Outcome], None] = lambda outcome: None


@dataclass(frozen=True)
class AgentCommand:
    """A validated agent command (op 'nmt', args {'command': ..., 'axis': optional})."""

    request_id: str
    op: str
    args: Mapping[str, Any] = field(default_factory=dict)
    timeout_s: float = 5.0
    supervisor: str = ""
    received_ns: int = 0
    on_outcome: Callable[[Outcome], None] = lambda outcome: None


@dataclass(frozen=True)
class DriveSnapshot:
    axis: str
    slave: int
    state: str
    statusword: int
    controlword: int
    goal: str
    halt: bool
    mode: int
    mode_display: int
    position: int
    velocity: int
    torque: int
    error_code: int
    error_text: str
    al_state: str
    lost: bool
    #: Actual values (position, velocity, torque) the drive does not map: their fields read 0.
    absent: tuple[str, ...] = ()
    #: Other mapped input objects: names (CiA 402 table, else '0xIIII:SS') and their values.
    object_names: tuple[str, ...] = ()
    objects: tuple[int, ...] = ()
    #: DC state of the drive's slave: "sync0" (SYNC0 running), "off" (DC capable, not used), "none".
    dc: str = "none"
    # motion layer (bus_agent.motion): PLCopen axis state, homed, 0x607A written, following error
    axis_state: str = "disabled"
    homed: bool = False
    target_position: int = 0
    following_error: int = 0
    motion_request_id: str = ""
    #: Cycles in which the output stage limited a target (bus_agent.motion.output_stage).
    target_clamps: int = 0
    #: A lost drive (``state`` "unknown"): the state it was in when it was lost; '' otherwise.
    last_known_state: str = ""


@dataclass(frozen=True)
class CycleEvent:
    """Something worth an Event message (kinds: schemas.messages.EVENT_KINDS)."""

    axis: str
    kind: str
    detail: str = ""
    from_state: str = "unknown"
    to_state: str = "unknown"
    error_code: int = 0
    request_id: str = ""
    requester: str = ""  # who sent the command (kind "command")


@dataclass(frozen=True)
class CycleStats:
    cycles: int = 0
    cycle_us: int = 1000
    period_p50_us: float = 0.0
    period_p99_us: float = 0.0
    period_max_us: float = 0.0
    overruns: int = 0
    wkc_errors: int = 0
    expected_wkc: int = 0
    dc_offset_p50_us: float = 0.0  # frame-to-SYNC0 phase (DC), over the statistics window
    dc_offset_p99_us: float = 0.0


@dataclass(frozen=True)
class CycleSnapshot:
    cycle: int
    time_ns: int  # wall clock
    drives: tuple[DriveSnapshot, ...]
    events: tuple[CycleEvent, ...]
    stats: CycleStats
    agent_state: str = "running"  # schemas.messages.AGENT_STATES
