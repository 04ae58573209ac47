"""The ``ecat`` backend's per-host bed: a network namespace holding an EtherCAT veth pair (root).

Host ``i`` of a twin with prefix ``P`` is namespace ``P h i`` (``tw1234h1``) with the pair
``P i m`` (master end, for the agent's pysoem) / ``P i s`` (``ecat-sim``'s end) inside it, like a
host of the multi-host bed (``bus_agent.sim.netns``). The host reaches the router only through
its twin link (a UNIX socket, which crosses namespaces), so cutting the link isolates it.
Deleting the namespace deletes the pair with it.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass

from bus_agent.sim.netns import NetnsError, netns_del, netns_exists, pair_names, veth_down, veth_up


@dataclass(frozen=True)
class EcatHost:
    """Namespace and EtherCAT pair of one twin host."""

    netns: str
    master: str
    sim: str

    def exec_argv(self, *argv: str) -> list[str]:
        """``argv`` run inside this host's namespace."""
        return ["ip", "netns", "exec", self.netns, *argv]


def ecat_plan(prefix: str, index: int) -> EcatHost:
    """Names for host ``index`` (1-based) of the twin ``prefix`` (pure)."""
    master, sim = pair_names(prefix, index)
    return EcatHost(netns=f"{prefix}h{index}", master=master, sim=sim)


def prerequisites() -> str | None:
    """Why the ecat backend cannot run here, or None."""
    if os.geteuid() != 0:
        return "the ecat backend needs root (network namespaces, veth pairs, raw sockets)"
    if shutil.which("ip") is None:
        return "the ecat backend needs iproute2 (`ip`)"
    return None


def ecat_up(host: EcatHost) -> None:
    """Create the namespace and the pair inside it (both ends up). Raises NetnsError."""
    veth_up(host.master, host.sim, master_netns=host.netns, sim_netns=host.netns)


def ecat_down(host: EcatHost) -> None:
    """Remove the namespace (and the pair in it); also a pair left half-made in the root namespace."""
    veth_down(host.master)
    netns_del(host.netns)
    if netns_exists(host.netns):
        raise NetnsError(f"namespace {host.netns} still exists after delete")
