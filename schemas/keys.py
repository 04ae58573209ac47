"""The key space, version 1: the only place keys are built and parsed.

Layout (every level fixed, so keys parse without guessing)::

    drives/@v1/<host>/agent                   agent status
    drives/@v1/<host>/agent/cmd/<op>          agent commands (nmt)
    drives/@v1/<host>/alive                   agent liveliness token
    drives/@v1/<host>/drive/<axis>/status     drive status (put on change + heartbeat; get)
    drives/@v1/<host>/drive/<axis>/event      drive events
    drives/@v1/<host>/drive/<axis>/cmd/<op>   drive commands
    drives/@v1/@sup/<name>                    supervisor liveliness token

``@v1`` and ``@sup`` are verbatim chunks: wildcards never match them.
Host, axis and supervisor names are single legal chunks (see :func:`validate_name`).
Selectors (``*``, ``**``, ``?``-free zenoh wildcards) are accepted where documented.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum

PREFIX = "drives"
VERSION_CHUNK = "@v1"
ROOT = f"{PREFIX}/{VERSION_CHUNK}"
SUPERVISOR_CHUNK = "@sup"

# A name is one key chunk: no '/', no wildcard characters, no leading '@' (verbatim),
# no zenoh-reserved characters. Kept conservative so names are also valid file/unit names.
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
# A selector chunk: a name, '*', '**', or a name with '*' standing for any substring
# (zenoh's "sub-chunk" wildcard, e.g. 'axis*' or 'h*').
_SELECTOR_CHUNK_RE = re.compile(r"^(\*\*|\*|[A-Za-z0-9_.\-]*\*?[A-Za-z0-9_.\-]*(\*[A-Za-z0-9_.\-]*)*)$")


class KeyError_(ValueError):
    """A key or name that is not part of the key space."""


InvalidKey = KeyError_


def validate_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is a legal single chunk, else raise :class:`InvalidKey`."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise InvalidKey(
            f"{what} {name!r} is not a legal key chunk: use 1-64 of [A-Za-z0-9_.-], "
            "not starting with '.' or '-', no '/', '*', '@', '$', '?' or '#'"
        )
    return name


def validate_selector_chunk(chunk: str, what: str = "selector") -> str:
    """Return ``chunk`` if it is a name or a wildcard chunk (``*``, ``**``, ``ax*``)."""
    if not isinstance(chunk, str) or not chunk or not _SELECTOR_CHUNK_RE.match(chunk) or "**" in chunk.replace("**", "", 1) or ("**" in chunk and chunk != "**"):
        raise InvalidKey(f"{what} {chunk!r} is not a legal name or wildcard chunk")
    return chunk


class KeyKind(str, Enum):
    AGENT_STATUS = "agent_status"
    AGENT_CMD = "agent_cmd"
    ALIVE = "alive"
    DRIVE_STATUS = "drive_status"
    DRIVE_EVENT = "drive_event"
    DRIVE_CMD = "drive_cmd"
    SUPERVISOR = "supervisor"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key taken apart. ``axis``/``op``/``name`` are None where the kind has none."""

    kind: KeyKind
    host: str | None = None
    axis: str | None = None
    op: str | None = None
    name: str | None = None


def agent_status(host: str) -> str:
    return f"{ROOT}/{validate_selector_chunk(host, 'host')}/agent"


def agent_cmd(host: str, op: str) -> str:
    return f"{ROOT}/{validate_selector_chunk(host, 'host')}/agent/cmd/{validate_selector_chunk(op, 'op')}"


def alive(host: str) -> str:
    return f"{ROOT}/{validate_selector_chunk(host, 'host')}/alive"


def drive_status(host: str, axis: str) -> str:
    return f"{ROOT}/{validate_selector_chunk(host, 'host')}/drive/{validate_selector_chunk(axis, 'axis')}/status"


def drive_event(host: str, axis: str) -> str:
    return f"{ROOT}/{validate_selector_chunk(host, 'host')}/drive/{validate_selector_chunk(axis, 'axis')}/event"


def drive_cmd(host: str, axis: str, op: str) -> str:
    return (
        f"{ROOT}/{validate_selector_chunk(host, 'host')}/drive/"
        f"{validate_selector_chunk(axis, 'axis')}/cmd/{validate_selector_chunk(op, 'op')}"
    )


def supervisor_alive(name: str) -> str:
    return f"{ROOT}/{SUPERVISOR_CHUNK}/{validate_selector_chunk(name, 'supervisor')}"


def parse(key: str) -> ParsedKey:
    """Parse a concrete key of the key space; raise :class:`InvalidKey` otherwise."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != PREFIX or parts[1] != VERSION_CHUNK:
        raise InvalidKey(f"key {key!r} is not under {ROOT}/")
    rest = parts[2:]
    if len(rest) == 2 and rest[0] == SUPERVISOR_CHUNK:
        return ParsedKey(KeyKind.SUPERVISOR, name=validate_name(rest[1], "supervisor"))
    host = validate_name(rest[0], "host")
    tail = rest[1:]
    if tail == ["agent"]:
        return ParsedKey(KeyKind.AGENT_STATUS, host=host)
    if tail == ["alive"]:
        return ParsedKey(KeyKind.ALIVE, host=host)
    if len(tail) == 3 and tail[:2] == ["agent", "cmd"]:
        return ParsedKey(KeyKind.AGENT_CMD, host=host, op=validate_name(tail[2], "op"))
    if len(tail) >= 3 and tail[0] == "drive":
        axis = validate_name(tail[1], "axis")
        if tail[2:] == ["status"]:
            return ParsedKey(KeyKind.DRIVE_STATUS, host=host, axis=axis)
        if tail[2:] == ["event"]:
            return ParsedKey(KeyKind.DRIVE_EVENT, host=host, axis=axis)
        if len(tail) == 4 and tail[2] == "cmd":
            return ParsedKey(KeyKind.DRIVE_CMD, host=host, axis=axis, op=validate_name(tail[3], "op"))
    raise InvalidKey(f"key {key!r} has no meaning in the {ROOT} key space")


# Simulation control (fault injection), a separate verbatim root so production ACLs deny it whole:
#   drives/@sim/<segment>/<slave>/<action>    slave = position (0-based) or '*'; action e.g. fault, unplug
SIM_ROOT = f"{PREFIX}/@sim"


def sim_control(segment: str, slave: int | str, action: str) -> str:
    """Key of a simulator's fault-injection queryable (``ecat-sim`` and the in-process sim bus)."""
    slave_chunk = str(slave) if isinstance(slave, int) else validate_selector_chunk(slave, "slave")
    return f"{SIM_ROOT}/{validate_selector_chunk(segment, 'segment')}/{slave_chunk}/{validate_selector_chunk(action, 'action')}"


# Wildcard selectors used by subscribers and fan-out queries.
ALL_DRIVE_STATUS = f"{ROOT}/*/drive/*/status"
ALL_DRIVE_EVENTS = f"{ROOT}/*/drive/*/event"
ALL_AGENT_STATUS = f"{ROOT}/*/agent"
ALL_ALIVE = f"{ROOT}/*/alive"
ALL_SUPERVISORS = f"{ROOT}/{SUPERVISOR_CHUNK}/*"
