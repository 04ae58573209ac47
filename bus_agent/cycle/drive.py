"""The cycle's per-drive and per-command records, the segment record, and the state sets the cycle's parts share.

Plain mutable records owned by the cycle thread (:class:`bus_agent.cycle.cycle.Cycle`); nothing
here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from bus_agent.bus.base import ALState, SlaveALStatus, SlaveInfo
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.cia402.controller import DriveController, Goal
from bus_agent.cia402.states import Mode, State
from bus_agent.config import DriveConfig
from bus_agent.cycle.groups import Groups
from bus_agent.motion.axis import AxisMotion
from bus_agent.motion.output_stage import OutputStage
from bus_agent.runtime import AgentCommand, DriveCommand, DriveSnapshot

#: Goals that move a drive towards torque; withdrawn when nobody waits for them any more.
UPWARD_GOALS = (Goal.READY, Goal.SWITCHED_ON, Goal.ENABLED)
FAULT_STATES = (State.FAULT, State.FAULT_REACTION_ACTIVE)
#: States in which a drive counts as down for the ordered shutdown.
DOWN_STATES = (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT)
#: Power stage on (CiA 402: high voltage applied from Switched on; torque in the rest): while a
#: drive is in one of these, the period's jitter matters and the cycle spins before its deadlines.
ARMED_STATES = frozenset((State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE,
                          State.FAULT_REACTION_ACTIVE))
VALID_MODES = frozenset(int(m) for m in Mode)
MODE_UNWRITTEN = -129  # no i8: the first cycle writes 0x6060 by SDO
CSX_MODES = (int(Mode.CYCLIC_SYNC_POSITION), int(Mode.CYCLIC_SYNC_VELOCITY), int(Mode.CYCLIC_SYNC_TORQUE))


@dataclass(slots=True)
class Pending:
    """A drive command waiting for its terminal outcome (one per axis)."""

    cmd: DriveCommand
    kind: str                 # "goal" | "mode" | "fault_reset"
    start_cycle: int
    start_ns: int
    deadline_ns: int


@dataclass(slots=True)
class Drive:
    """One configured axis as the cycle sees it: controller, motion, process data, bookkeeping."""

    cfg: DriveConfig
    axis: str
    slave: int
    ctrl: DriveController
    motion: AxisMotion
    index: int = 0                      # position in Cycle.drives (and the recorder's axes)
    out: DriveOutputs = field(default_factory=DriveOutputs)
    inputs: DriveInputs = field(default_factory=DriveInputs)
    state: State = State.UNKNOWN
    controlword: int = 0
    lost: bool = False
    lost_reason: str = ""               # why it was lost (the status's error_text while lost)
    al: SlaveALStatus = SlaveALStatus(ALState.NONE, False, 0)
    pending: Pending | None = None
    target_position: int = 0
    target_velocity: int = 0
    target_torque: int = 0
    # auto reset bookkeeping
    fault_since_ns: int = 0
    last_fault_ns: int = 0
    auto_attempts: int = 0
    auto_exhausted: bool = False
    # objects the drive does not map (see docs/agent-cycle.md, "Real drives")
    absent: tuple[str, ...] = ()        # actual values not mapped: reported absent
    object_names: tuple[str, ...] = ()  # other mapped input objects
    sdo_mode: bool = False              # 0x6060 not in the RxPDO: written by SDO
    sdo_mode_display: bool = False      # 0x6061 not in the TxPDO: read by SDO
    sdo_error_code: bool = False        # 0x603F not in the TxPDO: read by SDO on a fault
    mode_written: int = 0
    mode_display_sdo: int = 0
    error_code_sdo: int = 0             # 0x603F not mapped: the error code read by SDO, or the last EMCY's
    error_code_readable: bool = True    # False once an SDO read of 0x603F was refused: EMCY only
    last_emcy_code: int = 0             # the last emergency's error code (0 after an error reset EMCY)
    dc: str = "none"                    # DC state of the slave (bus dc_states)
    # the last published snapshot and the values it was built from (Snapshots.drive_snapshots)
    snapshot: DriveSnapshot | None = None
    snapshot_key: tuple = ()
    #: The axis limits on the targets written to the wire (``out``); built from ``motion``.
    stage: OutputStage = field(init=False)

    def __post_init__(self) -> None:
        lim = self.motion.limits
        self.stage = OutputStage(lim.velocity, lim.acceleration, self.motion.lead_s)


@dataclass(slots=True)
class NmtRun:
    """An NMT agent command in progress (docs/cia402.md section 5)."""

    cmd: AgentCommand
    command: str
    slaves: tuple[int, ...]
    phase: str                # "bring_down" | "to_init" | "to_target" | "recover"
    start_cycle: int
    start_ns: int
    deadline_ns: int
    down_deadline_ns: int
    note: str = ""
    ticket: int = 0           # AL status must be read after this management request


class Segment:
    """What the cycle knows of its segment once open: the slaves, the configured drives (in
    configuration order: ``Drive.index``), the drives by axis and the groups. One record per
    cycle, given to the parts that look drives up; filled in place by ``Cycle.open``."""

    __slots__ = ("host", "slaves", "drives", "by_axis", "groups")

    def __init__(self, host: str, groups: Groups) -> None:
        self.host = host
        self.slaves: list[SlaveInfo] = []
        self.drives: list[Drive] = []
        self.by_axis: dict[str, Drive] = {}
        self.groups = groups

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(d.axis for d in self.drives)
