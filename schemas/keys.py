"""The key space, version 1: the only place keys are built and parsed.

Layout (every level fixed, so keys parse without guessing)::

    drives/@v1/<host>/agent                   agent status
    drives/@v1/<host>/agent/cmd/<op>          agent commands (nmt)
    drives/@v1/<host>/alive                   agent liveliness token
    drives/@v1/<host>/drive/<axis>/status     drive status (put on change + heartbeat; get)
    drives/@v1/<host>/drive/<axis>/event      drive events
    drives/@v1/<host>/drive/<axis>/cmd/<op>   drive commands
    drives/@v1/<host>/drive/<axis>/cmd/<op>/@sup/<principal>   drive commands, authenticated
    drives/@v1/<host>/agent/cmd/<op>/@sup/<principal>          agent commands, authenticated
    drives/@v1/@sup/<name>                    supervisor liveliness token

A command key ending in ``@sup/<principal>`` names who asks. On a secure deployment the router's
ACL lets each principal query only keys that end in its own name (``bus_agent.security.roles``),
so the agent takes the requester from the key, never from the payload.

``@v1`` and ``@sup`` are verbatim chunks: wildcards never match them.
Host, axis and supervisor names are single legal chunks (see :func:`validate_name`).
Every builder also takes selector chunks (``*``, ``**``, ``ax*``; see
:func:`validate_selector_chunk`) and returns a valid zenoh key expression (``ax*`` is written
``ax$*``). User selectors ``host/axis`` with fnmatch wildcards go through
:func:`selector_to_keyexpr` (for the query) and :func:`selector_matches` (to filter replies).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import re
from dataclasses import dataclass
from enum import Enum

PREFIX = "drives"
VERSION_CHUNK = "@v1"
ROOT = f"{PREFIX}/{VERSION_CHUNK}"
SUPERVISOR_CHUNK = "@sup"

# Matched with fullmatch: '$' alone would accept a trailing newline.
# A name is one key chunk: no '/', no wildcard characters, no leading '@' (verbatim),
# no zenoh-reserved characters. Kept conservative so names are also valid file/unit names.
NAME_MAX_LEN = 64
_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
#: The name rule as a regular expression (JSON Schema ``pattern``).
NAME_PATTERN = _NAME_RE.pattern
# One chunk of a selector once every sub-chunk wildcard is written '*': name characters and
# single '*'s, not starting with '.', '-' or '@'. '**' alone is handled before this rule.
_PATTERN_CHUNK_RE = re.compile(r"^[A-Za-z0-9_*][A-Za-z0-9_.\-*]*$")


class KeyError_(ValueError):
    """A key or name that is not part of the key space."""


InvalidKey = KeyError_


def validate_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is a legal single chunk, else raise :class:`InvalidKey`."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        raise InvalidKey(
            f"{what} {name!r} is not a legal key chunk: use 1-64 of [A-Za-z0-9_.-], "
            "not starting with '.' or '-', no '/', '*', '@', '$', '?' or '#'"
        )
    return name


def is_name(name: object) -> bool:
    """True if ``name`` is a legal single chunk (see :func:`validate_name`)."""
    return isinstance(name, str) and _NAME_RE.fullmatch(name) is not None


def _selector_chunk_error(chunk: object, what: str, why: str) -> InvalidKey:
    return InvalidKey(
        f"{what} {chunk!r} is not a legal name or wildcard chunk: {why} "
        "(use a name of [A-Za-z0-9_.-], '*', '**', or a name with '*' for any substring, e.g. 'ax*')"
    )


def validate_selector_chunk(chunk: str, what: str = "selector") -> str:
    """Return ``chunk`` if it is a name or a wildcard chunk, else raise :class:`InvalidKey`.

    Accepted: a legal name (:func:`validate_name`), ``*`` (one chunk), ``**`` (any number of
    chunks), or a name with ``*`` standing for any substring (``ax*``, ``h*1``); zenoh's own
    spelling of that sub-chunk wildcard, ``$*``, is accepted too. Rejected: ``/``, ``?``, ``#``,
    any other ``$``, a leading ``@`` (verbatim chunks are never selected), ``**`` inside a
    chunk, adjacent wildcards and the empty string. The chunk is returned unchanged; the key
    builders turn it into a zenoh key expression chunk (:func:`zenoh_chunk`).
    """
    if not isinstance(chunk, str):
        raise _selector_chunk_error(chunk, what, f"expected a string, got {type(chunk).__name__}")
    if chunk in ("*", "**"):
        return chunk
    if not chunk:
        raise _selector_chunk_error(chunk, what, "empty")
    for bad in ("/", "?", "#"):
        if bad in chunk:
            raise _selector_chunk_error(chunk, what, f"{bad!r} is not allowed")
    if chunk.startswith("@"):
        raise _selector_chunk_error(chunk, what, "a leading '@' marks a verbatim chunk")
    plain = chunk.replace("$*", "*")
    if "$" in plain:
        raise _selector_chunk_error(chunk, what, "'$' is only allowed as zenoh's '$*'")
    if "**" in plain:
        raise _selector_chunk_error(chunk, what, "'**' must stand alone, and wildcards must not be adjacent")
    if len(plain) > NAME_MAX_LEN or not _PATTERN_CHUNK_RE.fullmatch(plain):
        raise _selector_chunk_error(chunk, what, "illegal character, leading '.'/'-', or longer than 64")
    return chunk


def zenoh_chunk(chunk: str, what: str = "selector") -> str:
    """Validate a selector chunk and spell it as zenoh wants it.

    zenoh writes a sub-chunk wildcard ``$*`` (``ax*`` is an invalid key expression), a whole
    chunk ``*``: so ``ax*`` -> ``ax$*``, ``$*`` -> ``*``, names, ``*`` and ``**`` unchanged.
    """
    validate_selector_chunk(chunk, what)
    plain = chunk.replace("$*", "*")
    if plain in ("*", "**"):
        return plain
    return plain.replace("*", "$*")


# User selectors 'host/axis' with fnmatch wildcards: '*', '?', '[seq]', '[!seq]'.
_SEL_TOKEN_RE = re.compile(r"\[!?\]?[^\]]*\]|\$\*|.", re.S)
_SEL_LITERAL_RE = re.compile(r"^[A-Za-z0-9_.\-]$")
_SEL_CLASS_RE = re.compile(r"^\[!?[A-Za-z0-9_.\-]+\]$")


def _selector_part(part: str, what: str, selector: str) -> tuple[str, str]:
    """One side of a user selector -> (zenoh chunk, fnmatch pattern)."""
    if part in ("*", "**"):
        return "*", "*"
    if not part:
        raise InvalidKey(f"selector {selector!r}: {what} is empty (use '*' for any {what})")
    if part.startswith("@"):
        raise InvalidKey(f"selector {selector!r}: {what} {part!r} starts with '@' (verbatim chunks are never selected)")
    literal = 0
    zparts: list[str] = []  # literal runs and '*' markers
    fparts: list[str] = []
    for tok in _SEL_TOKEN_RE.findall(part):
        if tok in ("*", "$*"):
            if fparts[-1:] == ["*"]:
                continue  # 'a**b' means the same as 'a*b'
            fparts.append("*")
            wild = True
        elif tok == "?" or (tok.startswith("[") and len(tok) > 1):
            if tok != "?" and not _SEL_CLASS_RE.fullmatch(tok):
                raise InvalidKey(f"selector {selector!r}: {what} character class {tok!r} may hold only [A-Za-z0-9_.-]")
            fparts.append(tok)
            wild = True
        elif _SEL_LITERAL_RE.fullmatch(tok):
            fparts.append(tok)
            literal += 1
            wild = False
        else:
            raise InvalidKey(
                f"selector {selector!r}: {what} {part!r} has illegal character {tok!r} "
                "(names use [A-Za-z0-9_.-]; wildcards are '*', '?', '[abc]', '[!abc]')"
            )
        if wild:
            if zparts[-1:] != ["*"]:
                zparts.append("*")
        else:
            zparts.append(tok)
    if literal > NAME_MAX_LEN:
        raise InvalidKey(f"selector {selector!r}: {what} {part!r} is longer than {NAME_MAX_LEN} characters")
    if fparts and fparts[0] in (".", "-"):
        raise InvalidKey(f"selector {selector!r}: {what} {part!r} starts with {fparts[0]!r}, which no name does")
    zchunk = "".join(zparts)
    return zenoh_chunk(zchunk, what), "".join(fparts)


def _split_selector(selector: str) -> tuple[str, str]:
    if not isinstance(selector, str):
        raise InvalidKey(f"selector {selector!r} must be a string 'host/axis'")
    parts = selector.split("/")
    if len(parts) == 1 and parts[0]:
        return parts[0], "*"  # 'h1' is every axis of h1, '**' everything
    if len(parts) != 2:
        raise InvalidKey(
            f"selector {selector!r} must be 'host/axis' (or 'host' for all its axes) with at most "
            "one '/', e.g. 'h1/x', 'h1/*', 'h1', '*/x', 'h*/axis?'"
        )
    return parts[0], parts[1]


def selector_to_keyexpr(selector: str) -> tuple[str, str]:
    """Turn a user selector ``host/axis`` into zenoh-ready ``(host_chunk, axis_chunk)``.

    A selector without ``/`` is a host: ``h1`` means ``h1/*`` and ``**`` every drive.

    Both sides take fnmatch wildcards: ``*`` (any substring), ``?`` (one character),
    ``[abc]``/``[!abc]`` (one character of/not of a set); ``**`` means ``*``. zenoh has no
    single-character wildcard, so ``?`` and classes widen to ``$*`` (``*`` when the whole chunk
    is wild): the query may return more than asked, and callers keep only the replies for
    which :func:`selector_matches` is true. The chunks are accepted by every key builder.
    Examples: ``h1/*`` -> (``h1``, ``*``); ``h*/axis?`` -> (``h$*``, ``axis$*``).
    Raise :class:`InvalidKey` for anything else.
    """
    host, axis = _split_selector(selector)
    return _selector_part(host, "host", selector)[0], _selector_part(axis, "axis", selector)[0]


def selector_matches(selector: str, host: str, axis: str) -> bool:
    """True if drive ``host/axis`` is selected by ``selector`` (fnmatch, case-sensitive).

    Raise :class:`InvalidKey` if the selector is malformed (see :func:`selector_to_keyexpr`).
    """
    h, a = _split_selector(selector)
    hpat = _selector_part(h, "host", selector)[1]
    apat = _selector_part(a, "axis", selector)[1]
    return (
        isinstance(host, str)
        and isinstance(axis, str)
        and fnmatch.fnmatchcase(host, hpat)
        and fnmatch.fnmatchcase(axis, apat)
    )


class KeyKind(str, Enum):
    AGENT_STATUS = "agent_status"
    AGENT_CMD = "agent_cmd"
    ALIVE = "alive"
    DRIVE_STATUS = "drive_status"
    DRIVE_EVENT = "drive_event"
    DRIVE_CMD = "drive_cmd"
    SUPERVISOR = "supervisor"
    AGENT_RECORDING = "agent_recording"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key taken apart. ``axis``/``op``/``name`` are None where the kind has none."""

    kind: KeyKind
    host: str | None = None
    axis: str | None = None
    op: str | None = None
    name: str | None = None
    principal: str | None = None  # commands: the ``@sup/<principal>`` tail, None without it


def agent_status(host: str) -> str:
    """Key of the agent status of ``host`` (message ``agent_status``)."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/agent"


def _by(principal: str | None) -> str:
    return "" if principal is None else f"/{SUPERVISOR_CHUNK}/{zenoh_chunk(principal, 'principal')}"


def agent_cmd(host: str, op: str, principal: str | None = None) -> str:
    """Key of agent command ``op`` on ``host`` (a query; op ``nmt``); with ``principal``, the
    authenticated form ending in ``@sup/<principal>``."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/agent/cmd/{zenoh_chunk(op, 'op')}{_by(principal)}"


def agent_recording(host: str) -> str:
    """Key of the flight recorder of ``host`` (a query with a ``recording_request``)."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/agent/recording"


def alive(host: str) -> str:
    """Key of the liveliness token of the agent on ``host``."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/alive"


def drive_status(host: str, axis: str) -> str:
    """Key of the status of drive ``host/axis`` (message ``drive_status``)."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/drive/{zenoh_chunk(axis, 'axis')}/status"


def drive_event(host: str, axis: str) -> str:
    """Key of the events of drive ``host/axis`` (message ``event``)."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/drive/{zenoh_chunk(axis, 'axis')}/event"


def drive_cmd(host: str, axis: str, op: str, principal: str | None = None) -> str:
    """Key of drive command ``op`` for ``host/axis`` (a query with a ``command_request``); with
    ``principal``, the authenticated form ending in ``@sup/<principal>``."""
    return (
        f"{ROOT}/{zenoh_chunk(host, 'host')}/drive/"
        f"{zenoh_chunk(axis, 'axis')}/cmd/{zenoh_chunk(op, 'op')}{_by(principal)}"
    )


def command_principal(key: str) -> str | None:
    """The principal of a command key or key expression (its ``@sup/<principal>`` tail), None
    if it has none. Raises :class:`InvalidKey` when the principal chunk is not a plain name
    (a wildcard there would stand for anyone)."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[-2] != SUPERVISOR_CHUNK or "cmd" not in parts[:-2]:
        return None
    return validate_name(parts[-1], "principal")


def host_tree(host: str) -> str:
    """Every key of ``host`` without a verbatim chunk below it (``drives/@v1/<host>/**``):
    status, events, agent status, its token and the unauthenticated command keys."""
    return f"{ROOT}/{zenoh_chunk(host, 'host')}/**"


def supervisor_alive(name: str) -> str:
    """Key of the liveliness token of supervisor ``name`` (held while it holds leases)."""
    return f"{ROOT}/{SUPERVISOR_CHUNK}/{zenoh_chunk(name, 'supervisor')}"


def parse(key: str) -> ParsedKey:
    """Parse a concrete key of the key space; raise :class:`InvalidKey` otherwise."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != PREFIX or parts[1] != VERSION_CHUNK:
        raise InvalidKey(f"key {key!r} is not under {ROOT}/")
    rest = parts[2:]
    if len(rest) == 2 and rest[0] == SUPERVISOR_CHUNK:
        return ParsedKey(KeyKind.SUPERVISOR, name=validate_name(rest[1], "supervisor"))
    principal = None
    if len(rest) > 2 and rest[-2] == SUPERVISOR_CHUNK and "cmd" in rest:
        principal = validate_name(rest[-1], "principal")
        rest = rest[:-2]
    parsed = _parse_host_key(key, rest)
    if principal is None:
        return parsed
    if parsed.kind not in (KeyKind.DRIVE_CMD, KeyKind.AGENT_CMD):
        raise InvalidKey(f"key {key!r}: only command keys end in {SUPERVISOR_CHUNK}/<principal>")
    return dataclasses.replace(parsed, principal=principal)


def _parse_host_key(key: str, rest: list[str]) -> ParsedKey:
    host = validate_name(rest[0], "host")
    tail = rest[1:]
    if tail == ["agent"]:
        return ParsedKey(KeyKind.AGENT_STATUS, host=host)
    if tail == ["agent", "recording"]:
        return ParsedKey(KeyKind.AGENT_RECORDING, host=host)
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
    if isinstance(slave, bool) or (isinstance(slave, int) and not 0 <= slave <= 65535):
        raise InvalidKey(f"slave {slave!r} is not a slave position 0..65535 or a selector chunk")
    slave_chunk = str(slave) if isinstance(slave, int) else zenoh_chunk(slave, "slave")
    return f"{SIM_ROOT}/{zenoh_chunk(segment, 'segment')}/{slave_chunk}/{zenoh_chunk(action, 'action')}"


# Wildcard selectors used by subscribers and fan-out queries.
ALL_DRIVE_STATUS = f"{ROOT}/*/drive/*/status"
ALL_DRIVE_EVENTS = f"{ROOT}/*/drive/*/event"
ALL_AGENT_STATUS = f"{ROOT}/*/agent"
ALL_ALIVE = f"{ROOT}/*/alive"
ALL_SUPERVISORS = f"{ROOT}/{SUPERVISOR_CHUNK}/*"
#: Every simulator control key (what production ACLs deny).
ALL_SIM = f"{SIM_ROOT}/**"


def parse_sim_control(key: str) -> tuple[str, int, str]:
    """Parse a concrete :func:`sim_control` key into (segment, slave position, action)."""
    parts = str(key).split("/")
    if len(parts) != 5 or "/".join(parts[:2]) != SIM_ROOT:
        raise InvalidKey(f"key {key!r} is not a {SIM_ROOT}/<segment>/<slave>/<action> key")
    segment = validate_name(parts[2], "segment")
    if not parts[3].isdigit() or not 0 <= int(parts[3]) <= 65535:
        raise InvalidKey(f"key {key!r}: slave {parts[3]!r} is not a slave position 0..65535")
    return segment, int(parts[3]), validate_name(parts[4], "action")


@dataclass(frozen=True)
class KeyInfo:
    """One row of the key table: the pattern, what lives there, and who declares it."""

    pattern: str
    kind: str
    meaning: str
    zenoh: str  # put, queryable, liveliness token
    message: str = ""  # message type name carried, '' if none


#: The key space as data: source of ``python -m schemas keys`` and docs/contract.md.
KEY_TABLE: tuple[KeyInfo, ...] = (
    KeyInfo(f"{ROOT}/<host>/agent", KeyKind.AGENT_STATUS.value,
            "agent status: AL states, cycle statistics, leases", "put (periodic)", "agent_status"),
    KeyInfo(f"{ROOT}/<host>/agent/cmd/<op>", KeyKind.AGENT_CMD.value,
            "agent commands; op: nmt", "queryable", "command_request -> command_reply"),
    KeyInfo(f"{ROOT}/<host>/agent/recording", KeyKind.AGENT_RECORDING.value,
            "flight recorder: the last seconds of every cycle, or a window frozen around a trigger",
            "queryable", "recording_request -> recording"),
    KeyInfo(f"{ROOT}/<host>/alive", KeyKind.ALIVE.value,
            "liveliness token of the agent", "liveliness token"),
    KeyInfo(f"{ROOT}/<host>/drive/<axis>/status", KeyKind.DRIVE_STATUS.value,
            "drive status, on change and as a heartbeat; a get returns the current one",
            "put + queryable", "drive_status"),
    KeyInfo(f"{ROOT}/<host>/drive/<axis>/event", KeyKind.DRIVE_EVENT.value,
            "transitions, faults, command outcomes", "put", "event"),
    KeyInfo(f"{ROOT}/<host>/drive/<axis>/cmd/<op>", KeyKind.DRIVE_CMD.value,
            "drive commands; one reply per addressed drive on its own key",
            "queryable", "command_request -> command_reply"),
    KeyInfo(f"{ROOT}/<host>/drive/<axis>/cmd/<op>/{SUPERVISOR_CHUNK}/<principal>", KeyKind.DRIVE_CMD.value,
            "drive commands from an authenticated principal (the ACL admits only its own name); "
            "the only command keys an agent serves with --pki", "queryable", "command_request -> command_reply"),
    KeyInfo(f"{ROOT}/<host>/agent/cmd/<op>/{SUPERVISOR_CHUNK}/<principal>", KeyKind.AGENT_CMD.value,
            "agent commands from an authenticated principal", "queryable", "command_request -> command_reply"),
    KeyInfo(f"{ROOT}/{SUPERVISOR_CHUNK}/<name>", KeyKind.SUPERVISOR.value,
            "liveliness token of a supervisor that holds leases", "liveliness token"),
    KeyInfo(f"{SIM_ROOT}/<segment>/<slave>/<action>", "sim_control",
            "simulator fault injection (test beds only; deny in production ACLs)", "queryable"),
)
