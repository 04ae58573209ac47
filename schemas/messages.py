"""Message types of the wire contract, version 1, and their msgpack codec.

Every message is a frozen dataclass. On the wire it is a msgpack map of its field names plus
``"v"`` (the schema version) and ``"type"`` (the message type name). :func:`decode` validates
types, ranges, choices and required fields and raises only :class:`SchemaError`, whose message
names the field and the problem.

Field constraints live in each field's metadata (``range``, ``choices``, ``max_len``), so the
codec, the JSON Schema export and the README are generated from one definition.
"""

from __future__ import annotations

import copy
import functools
import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar

import msgpack

from . import compiled as _compiled
from .values import ARG_INT, ARG_MAX_DEPTH, Meta, SchemaError, _check_value, _field_types

__all__ = ["SCHEMA_VERSION", "SchemaError", "Meta", "ARG_INT", "ARG_MAX_DEPTH", "encode", "decode", "validate",
           "to_dict", "validate_args", "encode_new"]

SCHEMA_VERSION = 1


# ---- vocabularies -----------------------------------------------------------------------

#: CiA 402 states as they appear on the wire (lower-case standard names), plus "unknown".
DRIVE_STATES = (
    "not_ready_to_switch_on",
    "switch_on_disabled",
    "ready_to_switch_on",
    "switched_on",
    "operation_enabled",
    "quick_stop_active",
    "fault_reaction_active",
    "fault",
    "unknown",
)
#: What the agent drives a drive towards (the controller's goal).
GOALS = ("disabled", "ready", "switched_on", "enabled", "quick_stop")
#: Drive command ops (the last chunk of ``.../drive/<axis>/cmd/<op>``).
DRIVE_OPS = (
    "enable",       # -> operation_enabled
    "switch_on",    # -> switched_on
    "shutdown",     # -> ready_to_switch_on
    "disable",      # seed order: disable operation, shutdown, disable voltage -> switch_on_disabled
    "quick_stop",   # -> quick_stop_active (or switch_on_disabled by 0x605A 0..4)
    "halt",         # args {"on": bool}: controlword bit 8
    "fault_reset",  # rising edge on bit 7, bounded retries -> switch_on_disabled
    "set_mode",     # args {"mode": int}: 0x6060, done on the 0x6061 echo
    "lease",        # args {"holder": str, "ttl_s": float, "takeover": bool}
    "release",      # args {"holder": str}
    "move",         # args {"to" | "by": float, "velocity", "accel", "jerk": float, "sync": bool, "targets", "axes"}
    "jog",          # args {"velocity": float, "for_s": float}
    "home",         # args {"method": int}
    "stop",         # args {"release": bool}: decelerate and refuse motion until released
)
#: Agent command ops (``.../agent/cmd/<op>``).
AGENT_OPS = ("nmt",)
#: Network management commands (cia402.md §5) and their EtherCAT meaning.
NMT_COMMANDS = ("start", "stop", "preop", "reset_comm", "reset_node")
#: Terminal outcomes of a command, one per addressed drive.
OUTCOMES = ("done", "failed", "timeout", "rejected", "busy", "aborted")
#: PLCopen axis states of the motion layer (drive_status.axis_state).
AXIS_STATES = ("disabled", "standstill", "homing", "discrete_motion", "continuous_motion",
               "synchronized_motion", "stopping", "error_stop")
#: Event kinds.
EVENT_KINDS = ("transition", "fault", "outcome", "lost", "found", "lease", "reflex", "al_state", "warning",
               "command", "conflict", "emcy")
#: EtherCAT AL states by name (register 0x0130 low nibble).
AL_STATES = ("init", "preop", "boot", "safeop", "op", "none")
AGENT_STATES = ("starting", "running", "stopping", "stopped", "error")

MODES = (1, 3, 4, 6, 7, 8, 9, 10)

#: What a ``recording_request`` asks for: the last seconds of the ring, the latest window frozen
#: by a trigger of that kind (``any``: of any kind), or a window frozen now (``now``: an explicit
#: request, answered when its after-trigger part is recorded).
RECORDING_WHAT = ("last", "fault", "reflex", "lost", "request", "any", "now")
#: Why a recording holds what it holds (an open vocabulary: the trigger kinds, or ``last``).
RECORDING_REASONS = ("last", "fault", "reflex", "lost", "request")
#: Channels of a recording, in order: name -> (per ``cycle`` or per ``drive``, meaning). A per-drive
#: channel holds n_cycles x len(axes) values, cycle-major (all axes of the first cycle, then ...).
RECORDING_CHANNELS: dict[str, tuple[str, str]] = {
    "cycle": ("cycle", "agent cycle counter"),
    "time_ns": ("cycle", "monotonic clock at the cycle start, ns"),
    "period_ns": ("cycle", "time since the previous cycle start, ns"),
    "wkc": ("cycle", "working counter of the exchange"),
    "statusword": ("drive", "0x6041 statusword"),
    "controlword": ("drive", "0x6040 controlword written"),
    "target_position": ("drive", "0x607A target position written"),
    "target_velocity": ("drive", "0x60FF target velocity written"),
    "target_torque": ("drive", "0x6071 target torque written"),
    "position": ("drive", "0x6064 position actual value"),
    "velocity": ("drive", "0x606C velocity actual value"),
    "torque": ("drive", "0x6077 torque actual value"),
    "error_code": ("drive", "0x603F error code"),
    "mode_display": ("drive", "0x6061 modes of operation display"),
}
#: Longest recording a request may ask for (``last_s``).
RECORDING_MAX_S = 600.0

U16 = (0, 0xFFFF)
I32 = (-(2**31), 2**31 - 1)
I16 = (-(2**15), 2**15 - 1)
I8 = (-128, 127)
U64 = (0, 2**64 - 1)
NAME_LEN = 64


def _f(default: Any = dataclasses.MISSING, **meta: Any) -> Any:
    """A dataclass field with validation metadata (``range``, ``choices``, ``max_len``, ``doc``)."""
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    if isinstance(default, (dict, list)):
        return field(default_factory=functools.partial(copy.copy, default), metadata=meta)
    return field(default=default, metadata=meta)


NAME = Meta(str, {"name": True})
MEMBER = Meta(str, {"member": True, "doc": "'host/axis' of legal names"})
AL_STATE = Meta(str, {"choices": AL_STATES})


# ---- messages -----------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveStatus:
    """Published on ``drives/@v1/<host>/drive/<axis>/status`` on change and as a heartbeat. A change of what the agent asked alone (``controlword``, ``goal``, ``halt``, ``mode``) waits for the drive's answer (the next statusword change) to go out with it, at most 3 agent cycles; ``seq`` counts publications."""

    TYPE: ClassVar[str] = "drive_status"
    STRICT: ClassVar[bool] = False  # published/replied state: readers ignore fields they do not know
    host: str = _f(max_len=NAME_LEN, name=True, doc="agent host name")
    axis: str = _f(max_len=NAME_LEN, name=True, doc="axis name")
    seq: int = _f(range=U64, doc="per-drive sequence number, +1 per publication")
    time_ns: int = _f(range=U64, doc="agent wall clock at the snapshot, ns since the epoch")
    cycle: int = _f(range=U64, doc="agent cycle counter at the snapshot")
    state: str = _f(choices=DRIVE_STATES, doc="CiA 402 state decoded from the statusword; 'unknown' while the drive is lost (its inputs are old: statusword, mode_display, error_code and objects read 0 or empty, the actual values are listed in absent)")
    statusword: int = _f(range=U16, doc="0x6041")
    controlword: int = _f(range=U16, doc="0x6040 last written")
    goal: str = _f(choices=GOALS, doc="what the agent drives this drive towards")
    halt: bool = _f(doc="controlword bit 8 requested")
    mode: int = _f(range=I8, doc="0x6060 requested mode of operation")
    mode_display: int = _f(range=I8, doc="0x6061 mode of operation display")
    position: int = _f(range=I32, doc="0x6064 position actual value")
    velocity: int = _f(range=I32, doc="0x606C velocity actual value")
    torque: int = _f(range=I16, doc="0x6077 torque actual value")
    error_code: int = _f(range=U16, doc="0x603F error code (0 = none)")
    error_text: str = _f("", max_len=200, doc="meaning of error_code, or the agent's reason")
    al_state: str = _f("op", choices=AL_STATES, doc="EtherCAT AL state of the slave")
    lost: bool = _f(False, doc="slave not answering (working counter or AL state)")
    lease_holder: str = _f("", max_len=NAME_LEN, name=True, doc="supervisor holding the lease, '' if none")
    slave: int = _f(0, range=(0, 65535), doc="slave position on the segment (0-based)")
    absent: list = _f([], items=Meta(str, {"choices": ("position", "velocity", "torque")}),
                      doc="actual values the drive does not map (their fields read 0 and mean nothing)")
    objects: dict = _f({}, keys=Meta(str, {"max_len": 64}), values=Meta(int, {"range": (-(2**63), 2**64 - 1)}),
                       doc="other mapped input objects by name (CiA 402 table, else the ESI's, else '0xIIII:SS') -> value")
    axis_state: str = _f("disabled", choices=AXIS_STATES, open=True, doc="PLCopen axis state of the motion layer")
    homed: bool = _f(False, doc="the last home command of this axis succeeded (false after a failed or aborted one)")
    target_position: int = _f(0, range=I32, doc="0x607A target position written last")
    following_error: int = _f(0, range=I32, doc="target position written last minus 0x6064 (counts)")
    motion_request_id: str = _f("", max_len=128, doc="request id of the running motion command ('' if none)")
    target_clamps: int = _f(0, range=U64, doc="cycles in which the output stage limited 0x607A/0x60FF to the axis "
                            "velocity/acceleration limits, since the agent started (0 in older agents)")
    last_known_state: str = _f("", choices=DRIVE_STATES + ("",), doc="a lost drive (state 'unknown'): the CiA 402 state it was in when it was lost; '' while not lost")


@dataclass(frozen=True)
class AgentStatus:
    """Published on ``drives/@v1/<host>/agent``: the agent and its cycle."""

    TYPE: ClassVar[str] = "agent_status"
    STRICT: ClassVar[bool] = False  # published/replied state: readers ignore fields they do not know
    host: str = _f(max_len=NAME_LEN, name=True, doc="agent host name")
    seq: int = _f(range=U64, doc="sequence number, +1 per publication")
    time_ns: int = _f(range=U64, doc="agent wall clock, ns since the epoch")
    state: str = _f(choices=AGENT_STATES, doc="agent lifecycle state")
    backend: str = _f(max_len=32, doc="'pysoem' or 'sim'")
    cycle_us: int = _f(range=(1, 10_000_000), doc="configured cycle period")
    cycles: int = _f(range=U64, doc="cycles run since start")
    period_p50_us: float = _f(doc="measured period, over the last statistics window")
    period_p99_us: float = _f(doc="measured period, 99th percentile")
    period_max_us: float = _f(doc="measured period, maximum")
    overruns: int = _f(range=U64, doc="cycles that started later than one period after their deadline")
    wkc_errors: int = _f(range=U64, doc="cycles whose working counter was not the expected one")
    expected_wkc: int = _f(range=(0, 65535), doc="working counter expected per cycle")
    axes: list = _f([], items=NAME, doc="axis names in slave order")
    al_states: dict = _f({}, keys=NAME, values=AL_STATE, doc="axis -> AL state name")
    leases: dict = _f({}, keys=NAME, values=NAME, doc="axis -> lease holder, for leased axes")
    groups: dict = _f({}, keys=NAME, values=Meta(list, {"items": MEMBER}), doc="group name -> list of member keys 'host/axis'")
    dc: dict = _f({}, keys=NAME, values=Meta(str, {"choices": ("sync0", "off", "none")}),
                  doc="axis -> DC state of its slave: sync0 (SYNC0 running), off (DC capable, unused), none")
    dc_offset_p50_us: float = _f(0.0, doc="frame-to-SYNC0 offset (time since SYNC0 as the frame passed), median")
    dc_offset_p99_us: float = _f(0.0, doc="frame-to-SYNC0 offset, 99th percentile (0 without DC)")
    instance: str = _f("", max_len=64, doc="this agent process' random id, new at every start: two ids under one host name are a conflict")
    conflict: str = _f("", max_len=400, doc="another agent publishes under this host name ('' if none): commands are refused by supervisors")
    commands: dict = _f({}, keys=NAME, values=Meta(int, {"range": U64}),
                        doc="'op.outcome' -> command replies given since start (e.g. 'enable.done')")


@dataclass(frozen=True)
class Event:
    """Published on ``drives/@v1/<host>/drive/<axis>/event``."""

    TYPE: ClassVar[str] = "event"
    STRICT: ClassVar[bool] = False  # published/replied state: readers ignore fields they do not know
    host: str = _f(max_len=NAME_LEN, name=True, doc="agent host name")
    axis: str = _f(max_len=NAME_LEN, name=True, doc="axis name")
    seq: int = _f(range=U64, doc="per-drive event sequence number")
    time_ns: int = _f(range=U64, doc="agent wall clock at the event, ns since the epoch")
    cycle: int = _f(range=U64, doc="agent cycle counter at the event")
    kind: str = _f(choices=EVENT_KINDS, open=True, doc="what happened")
    detail: str = _f("", max_len=400, doc="human-readable detail")
    from_state: str = _f("unknown", choices=DRIVE_STATES, doc="CiA 402 state before (transition)")
    to_state: str = _f("unknown", choices=DRIVE_STATES, doc="CiA 402 state after (transition)")
    error_code: int = _f(0, range=U16, doc="0x603F error code (fault), 0 = none")
    request_id: str = _f("", max_len=128, doc="request the event belongs to ('' if none)")
    requester: str = _f("", max_len=128, doc="who sent the command (kind command; '' = anonymous)")


@dataclass(frozen=True)
class CommandRequest:
    """Payload of a query on a ``cmd/<op>`` key. ``op`` must equal the key's op.

    ``args`` must fit the op (see :data:`OP_ARGS` and :func:`validate_args`): decode rejects
    unknown, missing and out-of-range arguments.
    """

    TYPE: ClassVar[str] = "command_request"
    STRICT: ClassVar[bool] = True  # an agent never acts on a command with fields it does not know
    #: Optional fields added after agents were deployed: encoded only when not at their default,
    #: so a request that does not use them is what older (strict) agents accept.
    SPARSE: ClassVar[tuple[str, ...]] = ("on_behalf_of",)
    request_id: str = _f(max_len=128, min_len=1, doc="caller-chosen id; a repeat returns the first outcome")
    op: str = _f(choices=DRIVE_OPS + AGENT_OPS, doc="the op, equal to the last chunk of the key")
    args: dict = _f({}, arg_value=True, doc="op arguments, see the op argument table")
    timeout_s: float = _f(5.0, range=(0.0, 3600.0), doc="deadline for the goal, from receipt")
    supervisor: str = _f("", max_len=NAME_LEN, name=True, doc="sender identity, for leases ('' = anonymous); on an @sup/<principal> key, '' or that principal")
    on_behalf_of: str = _f("", max_len=NAME_LEN, name=True, doc="the user a gateway sends this for (an OPC UA user), for the audit; sent only when set")


@dataclass(frozen=True)
class CommandReply:
    """One terminal answer per addressed drive, on that drive's own ``cmd/<op>`` key."""

    TYPE: ClassVar[str] = "command_reply"
    STRICT: ClassVar[bool] = False  # published/replied state: readers ignore fields they do not know
    request_id: str = _f(max_len=128, doc="request_id of the request answered")
    host: str = _f(max_len=NAME_LEN, name=True, doc="agent host name")
    op: str = _f(choices=DRIVE_OPS + AGENT_OPS, doc="the op of the request")
    outcome: str = _f(choices=OUTCOMES, open=True, doc="terminal outcome for this drive")
    axis: str = _f("", max_len=NAME_LEN, name=True, doc="'' for agent commands")
    state: str = _f("unknown", choices=DRIVE_STATES, doc="state when the outcome was decided")
    error_code: int = _f(0, range=U16, doc="0x603F error code reached (failed), 0 = none")
    reason: str = _f("", max_len=400, doc="why (failed, rejected, busy, timeout)")
    elapsed_s: float = _f(0.0, doc="receipt to outcome")
    duration_s: float = _f(0.0, range=(0.0, 1e6), doc="motion: the planned profile duration (move prepare: the axis's minimum)")
    cycles: int = _f(0, range=U64, doc="agent cycles from receipt to outcome")
    lease_holder: str = _f("", max_len=NAME_LEN, name=True, doc="holder of the lease (busy), '' if none")


@dataclass(frozen=True)
class RecordingRequest:
    """Payload of a query on ``drives/@v1/<host>/agent/recording`` (the flight recorder)."""

    TYPE: ClassVar[str] = "recording_request"
    STRICT: ClassVar[bool] = True  # a request the agent does not fully understand is refused
    what: str = _f("last", choices=RECORDING_WHAT, doc="last seconds, latest frozen window of a trigger kind, or freeze now")
    last_s: float = _f(10.0, range=(0.001, RECORDING_MAX_S), doc="with what=last: how many seconds back")


I64 = (-(2**63), 2**63 - 1)


@dataclass(frozen=True)
class Recording:
    """Reply on ``drives/@v1/<host>/agent/recording``: consecutive cycles of every drive of the
    agent, one value list per channel (:data:`RECORDING_CHANNELS`)."""

    TYPE: ClassVar[str] = "recording"
    STRICT: ClassVar[bool] = False  # published/replied state: readers ignore fields they do not know
    host: str = _f(max_len=NAME_LEN, name=True, doc="agent host name")
    reason: str = _f(choices=RECORDING_REASONS, open=True, doc="the trigger that froze it, or last")
    cycle_us: int = _f(range=(1, 10_000_000), doc="configured cycle period")
    first_cycle: int = _f(range=U64, doc="cycle counter of the first recorded cycle")
    n_cycles: int = _f(range=(0, 2**32 - 1), doc="consecutive cycles recorded")
    time_origin_ns: int = _f(range=U64, doc="agent wall clock at the first recorded cycle, ns since the epoch")
    axes: list = _f([], items=NAME, doc="axis names, the order of per-drive values")
    channels: dict = _f({}, keys=NAME, values=Meta(list, {"items": Meta(int, {"range": I64})}),
                        doc="channel name -> values (per cycle, or per cycle and axis, cycle-major)")
    axis: str = _f("", max_len=NAME_LEN, name=True, doc="axis of the trigger, '' if none")
    detail: str = _f("", max_len=400, doc="what triggered it")
    trigger_cycle: int = _f(0, range=U64, doc="cycle of the trigger, 0 if none")


def _check_recording(kw: dict) -> None:
    """Every known channel holds one value per cycle (or per cycle and axis)."""
    n, axes = kw["n_cycles"], kw.get("axes", [])
    for name, values in kw.get("channels", {}).items():
        scope = RECORDING_CHANNELS.get(name, ("",))[0]
        want = n if scope == "cycle" else n * len(axes) if scope == "drive" else len(values)
        if len(values) != want:
            raise SchemaError(f"recording.channels[{name!r}]: {len(values)} values, expected {want} "
                              f"({n} cycles{' x ' + str(len(axes)) + ' axes' if scope == 'drive' else ''})")


MESSAGE_TYPES: tuple[type[Any], ...] = (DriveStatus, AgentStatus, Event, CommandRequest, CommandReply,
                                        RecordingRequest, Recording)
_BY_TYPE = {cls.TYPE: cls for cls in MESSAGE_TYPES}


# ---- op arguments -------------------------------------------------------------------------


@dataclass(frozen=True)
class Arg:
    """One argument of a command op: type, rule metadata (as a field's), required or default."""

    type: type
    required: bool = False
    default: Any = None
    meta: dict = field(default_factory=dict)


#: Default lease duration when ``lease`` is sent without ``ttl_s``.
LEASE_TTL_DEFAULT_S = 10.0

#: Arguments of every op that takes any; every other op takes none.
OP_ARGS: dict[str, dict[str, Arg]] = {
    "set_mode": {
        "mode": Arg(int, required=True, meta={"choices": MODES, "doc": "0x6060 modes of operation"}),
    },
    "halt": {
        "on": Arg(bool, required=True, meta={"doc": "set (true) or clear (false) controlword bit 8"}),
    },
    "lease": {
        "holder": Arg(str, required=True, meta={"name": True, "max_len": NAME_LEN, "doc": "supervisor taking the lease"}),
        "ttl_s": Arg(float, default=LEASE_TTL_DEFAULT_S, meta={"range": (0.1, 3600.0), "doc": "lease duration; renew before it ends"}),
        "takeover": Arg(bool, default=False, meta={"doc": "take the lease even if another supervisor holds it"}),
    },
    "release": {
        "holder": Arg(str, required=True, meta={"name": True, "max_len": NAME_LEN, "doc": "supervisor giving the lease back"}),
    },
    "move": {
        "to": Arg(float, meta={"range": (-1e12, 1e12), "doc": "absolute target position (axis unit); exactly one of to, by"}),
        "by": Arg(float, meta={"range": (-1e12, 1e12), "doc": "relative distance from the position being commanded (axis unit)"}),
        "velocity": Arg(float, meta={"range": (0.0, 1e12), "doc": "max velocity (unit/s; default the axis limit; above it: clamped or rejected by the axis policy)"}),
        "accel": Arg(float, meta={"range": (0.0, 1e15), "doc": "max acceleration (unit/s^2; default the axis limit)"}),
        "jerk": Arg(float, meta={"range": (0.0, 1e18), "doc": "max jerk (unit/s^3; default the axis limit)"}),
        "sync": Arg(bool, default=False, meta={"doc": "the addressed axes of this host start in one cycle and arrive together"}),
        "duration_s": Arg(float, meta={"range": (0.0, 3600.0), "doc": "sync: the group's common duration (at least; commit of a cross-host move)"}),
        "start_at_ns": Arg(int, meta={"range": (0, 2**63 - 1), "doc": "sync: start at this agent wall-clock time (ns since the epoch)"}),
        "prepare": Arg(bool, default=False, meta={"doc": "sync: only plan; the reply's duration_s is the axes' minimum duration"}),
        "targets": Arg(dict, meta={"keys": NAME, "values": Meta(float, {"range": (-1e12, 1e12)}), "doc": "per-axis absolute targets (axis -> position), instead of to/by"}),
        "axes": Arg(list, meta={"items": NAME, "doc": "sync: the axes of this host in the group (to/by for each); the query may address more, the agent takes these (a group move of some of a host's axes)"}),
    },
    "jog": {
        "velocity": Arg(float, required=True, meta={"range": (-1e12, 1e12), "doc": "velocity (unit/s, signed)"}),
        "for_s": Arg(float, meta={"range": (0.001, 3600.0), "doc": "run this long, then stop (default: until the command's timeout)"}),
        "accel": Arg(float, meta={"range": (0.0, 1e15), "doc": "max acceleration (unit/s^2; default the axis limit)"}),
        "jerk": Arg(float, meta={"range": (0.0, 1e18), "doc": "max jerk (unit/s^3; default the axis limit)"}),
    },
    "home": {
        "method": Arg(int, meta={"range": (-128, 127), "doc": "0x6098 homing method (default the axis's configured one)"}),
    },
    "stop": {
        "release": Arg(bool, default=False, meta={"doc": "release a stop: motion is accepted again"}),
    },
    "nmt": {
        "command": Arg(str, required=True, meta={"choices": NMT_COMMANDS, "doc": "network management command"}),
        "axis": Arg(str, meta={"name": True, "max_len": NAME_LEN, "doc": "only this axis' slave (default: the whole segment)"}),
    },
}


def _validate_args(op: Any, args: Any, where: str) -> dict:
    if op not in DRIVE_OPS + AGENT_OPS:
        raise SchemaError(f"op: {op!r} is not one of {', '.join(DRIVE_OPS + AGENT_OPS)}")
    if args is None:
        args = {}
    if not isinstance(args, dict) or not all(isinstance(k, str) for k in args):
        raise SchemaError(f"{where}: expected a map with string keys")
    spec = OP_ARGS.get(op, {})
    unknown = sorted(set(args) - set(spec))
    if unknown:
        takes = ", ".join(spec) if spec else "no arguments"
        raise SchemaError(f"{where}: unknown argument(s) {', '.join(unknown)} for op {op} (takes {takes})")
    out = {}
    for name, arg in spec.items():
        if name in args:
            out[name] = _check_value(f"{where}.{name}", arg.type, arg.meta, args[name], allow_empty=False)
        elif arg.required:
            raise SchemaError(f"{where}.{name}: required for op {op}")
        elif arg.default is not None:
            out[name] = arg.default
    return out


def validate_args(op: str, args: dict) -> dict:
    """Check the arguments of command ``op``; return them normalised, defaults filled in.

    ``set_mode``: ``mode`` in :data:`MODES` (0x6060); ``halt``: ``on`` bool (controlword
    bit 8); ``lease``: ``holder`` name, ``ttl_s`` 0.1..3600 (default 10), ``takeover`` bool
    (default false); ``release``: ``holder`` name; ``nmt``: ``command`` in
    :data:`NMT_COMMANDS`, optional ``axis`` name; every other op: no arguments.
    Raise :class:`SchemaError` naming the field otherwise. Pure; cycle-safe.
    """
    return _validate_args(op, args, "args")


# ---- codec --------------------------------------------------------------------------------

_PLANS: dict[type, tuple[frozenset, _compiled.Checker]] = {}
#: Strings one field accepted, remembered up to this many per field (see :mod:`schemas.compiled`).
_SEEN_MAX = _compiled.SEEN_MAX


def _plan(cls: type[Any]) -> tuple[frozenset, _compiled.Checker]:
    """Per class, once: the known field names (with ``v`` and ``type``) and its compiled checker."""
    plan = _PLANS.get(cls)
    if plan is None:
        ftypes = _field_types(cls)
        rows = tuple(
            _compiled.Row(f.name, f"{cls.TYPE}.{f.name}", ftypes[f.name], f.metadata, f.default == "",
                          f.default, f.default_factory)
            for f in dataclasses.fields(cls)
        )
        plan = _PLANS[cls] = (frozenset(r.name for r in rows) | {"v", "type"},
                              _compiled.compile_checker(cls.TYPE, rows))
    return plan


def _validated(cls: type[Any], body: dict, out: dict) -> dict:
    """Every field of ``cls`` taken from ``body`` into ``out``, checked, normalised, defaults filled."""
    known, check = _plan(cls)
    if cls.STRICT and not known.issuperset(body):
        unknown = set(body) - known
        raise SchemaError(f"{cls.TYPE}: unknown field(s) {', '.join(sorted(map(repr, unknown)))}")
    check(body, out)
    if cls is CommandRequest:
        _validate_args(out["op"], out["args"], f"{cls.TYPE}.args")
    elif cls is Recording:
        _check_recording(out)
    return out


def _built(cls: type[Any], fields: dict) -> Any:
    """An instance of message class ``cls`` holding ``fields`` (every field, already checked).

    The frozen dataclass's ``__init__`` sets each field through ``object.__setattr__`` (about
    6 us for a drive status); the checked map goes into the instance's ``__dict__`` at once
    instead. The messages define no ``__post_init__``, so the two give equal objects."""
    msg = object.__new__(cls)
    msg.__dict__.update(fields)
    return msg


_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def to_dict(msg: Any) -> dict:
    """The wire map of a message (``v``, ``type`` and every field), without validation."""
    if type(msg) not in _BY_TYPE.values():
        raise SchemaError(f"not a message type: {type(msg).__name__}")
    cls = type(msg)
    names = _FIELD_NAMES.get(cls)
    if names is None:
        names = _FIELD_NAMES[cls] = tuple(f.name for f in dataclasses.fields(cls))
    body: dict[str, Any] = {"v": SCHEMA_VERSION, "type": msg.TYPE}
    for name in names:
        body[name] = getattr(msg, name)
    return body


def validate(msg: Any) -> Any:
    """Check a message object against its schema; return it, or raise :class:`SchemaError`."""
    if type(msg) not in _BY_TYPE.values():
        raise SchemaError(f"not a message type: {type(msg).__name__}")
    _validated(type(msg), msg.__dict__, {})
    return msg


def _drop_sparse(cls: type[Any], body: dict) -> None:
    """Leave out the class's ``SPARSE`` fields (optional strings) that are empty (see ``CommandRequest``)."""
    for name in getattr(cls, "SPARSE", ()):
        if body.get(name) == "":
            del body[name]


def encode(msg: Any) -> bytes:
    """Validate and encode a message dataclass as msgpack (fields + ``v`` + ``type``).

    Raise :class:`SchemaError` if ``msg`` would not decode on the other side, so an invalid
    message never reaches the wire.
    """
    if type(msg) not in _BY_TYPE.values():
        raise SchemaError(f"cannot encode {type(msg).__name__}: not a message type")
    body = _validated(type(msg), msg.__dict__, {"v": SCHEMA_VERSION, "type": msg.TYPE})
    _drop_sparse(type(msg), body)
    try:
        return msgpack.packb(body, use_bin_type=True)
    except Exception as exc:  # defensive: validation admits only packable values
        raise SchemaError(f"cannot encode {msg.TYPE}: {exc}") from None


def decode(data: bytes, expected: type[Any] | None = None) -> Any:
    """Decode and validate ``data``; raise :class:`SchemaError` (and nothing else) if invalid.

    ``data`` is bytes-like (or has ``to_bytes()``, as a zenoh ``ZBytes``). ``expected``
    restricts the accepted message type.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)) and hasattr(data, "to_bytes"):
        try:
            data = data.to_bytes()
        except Exception as exc:
            raise SchemaError(f"payload cannot be read as bytes: {exc}") from None
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types; the contract is one.
        raise SchemaError(f"payload is not valid msgpack: {exc}") from None
    try:
        return from_dict(body, expected)
    except SchemaError:
        raise
    except Exception as exc:  # last line of defence for the "only SchemaError" contract
        raise SchemaError(f"internal error while validating payload: {type(exc).__name__}: {exc}") from None


def from_dict(body: Any, expected: type[Any] | None = None) -> Any:
    """Validate a decoded map (see :func:`decode`)."""
    if not isinstance(body, dict):
        raise SchemaError(f"payload is not a map (got {type(body).__name__})")
    if "v" not in body:
        raise SchemaError("v: missing schema version")
    v = body["v"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (isinstance(v, float) and not v.is_integer()):
        raise SchemaError(f"v: schema version must be an integer, got {v!r}")
    if v != SCHEMA_VERSION:
        raise SchemaError(f"v: schema version {v!r} is not supported (this side speaks {SCHEMA_VERSION})")
    tname = body.get("type")
    cls = _BY_TYPE.get(tname) if isinstance(tname, str) else None
    if cls is None:
        raise SchemaError(f"type: {tname!r} is not a message type ({', '.join(_BY_TYPE)})")
    if expected is not None and cls is not expected:
        raise SchemaError(f"type: expected {expected.TYPE}, got {tname}")
    return _built(cls, _validated(cls, body, {}))


def encode_new(cls: type[Any], fields: dict) -> tuple[Any, bytes]:
    """A new message of class ``cls`` from ``fields`` (optional ones may be left out) and its
    encoding, validated once: what ``encode(cls(**fields))`` gives, for half the work.

    Raise :class:`SchemaError` naming the field when a value is not valid (nothing is built);
    a name that is not a field of ``cls`` is refused as by ``cls(**fields)``."""
    if cls not in _BY_TYPE.values():
        raise SchemaError(f"cannot encode {cls.__name__}: not a message type")
    known, _ = _plan(cls)
    if not known.issuperset(fields) or "v" in fields or "type" in fields:
        unknown = set(fields) - known | ({"v", "type"} & set(fields))
        raise SchemaError(f"{cls.TYPE}: unknown field(s) {', '.join(sorted(map(repr, unknown)))}")
    body = _validated(cls, fields, {"v": SCHEMA_VERSION, "type": cls.TYPE})
    wire = body
    if getattr(cls, "SPARSE", ()):
        wire = dict(body)
        _drop_sparse(cls, wire)
    try:
        payload = msgpack.packb(wire, use_bin_type=True)
    except Exception as exc:  # defensive: validation admits only packable values
        raise SchemaError(f"cannot encode {cls.TYPE}: {exc}") from None
    del body["v"], body["type"]
    return _built(cls, body), payload
