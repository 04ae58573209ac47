"""Drive selectors and query planning: pure functions, no I/O.

A *selector* names drives the way key expressions do, over the two levels ``host/axis``:

- ``h1/x``        one drive
- ``h1/*``        every axis of host h1 (``h1`` alone means the same)
- ``*/x``         axis x on every host
- ``h*/axis?``    ``*`` inside a chunk stands for any run of characters, ``?`` for one character
- ``**``          every drive (``**`` matches any number of levels, as in zenoh)
- ``@name``       a named group (from the agents' ``AgentStatus.groups`` or a local table)

Patterns follow ``schemas.keys`` (``selector_to_keyexpr`` / ``selector_matches``, fnmatch
``[abc]`` classes too). Zenoh has no ``?`` and spells the sub-chunk wildcard ``$*``;
:func:`plan_queries` turns
a selection into the fewest key expressions that address exactly the selected drives, so that
one fan-out query per op reaches them all (one per host, or per drive, only when no key
expression can say "these and no others").
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

from schemas import keys


class SelectorError(ValueError):
    """A selector that is malformed, names an unknown group, or matches no known drive."""


@dataclass(frozen=True, order=True)
class DriveRef:
    """One drive, named by its agent's host and its axis."""

    host: str
    axis: str

    def __str__(self) -> str:
        return f"{self.host}/{self.axis}"

    @classmethod
    def parse(cls, text: str) -> "DriveRef":
        """Parse ``host/axis`` (concrete names only)."""
        parts = text.split("/")
        if len(parts) != 2:
            raise SelectorError(f"drive {text!r} is not of the form host/axis")
        try:
            return cls(keys.validate_name(parts[0], "host"), keys.validate_name(parts[1], "axis"))
        except keys.InvalidKey as exc:
            raise SelectorError(str(exc)) from None


@dataclass(frozen=True)
class Selector:
    """A parsed selector: a group name, or a normalised ``host/axis`` pattern."""

    text: str
    group: str | None = None
    pattern: str = ""  # 'host/axis' with fnmatch wildcards (schemas.keys selector syntax)

    @property
    def has_wildcards(self) -> bool:
        return any(c in self.pattern for c in "*?[")

    @property
    def chunks(self) -> tuple[str, str]:
        host, axis = self.pattern.split("/")
        return host, axis

    def matches(self, ref: DriveRef) -> bool:
        """True when this (non-group) selector matches ``ref``."""
        return self.group is None and keys.selector_matches(self.pattern, ref.host, ref.axis)

    def zenoh_pair(self) -> tuple[str, str] | None:
        """(host chunk, axis chunk) in zenoh syntax when one key expression addresses exactly
        the drives this selector matches, else None (``?`` and ``[..]`` have no zenoh form)."""
        if self.group is not None or "?" in self.pattern or "[" in self.pattern:
            return None
        return keys.selector_to_keyexpr(self.pattern)


def parse_selector(text: str) -> Selector:
    """Parse one selector; raise :class:`SelectorError` with the reason when it is malformed.

    Forms: ``@group``; ``**`` (all); ``host`` (all its axes); ``host/axis`` with ``*``, ``?``,
    ``[abc]`` wildcards on either side (``**`` on a side means ``*``).
    """
    if not isinstance(text, str) or not text.strip():
        raise SelectorError("empty selector (use '**' for every drive)")
    text = text.strip()
    if text.startswith("@"):
        name = text[1:]
        if not keys.is_name(name):
            raise SelectorError(f"selector {text!r}: group name {name!r} is not a legal name")
        return Selector(text=text, group=name)
    parts = text.split("/")
    if parts == ["**"]:
        parts = ["*", "*"]
    elif len(parts) == 1:
        parts = [parts[0], "*"]  # a bare host name means all its axes
    if len(parts) != 2:
        raise SelectorError(f"selector {text!r} has {len(parts)} levels; use host/axis, host, @group or **")
    pattern = "/".join(parts)
    try:
        keys.selector_to_keyexpr(pattern)
    except keys.InvalidKey as exc:
        raise SelectorError(str(exc)) from None
    return Selector(text=text, pattern=pattern)


def resolve(
    selectors: Iterable[str | Selector],
    roster: Iterable[DriveRef],
    groups: Mapping[str, Iterable[str]] | None = None,
    *,
    allow_empty: bool = False,
) -> list[DriveRef]:
    """Return the sorted drives of ``roster`` that any selector matches.

    Group members are ``host/axis`` strings; a member not in the roster is still selected (it
    will be reported missing rather than silently dropped). Raise :class:`SelectorError` for a
    malformed selector, an unknown group, or (unless ``allow_empty``) a selector matching nothing.
    """
    roster = sorted(set(roster))
    groups = groups or {}
    chosen: set[DriveRef] = set()
    parsed = [s if isinstance(s, Selector) else parse_selector(s) for s in selectors]
    if not parsed:
        raise SelectorError("no selector given (use '**' for every drive)")
    for sel in parsed:
        if sel.group is not None:
            if sel.group not in groups:
                known = ", ".join(sorted(groups)) or "none"
                raise SelectorError(f"unknown group {sel.group!r} (known groups: {known})")
            hits = {DriveRef.parse(m) for m in groups[sel.group]}
        else:
            hits = {r for r in roster if sel.matches(r)}
            if not sel.has_wildcards:
                # A concrete name outside the roster is still addressed: it will show as missing.
                hits.add(DriveRef(*sel.chunks))
        if not hits and not allow_empty:
            raise SelectorError(f"selector {sel.text!r} matches no known drive")
        chosen |= hits
    return sorted(chosen)


def drive_cmd_keyexpr(host: str, axis: str, op: str, principal: str | None = None) -> str:
    """A zenoh key expression for ``cmd/<op>`` of the drives (host, axis) selects (wildcards ok);
    with ``principal``, the authenticated form (``.../cmd/<op>/@sup/<principal>``)."""
    return keys.drive_cmd(host, axis, op, principal)


@dataclass(frozen=True)
class QueryPlan:
    """Key-expression pairs (host, axis) in zenoh syntax, each addressed by one query."""

    pairs: tuple[tuple[str, str], ...]

    def keyexprs(self, op: str, principal: str | None = None) -> list[str]:
        return [drive_cmd_keyexpr(h, a, op, principal) for h, a in self.pairs]


def plan_queries(
    selectors: Sequence[str | Selector],
    selected: Iterable[DriveRef],
    host_axes: Mapping[str, Iterable[str]] | None = None,
) -> QueryPlan:
    """The fewest (host, axis) key expressions that address the selection and nothing else.

    A selector expressible in zenoh syntax is sent as is (one query, whatever the fleet size;
    a drive that appears later and matches it is addressed too, as the selector asked).
    Other selectors (``?``, groups) become one query per host when every axis of that host is
    selected, according to ``host_axes`` (the agents' own complete axis lists,
    ``AgentStatus.axes``; never a guess from status seen so far), else one query per drive.
    """
    parsed = [s if isinstance(s, Selector) else parse_selector(s) for s in selectors]
    selected = sorted(set(selected))
    roster_by_host = {h: set(a) for h, a in (host_axes or {}).items()}
    pairs: list[tuple[str, str]] = []
    covered: set[DriveRef] = set()
    rest: list[Selector] = []
    for sel in parsed:
        pair = sel.zenoh_pair()
        if pair is None:
            rest.append(sel)
        elif pair not in pairs:
            pairs.append(pair)
            covered |= {r for r in selected if sel.matches(r)}
    if ("*", "*") in pairs:
        return QueryPlan((("*", "*"),))
    if rest:
        by_host: dict[str, list[str]] = {}
        for r in selected:
            if r not in covered:
                by_host.setdefault(r.host, []).append(r.axis)
        for host in sorted(by_host):
            axes = sorted(by_host[host])
            if roster_by_host.get(host) and set(axes) >= roster_by_host[host]:
                pairs.append((host, "*"))
            else:
                pairs.extend((host, a) for a in axes)
    return QueryPlan(tuple(pairs))


@dataclass(frozen=True)
class Selection:
    """Drives chosen by selectors at one moment, and the queries that address exactly them."""

    selectors: tuple[str, ...]
    drives: tuple[DriveRef, ...]
    plan: QueryPlan

    def __len__(self) -> int:
        return len(self.drives)


def exact_selection(refs: Iterable[DriveRef], host_axes: Mapping[str, Iterable[str]], *,
                    per_host: bool = False) -> Selection:
    """A selection of exactly ``refs``: one ``<host>/drive/*`` query per host where ``host_axes``
    says the host is whole, else one per drive. ``per_host``: one ``<host>/drive/*`` query per
    host whatever the axes (for a command the agent narrows itself)."""
    refs = sorted(set(refs))
    sels = [Selector(str(r), pattern=str(r)) for r in refs]
    if per_host:
        hosts = sorted({r.host for r in refs})
        return Selection(tuple(s.text for s in sels), tuple(refs), QueryPlan(tuple((h, "*") for h in hosts)))
    # Concrete names are each expressible; group them per host to save queries.
    by_host: dict[str, list[str]] = {}
    for r in refs:
        by_host.setdefault(r.host, []).append(r.axis)
    pairs: list[tuple[str, str]] = []
    for h, ax in sorted(by_host.items()):
        whole = set(host_axes.get(h) or ())
        if whole and set(ax) >= whole:
            pairs.append((h, "*"))
        else:
            pairs.extend((h, a) for a in sorted(ax))
    return Selection(tuple(s.text for s in sels), tuple(refs), QueryPlan(tuple(pairs)))


def _close(word: str, candidates: Iterable[str], n: int = 3) -> list[str]:
    return difflib.get_close_matches(word, sorted(set(candidates)), n=n, cutoff=0.6)


def unknown_selector_problems(selectors: Iterable[str], universe: Iterable[DriveRef],
                              groups: Mapping[str, Iterable[str]] | None = None) -> list[str]:
    """Why each selector names no known drive, with "did you mean" hints (pure).

    ``universe``: the drives that exist or are expected (live roster plus the expected fleet).
    A concrete ``host/axis`` outside it, or a wildcard matching none of it, is a problem: a bare
    axis name given as a host (``axis1`` -> ``*/axis1``), a misspelt name (closest names), an
    unknown group. Returns one message per problem; empty when every selector is known.
    """
    universe = sorted(set(universe))
    hosts = {r.host for r in universe}
    axes = {r.axis for r in universe}
    problems = []
    for text in selectors:
        sel = parse_selector(text)
        if sel.group is not None:
            if groups is not None and sel.group not in groups:
                hint = _close(sel.group, groups)
                problems.append(f"unknown group {sel.text!r}" + (f"; did you mean {', '.join('@' + g for g in hint)}?"
                                                                 if hint else f" (known: {', '.join(sorted(groups)) or 'none'})"))
            continue
        if any(sel.matches(r) for r in universe):
            continue
        host, axis = sel.chunks
        hints: list[str] = []
        if "/" not in sel.text and axis == "*" and sel.text in axes:
            hints.append(f"*/{sel.text}")  # an axis name given alone reads as a host name
        if not any(c in host for c in "*?["):
            if host in hosts:
                on_host = sorted(r.axis for r in universe if r.host == host)
                hints += [f"{host}/{a}" for a in _close(axis, on_host)]
                what = f"{host} has no axis {axis!r} (its axes: {', '.join(on_host)})"
            else:
                hints += [f"{h}/{axis}" for h in _close(host, hosts)]
                what = f"no host {host!r} (known: {', '.join(sorted(hosts)) or 'none'})"
        else:
            hints += [f"{host}/{a}" for a in _close(axis, axes)] if axis != "*" else []
            what = "matches no known drive"
        msg = f"selector {sel.text!r}: {what}"
        if hints:
            msg += f"; did you mean {', '.join(repr(h) for h in dict.fromkeys(hints))}?"
        problems.append(msg)
    return problems
