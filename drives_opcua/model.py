"""What drives-opcua shows and offers, as data: pure, no asyncua server, no Zenoh.

- :data:`DRIVE_VARIABLES` / :data:`HOST_VARIABLES`: the variables of ``Objects/Drives/<host>/<axis>``
  and ``Objects/Drives/<host>``, each with its OPC UA type and where its value comes from (the
  contract's ``drive_status`` and ``agent_status``);
- :data:`METHODS`: the methods of a drive, the contract op each sends, and their arguments;
- :func:`may_call`: the project's role table (``bus_agent.security.roles``) applied to an op;
- :func:`check_arguments`: a method call's arguments checked before anything is sent;
- :func:`drive_alarms`: the OPC UA events a status change raises (faults, lost drives);
- :func:`outcome`: a Fleet result as the method's (outcome, error text).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

from asyncua import ua

from bus_agent.security.roles import ROLE_DRIVE_OPS
from schemas.messages import OP_ARGS, AgentStatus, DriveStatus
from supervisor.results import CommandResult, Report

#: The namespace of every node drives-opcua adds.
NAMESPACE_URI = "urn:zenoh-drives"
#: The folder under Objects holding one object per host.
ROOT_FOLDER = "Drives"

V = ua.VariantType

#: ``Objects/Drives/<host>/<axis>`` variables: browse name -> (type, value from a drive_status).
DRIVE_VARIABLES: dict[str, tuple[ua.VariantType, Callable[[DriveStatus], Any]]] = {
    "State": (V.String, lambda s: s.state),
    "Goal": (V.String, lambda s: s.goal),
    "Statusword": (V.UInt16, lambda s: s.statusword),
    "Position": (V.Int32, lambda s: s.position),
    "Velocity": (V.Int32, lambda s: s.velocity),
    "Torque": (V.Int16, lambda s: s.torque),
    "ErrorCode": (V.UInt16, lambda s: s.error_code),
    "ErrorText": (V.String, lambda s: s.error_text),
    "Lost": (V.Boolean, lambda s: s.lost),
    "AlState": (V.String, lambda s: s.al_state),
    "AxisState": (V.String, lambda s: s.axis_state),
    "Homed": (V.Boolean, lambda s: s.homed),
    "LeaseHolder": (V.String, lambda s: s.lease_holder),
}
#: The value a drive's variable holds before any status came (an expected drive never seen).
DRIVE_INITIAL: dict[str, Any] = {"State": "unknown", "Goal": "disabled", "Statusword": 0, "Position": 0,
                                 "Velocity": 0, "Torque": 0, "ErrorCode": 0, "ErrorText": "", "Lost": False,
                                 "AlState": "none", "AxisState": "disabled", "Homed": False, "LeaseHolder": ""}

#: Agent state shown for a host whose agent is not alive (expected by --fleet, or gone).
OFFLINE = "offline"


@dataclass(frozen=True)
class HostView:
    """What ``Objects/Drives/<host>`` shows: the agent's liveliness and its last status."""

    alive: bool
    status: AgentStatus | None


#: ``Objects/Drives/<host>`` variables: browse name -> (type, value from a :class:`HostView`).
HOST_VARIABLES: dict[str, tuple[ua.VariantType, Callable[[HostView], Any]]] = {
    "AgentState": (V.String, lambda h: (h.status.state if h.status else "starting") if h.alive else OFFLINE),
    "Alive": (V.Boolean, lambda h: h.alive),
    "CycleP50us": (V.Double, lambda h: float(h.status.period_p50_us) if h.status else 0.0),
    "CycleP99us": (V.Double, lambda h: float(h.status.period_p99_us) if h.status else 0.0),
    "CycleMaxus": (V.Double, lambda h: float(h.status.period_max_us) if h.status else 0.0),
    "Overruns": (V.UInt64, lambda h: h.status.overruns if h.status else 0),
    "WkcErrors": (V.UInt64, lambda h: h.status.wkc_errors if h.status else 0),
}


def drive_values(st: DriveStatus) -> tuple[Any, ...]:
    """The drive's variable values in :data:`DRIVE_VARIABLES` order (compared to skip writes)."""
    return tuple(get(st) for _, get in DRIVE_VARIABLES.values())


def host_values(view: HostView) -> tuple[Any, ...]:
    return tuple(get(view) for _, get in HOST_VARIABLES.values())


# ---- methods --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Argument:
    """One input argument of a method: its name, OPC UA type and accepted range."""

    name: str
    type: ua.VariantType
    low: float
    high: float
    description: str
    key: str  # the command argument it becomes (schemas.messages.OP_ARGS)


@dataclass(frozen=True)
class Method:
    """A drive method: the contract op it sends and its input arguments."""

    op: str
    description: str
    arguments: tuple[Argument, ...] = ()
    fixed: tuple[tuple[str, Any], ...] = ()  # command arguments always sent
    two_phase: bool = False  # sent as Fleet.enable (two-phase orchestration), not one command
    timeout_s: float = 5.0

    def command_args(self, values: Sequence[float]) -> dict[str, Any]:
        """The command's arguments from the checked argument values."""
        return {**dict(self.fixed), **{a.key: v for a, v in zip(self.arguments, values)}}


#: The contract's ``move`` arguments: the ranges a method argument is checked against.
_MOVE = OP_ARGS["move"]

#: Drive methods (browse name -> op). Each returns ``Outcome`` (a contract outcome, ``missing``,
#: ``denied``, or ``rejected`` for what was never sent) and ``ErrorText``.
METHODS: dict[str, Method] = {
    "Enable": Method("enable", "two-phase enable to Operation enabled (as drivectl enable)", two_phase=True),
    "Disable": Method("disable", "to Switch on disabled"),
    "Shutdown": Method("shutdown", "CiA 402 Shutdown: to Ready to switch on"),
    "QuickStop": Method("quick_stop", "quick stop (transition 11)"),
    "Halt": Method("halt", "halt on (controlword bit 8)", fixed=(("on", True),)),
    "FaultReset": Method("fault_reset", "fault reset (transition 15)"),
    "Stop": Method("stop", "PLCopen MC_Stop: decelerate and refuse motion until released"),
    "MoveAbsolute": Method("move", "move to Position at Velocity (the axis's units), done in the window at rest", (
        Argument("Position", V.Double, _MOVE["to"].meta["range"][0], _MOVE["to"].meta["range"][1],
                 "target position, in the axis's unit", "to"),
        Argument("Velocity", V.Double, 1e-9, _MOVE["velocity"].meta["range"][1], "velocity, in the axis's unit per "
                 "second (> 0; above the axis limit: clamped or rejected by the axis)", "velocity"),
    ), timeout_s=60.0),
}
#: The two outputs of every method.
OUTPUTS = (("Outcome", "terminal outcome for this drive"), ("ErrorText", "why, when not done"))


def may_call(roles: Iterable[str], op: str) -> bool:
    """Whether a user with ``roles`` may send ``op`` (the project's role table, as the ACL)."""
    return any(op in ROLE_DRIVE_OPS.get(r, ()) for r in roles)


def roles_for(op: str) -> list[str]:
    return [r for r, ops in ROLE_DRIVE_OPS.items() if op in ops]


class ArgumentProblem(ValueError):
    """A method argument that is not accepted: which one (index), the status and the message."""

    def __init__(self, index: int, status: int, message: str) -> None:
        super().__init__(message)
        self.index = index
        self.status = status


_PYTYPES = {V.Double: (int, float), V.Float: (int, float)}


def check_arguments(method: Method, args: Sequence[ua.Variant | Any]) -> list[float]:
    """The method's argument values, checked for count, type and range; raise
    :class:`ArgumentProblem` (nothing is sent then)."""
    if len(args) < len(method.arguments):
        missing = ", ".join(a.name for a in method.arguments[len(args):])
        raise ArgumentProblem(len(args), ua.StatusCodes.BadArgumentsMissing, f"missing argument(s): {missing}")
    if len(args) > len(method.arguments):
        raise ArgumentProblem(len(method.arguments), ua.StatusCodes.BadTooManyArguments,
                              f"{len(args)} arguments given, {len(method.arguments)} expected")
    out = []
    for i, (spec, arg) in enumerate(zip(method.arguments, args)):
        vtype = arg.VariantType if isinstance(arg, ua.Variant) else None
        value = arg.Value if isinstance(arg, ua.Variant) else arg
        if vtype is not None and vtype != spec.type or isinstance(value, bool) or \
                not isinstance(value, _PYTYPES.get(spec.type, ())):
            got = vtype.name if vtype is not None else type(value).__name__
            raise ArgumentProblem(i, ua.StatusCodes.BadTypeMismatch, f"{spec.name}: a {spec.type.name} is expected, "
                                  f"got {got} {value!r}")
        value = float(value)
        if not math.isfinite(value) or not spec.low <= value <= spec.high:
            raise ArgumentProblem(i, ua.StatusCodes.BadOutOfRange, f"{spec.name}: {value!r} is out of range "
                                  f"({spec.low:g} .. {spec.high:g}: {spec.description})")
        out.append(value)
    return out


def outcome(result: CommandResult | Report, host: str, axis: str) -> tuple[str, str]:
    """The (outcome, error text) of drive ``host/axis`` in a Fleet result (one per addressed drive)."""
    found = result.final if isinstance(result, Report) else (*result.results, *result.unexpected)
    for r in found:
        if r.host == host and r.axis == axis:
            return r.outcome, r.error
    reason = result.reason if isinstance(result, Report) else "; ".join(result.errors)
    return "missing", reason or "no result for this drive"


# ---- events ---------------------------------------------------------------------------------

#: OPC UA event severities (1..1000) of what a drive or host does.
SEVERITY = {"fault": 800, "lost": 900, "found": 400, "fault_cleared": 300, "host_offline": 700, "host_online": 300}
_FAULT_STATES = ("fault", "fault_reaction_active")


def drive_alarms(old: DriveStatus | None, new: DriveStatus) -> list[tuple[str, int, str]]:
    """The events a drive's new status raises against its previous one: (kind, severity, message).
    A drive first seen in fault or lost raises them too."""
    name = f"{new.host}/{new.axis}"
    out = []
    was_lost = old is not None and old.lost
    if new.lost and not was_lost:
        out.append(("lost", SEVERITY["lost"], f"{name} lost: {new.error_text or 'slave not answering'}"))
    elif was_lost and not new.lost:
        out.append(("found", SEVERITY["found"], f"{name} answers again (state {new.state})"))
    was_fault = old is not None and old.state in _FAULT_STATES
    if new.state in _FAULT_STATES and not was_fault:
        text = new.error_text or "no error text"
        out.append(("fault", SEVERITY["fault"], f"{name} fault 0x{new.error_code:04X}: {text}"))
    elif was_fault and new.state not in _FAULT_STATES and new.state != "unknown":
        out.append(("fault_cleared", SEVERITY["fault_cleared"], f"{name} left fault (state {new.state})"))
    return out
