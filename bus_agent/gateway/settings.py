"""What the gateway reads from the agent's configuration once, and what it needs of the cycle.

:class:`GatewaySettings` is plain data (it crosses to the gateway process as keyword arguments);
every part of :class:`bus_agent.gateway.gateway.Gateway` is given it and only reads it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, Sequence

from bus_agent import runtime as rt

#: Drive states that count as bad: a drive in them is published first, and a remote group
#: member in them triggers the group here.
BAD_STATES = ("fault", "fault_reaction_active")


class CycleLike(Protocol):
    """What the gateway needs from the cycle (``bus_agent.cycle.cycle.Cycle``)."""

    snapshot_sink: Callable[[rt.CycleSnapshot], None] | None

    @property
    def latest(self) -> rt.CycleSnapshot | None: ...

    def submit(self, cmd: rt.DriveCommand | rt.AgentCommand) -> bool: ...

    def trigger_group(self, group: str, reason: str) -> None: ...


@dataclass(frozen=True)
class GatewaySettings:
    host: str
    axes: tuple[str, ...]                      # in slave order
    heartbeat_s: float = 1.0
    agent_period_s: float = 1.0
    motion_period_s: float = 0.1
    backend: str = "sim"
    cycle_us: int = 1000
    groups: Mapping[str, Sequence[str]] = field(default_factory=dict)   # name -> "host/axis"
    lease_reaction: Mapping[str, str] = field(default_factory=dict)     # axis -> LEASE_REACTION_OPS key
    lease_ttl_s: Mapping[str, float] = field(default_factory=dict)      # axis -> default ttl
    instance: str = ""              # this agent process' id ('' = a new random one)
    check_host: bool = True         # refuse to start while another agent holds the host name
    has_connect: bool = False       # the session has connect endpoints (wait for a link first)
    secure: bool = False  # --pki: serve only authenticated command keys (requester from the key)
    #: SCHED_FIFO of gw-publish and gw-command (0: off). Set only for the gateway process (its own
    #: GIL); threads of the cycle process keep ``realtime.helper_priority``.
    rt_priority: int = 0
