"""Drive groups: who reacts when a member faults or is lost. Pure; cycle-safe.

A group is a name and a list of members ``host/axis``; members may live on other hosts. On the
host where a member faults or is lost, the other *local* members react in the same cycle
(the cycle applies the reflex); the gateway carries the trigger to the other hosts, whose cycles
call :meth:`bus_agent.cycle.cycle.Cycle.trigger_group`, so their members react within milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping


@dataclass(frozen=True)
class Group:
    name: str
    members: tuple[str, ...]        # "host/axis", as configured
    local_axes: tuple[str, ...]     # axes of this host, in configuration order
    remote_members: tuple[str, ...]


class Groups:
    """Group membership seen from one host."""

    def __init__(self, host: str, groups: Mapping[str, Iterable[str]], local_axes: Iterable[str]) -> None:
        axes = set(local_axes)
        self.host = host
        self.groups: dict[str, Group] = {}
        by_axis: dict[str, list[str]] = {}
        for name, members in groups.items():
            members = tuple(members)
            local = tuple(m.split("/", 1)[1] for m in members if m.split("/", 1)[0] == host
                          and m.split("/", 1)[1] in axes)
            remote = tuple(m for m in members if m.split("/", 1)[0] != host)
            self.groups[name] = Group(name, members, local, remote)
            for a in local:
                by_axis.setdefault(a, []).append(name)
        self._by_axis = {a: tuple(g) for a, g in by_axis.items()}

    def of_axis(self, axis: str) -> tuple[str, ...]:
        """Names of the groups ``axis`` (a local axis) belongs to."""
        return self._by_axis.get(axis, ())

    def local_members(self, group: str) -> tuple[str, ...]:
        g = self.groups.get(group)
        return g.local_axes if g else ()

    def reacting(self, group: str, origin_axis: str | None = None) -> tuple[str, ...]:
        """Local members that react to a trigger of ``group`` (all but the origin)."""
        return tuple(a for a in self.local_members(group) if a != origin_axis)

    def as_dict(self) -> dict[str, list[str]]:
        """name -> members, for AgentStatus.groups."""
        return {name: list(g.members) for name, g in self.groups.items()}
