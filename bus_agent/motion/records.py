"""The motion layer's vocabulary: PLCopen axis states and what each accepts, the outcome of a
motion command, and the running command's record. Pure data (docs/motion.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any, Mapping

__all__ = ["MODE_CSP", "MODE_CSV", "AxisState", "ACCEPTS", "REFUSAL", "MOTION_OPS", "Finished", "Rejected",
           "Active", "num"]

MODE_CSP = 8
MODE_CSV = 9


class AxisState(str, Enum):
    """PLCopen axis states (values are the wire names of ``drive_status.axis_state``)."""

    DISABLED = "disabled"
    STANDSTILL = "standstill"
    HOMING = "homing"
    DISCRETE_MOTION = "discrete_motion"
    CONTINUOUS_MOTION = "continuous_motion"
    SYNCHRONIZED_MOTION = "synchronized_motion"
    STOPPING = "stopping"
    ERROR_STOP = "error_stop"


#: Motion ops of the drive command key space handled by this module.
MOTION_OPS = ("move", "jog", "home", "stop")

_A = AxisState
_MOVING = frozenset({"move", "jog", "home", "stop"})
#: PLCopen: the ops each axis state accepts (a new motion command aborts the running one).
ACCEPTS: dict[AxisState, frozenset[str]] = {
    _A.DISABLED: frozenset({"stop"}),
    _A.ERROR_STOP: frozenset({"stop"}),
    _A.STANDSTILL: _MOVING,
    _A.DISCRETE_MOTION: _MOVING,
    _A.CONTINUOUS_MOTION: _MOVING,
    _A.SYNCHRONIZED_MOTION: _MOVING,
    _A.HOMING: frozenset({"stop"}),
    _A.STOPPING: frozenset({"stop"}),
}
#: Why a state refuses the ops it does not accept.
REFUSAL: dict[AxisState, str] = {
    _A.DISABLED: "not enabled: motion needs operation_enabled",
    _A.ERROR_STOP: "axis in error_stop (drive fault): reset the fault and enable first",
    _A.HOMING: "homing in progress: stop it first",
    _A.STOPPING: "axis busy with a stop: release it first (stop --release)",
}


class Rejected(Exception):
    """A command refused before anything changed; the message is the reply's reason."""


@dataclass(frozen=True)
class Finished:
    """The terminal outcome of one motion command (``token`` is the caller's command)."""

    token: Any
    request_id: str
    outcome: str   # done | aborted | failed | timeout | rejected
    reason: str = ""
    duration_s: float = 0.0  # the profile's planned duration (done moves)


@dataclass(slots=True)
class Active:
    token: Any
    request_id: str
    op: str                 # move | jog | stop (home: bus_agent.motion.homing)
    deadline_s: float       # the command's timeout, on the caller's clock
    end_s: float = math.inf  # jog: when it starts to decelerate
    synchronized: bool = False
    note: str = ""          # clamps, appended to the done reason
    limit_ahead: str = ""   # jog (CSP): the software limit its position plan ends at
    limit_stop: str = ""    # jog: the software limit it stopped at


def num(args: Mapping[str, Any], name: str) -> float | None:
    v = args.get(name)
    return None if v is None else float(v)

