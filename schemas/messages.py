"""Message types of the wire contract, version 1, and their msgpack codec.

Every message is a frozen dataclass. On the wire it is a msgpack map of its field names plus
``"v"`` (the schema version) and ``"type"`` (the message type name). :func:`decode` validates
types, ranges, choices and required fields and raises only :class:`SchemaError`, whose message
names the field and the problem.

Field constraints live in each field's metadata (``range``, ``choices``, ``max_len``), so the
codec, the JSON Schema export and the README are generated from one definition.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

import msgpack

SCHEMA_VERSION = 1


class SchemaError(ValueError):
    """A payload that is not a valid message of this schema version."""


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
)
#: Agent command ops (``.../agent/cmd/<op>``).
AGENT_OPS = ("nmt",)
#: Network management commands (cia402.md §5) and their EtherCAT meaning.
NMT_COMMANDS = ("start", "stop", "preop", "reset_comm", "reset_node")
#: Terminal outcomes of a command, one per addressed drive.
OUTCOMES = ("done", "failed", "timeout", "rejected", "busy")
#: Event kinds.
EVENT_KINDS = ("transition", "fault", "outcome", "lost", "found", "lease", "reflex", "al_state", "warning")
#: EtherCAT AL states by name (register 0x0130 low nibble).
AL_STATES = ("init", "preop", "boot", "safeop", "op", "none")
AGENT_STATES = ("starting", "running", "stopping", "stopped", "error")

MODES = (1, 3, 4, 6, 7, 8, 9, 10)

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
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


# ---- messages -----------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveStatus:
    """Published on ``drives/@v1/<host>/drive/<axis>/status`` on change and as a heartbeat."""

    TYPE: ClassVar[str] = "drive_status"
    host: str = _f(max_len=NAME_LEN, doc="agent host name")
    axis: str = _f(max_len=NAME_LEN, doc="axis name")
    seq: int = _f(range=U64, doc="per-drive sequence number, +1 per publication")
    time_ns: int = _f(range=U64, doc="agent wall clock at the snapshot, ns since the epoch")
    cycle: int = _f(range=U64, doc="agent cycle counter at the snapshot")
    state: str = _f(choices=DRIVE_STATES, doc="CiA 402 state decoded from the statusword")
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
    lease_holder: str = _f("", max_len=NAME_LEN, doc="supervisor holding the lease, '' if none")
    slave: int = _f(0, range=(0, 65535), doc="slave position on the segment (0-based)")


@dataclass(frozen=True)
class AgentStatus:
    """Published on ``drives/@v1/<host>/agent``: the agent and its cycle."""

    TYPE: ClassVar[str] = "agent_status"
    host: str = _f(max_len=NAME_LEN)
    seq: int = _f(range=U64)
    time_ns: int = _f(range=U64)
    state: str = _f(choices=AGENT_STATES)
    backend: str = _f(max_len=32, doc="'pysoem' or 'sim'")
    cycle_us: int = _f(range=(1, 10_000_000), doc="configured cycle period")
    cycles: int = _f(range=U64)
    period_p50_us: float = _f(doc="measured period, over the last statistics window")
    period_p99_us: float = _f()
    period_max_us: float = _f()
    overruns: int = _f(range=U64, doc="cycles that started later than one period after their deadline")
    wkc_errors: int = _f(range=U64, doc="cycles whose working counter was not the expected one")
    expected_wkc: int = _f(range=(0, 65535))
    axes: list = _f([], doc="axis names in slave order")
    al_states: dict = _f({}, doc="axis -> AL state name")
    leases: dict = _f({}, doc="axis -> lease holder, for leased axes")
    groups: dict = _f({}, doc="group name -> list of member keys 'host/axis'")


@dataclass(frozen=True)
class Event:
    """Published on ``drives/@v1/<host>/drive/<axis>/event``."""

    TYPE: ClassVar[str] = "event"
    host: str = _f(max_len=NAME_LEN)
    axis: str = _f(max_len=NAME_LEN)
    seq: int = _f(range=U64, doc="per-drive event sequence number")
    time_ns: int = _f(range=U64)
    cycle: int = _f(range=U64)
    kind: str = _f(choices=EVENT_KINDS)
    detail: str = _f("", max_len=400)
    from_state: str = _f("unknown", choices=DRIVE_STATES)
    to_state: str = _f("unknown", choices=DRIVE_STATES)
    error_code: int = _f(0, range=U16)
    request_id: str = _f("", max_len=128)


@dataclass(frozen=True)
class CommandRequest:
    """Payload of a query on a ``cmd/<op>`` key. ``op`` must equal the key's op."""

    TYPE: ClassVar[str] = "command_request"
    request_id: str = _f(max_len=128, doc="caller-chosen id; a repeat returns the first outcome")
    op: str = _f(choices=DRIVE_OPS + AGENT_OPS)
    args: dict = _f({}, doc="op arguments (mode, on, holder, ttl_s, takeover, command, slave)")
    timeout_s: float = _f(5.0, range=(0.0, 3600.0), doc="deadline for the goal, from receipt")
    supervisor: str = _f("", max_len=NAME_LEN, doc="sender identity, for leases ('' = anonymous)")


@dataclass(frozen=True)
class CommandReply:
    """One terminal answer per addressed drive, on that drive's own ``cmd/<op>`` key."""

    TYPE: ClassVar[str] = "command_reply"
    request_id: str = _f(max_len=128)
    host: str = _f(max_len=NAME_LEN)
    op: str = _f(choices=DRIVE_OPS + AGENT_OPS)
    outcome: str = _f(choices=OUTCOMES)
    axis: str = _f("", max_len=NAME_LEN, doc="'' for agent commands")
    state: str = _f("unknown", choices=DRIVE_STATES, doc="state when the outcome was decided")
    error_code: int = _f(0, range=U16)
    reason: str = _f("", max_len=400)
    elapsed_s: float = _f(0.0, doc="receipt to outcome")
    cycles: int = _f(0, range=U64, doc="agent cycles from receipt to outcome")
    lease_holder: str = _f("", max_len=NAME_LEN)


MESSAGE_TYPES: tuple[type, ...] = (DriveStatus, AgentStatus, Event, CommandRequest, CommandReply)
_BY_TYPE = {cls.TYPE: cls for cls in MESSAGE_TYPES}


# ---- codec --------------------------------------------------------------------------------


def encode(msg: Any) -> bytes:
    """Encode a message dataclass as msgpack (fields + ``v`` + ``type``)."""
    if type(msg) not in _BY_TYPE.values():
        raise SchemaError(f"cannot encode {type(msg).__name__}: not a message type")
    body = {"v": SCHEMA_VERSION, "type": msg.TYPE}
    for f in dataclasses.fields(msg):
        body[f.name] = getattr(msg, f.name)
    return msgpack.packb(body, use_bin_type=True)


def _base_type(cls: type, name: str) -> type:
    hints = typing.get_type_hints(cls)
    t = hints[name]
    if isinstance(t, types.UnionType) or typing.get_origin(t) is typing.Union:
        t = next(a for a in typing.get_args(t) if a is not type(None))
    return typing.get_origin(t) or t


def _check_field(cls: type, f: dataclasses.Field, value: Any) -> Any:
    where = f"{cls.TYPE}.{f.name}"
    t = _base_type(cls, f.name)
    meta = f.metadata
    if t is bool:
        if not isinstance(value, bool):
            raise SchemaError(f"{where}: expected bool, got {type(value).__name__}")
    elif t is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SchemaError(f"{where}: expected int, got {type(value).__name__}")
    elif t is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SchemaError(f"{where}: expected number, got {type(value).__name__}")
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise SchemaError(f"{where}: must be a finite number")
    elif t is str:
        if not isinstance(value, str):
            raise SchemaError(f"{where}: expected str, got {type(value).__name__}")
        if "max_len" in meta and len(value) > meta["max_len"]:
            raise SchemaError(f"{where}: longer than {meta['max_len']} characters")
    elif t is dict:
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise SchemaError(f"{where}: expected a map with string keys")
    elif t is list:
        if not isinstance(value, (list, tuple)):
            raise SchemaError(f"{where}: expected a list")
        value = list(value)
    if "range" in meta:
        lo, hi = meta["range"]
        if not lo <= value <= hi:
            raise SchemaError(f"{where}: {value!r} out of range [{lo}, {hi}]")
    if "choices" in meta and value not in meta["choices"]:
        raise SchemaError(f"{where}: {value!r} is not one of {', '.join(map(str, meta['choices']))}")
    return value


def decode(data: bytes, expected: type | None = None) -> Any:
    """Decode and validate ``data``; raise :class:`SchemaError` (and nothing else) if invalid.

    ``expected`` restricts the accepted message type.
    """
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types; the contract is one.
        raise SchemaError(f"payload is not valid msgpack: {exc}") from None
    return from_dict(body, expected)


def from_dict(body: Any, expected: type | None = None) -> Any:
    """Validate a decoded map (see :func:`decode`)."""
    if not isinstance(body, dict):
        raise SchemaError("payload is not a map")
    v = body.get("v")
    if isinstance(v, bool) or not isinstance(v, int):
        raise SchemaError("v: missing schema version")
    if v != SCHEMA_VERSION:
        raise SchemaError(f"v: schema version {v!r} is not supported (this side speaks {SCHEMA_VERSION})")
    tname = body.get("type")
    cls = _BY_TYPE.get(tname) if isinstance(tname, str) else None
    if cls is None:
        raise SchemaError(f"type: {tname!r} is not a message type")
    if expected is not None and cls is not expected:
        raise SchemaError(f"type: expected {expected.TYPE}, got {tname}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(body) - known - {"v", "type"}
    if unknown:
        raise SchemaError(f"{cls.TYPE}: unknown field(s) {', '.join(sorted(map(str, unknown)))}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in body:
            kwargs[f.name] = _check_field(cls, f, body[f.name])
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise SchemaError(f"{cls.TYPE}.{f.name}: required field missing")
    return cls(**kwargs)
