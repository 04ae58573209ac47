"""veth pairs and network namespaces for simulated segments (root; idempotent).

    python -m bus_agent.sim.netns up   --prefix zd --count 2 [--netns]
    python -m bus_agent.sim.netns down --prefix zd --count 2 [--netns]

Pair ``i`` is ``<prefix><i>m`` (master side: give it to pysoem) and ``<prefix><i>s`` (simulator
side: give it to ``ecat-sim``). With ``--netns`` each end lives in its own namespace
``<prefix><i>m`` / ``<prefix><i>s`` so test hosts stay apart. Re-running ``up`` or ``down``
is safe. SOEM does not bring links up: ``up`` does, and disables IPv6 on both ends so the
kernel sends no router solicitations on them.
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys

log = logging.getLogger(__name__)

IFNAMSIZ = 15


class NetnsError(RuntimeError):
    pass


def _ip(*args: str, netns: str | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = ["ip", *(["-n", netns] if netns else []), *args]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if check and proc.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: {proc.stderr.strip()}")
    return proc


def _check_name(name: str) -> str:
    if not name or len(name) > IFNAMSIZ or not all(c.isalnum() or c in "-_." for c in name):
        raise NetnsError(f"interface/namespace name {name!r}: 1..{IFNAMSIZ} of [A-Za-z0-9_.-]")
    return name


def link_exists(name: str, netns: str | None = None) -> bool:
    return _ip("link", "show", "dev", name, netns=netns, check=False).returncode == 0


def netns_exists(name: str) -> bool:
    return os.path.exists(f"/run/netns/{name}")


def netns_add(name: str) -> None:
    """Create namespace ``name`` (no-op if it exists) with loopback up."""
    _check_name(name)
    if not netns_exists(name):
        _ip("netns", "add", name)
    _ip("link", "set", "lo", "up", netns=name)


def netns_del(name: str) -> None:
    if netns_exists(name):
        _ip("netns", "del", name, check=False)


def _disable_ipv6(ifname: str, netns: str | None) -> None:
    path = f"net.ipv6.conf.{ifname}.disable_ipv6=1"
    cmd = (["ip", "netns", "exec", netns] if netns else []) + ["sysctl", "-qw", path]
    subprocess.run(cmd, capture_output=True)


def veth_up(master: str, sim: str, *, master_netns: str | None = None, sim_netns: str | None = None) -> None:
    """Create the pair (if missing), move ends into namespaces, bring both up."""
    _check_name(master)
    _check_name(sim)
    if not link_exists(master, master_netns):
        if link_exists(master) or link_exists(sim):  # half-made by an earlier run
            veth_down(master)
            veth_down(sim)
        _ip("link", "add", master, "type", "veth", "peer", "name", sim)
        for end, ns in ((master, master_netns), (sim, sim_netns)):
            if ns:
                netns_add(ns)
                _ip("link", "set", end, "netns", ns)
    for end, ns in ((master, master_netns), (sim, sim_netns)):
        _disable_ipv6(end, ns)
        _ip("link", "set", end, "up", netns=ns)
    log.info("veth %s <-> %s up", master, sim)


def veth_down(name: str, netns: str | None = None) -> None:
    """Delete the pair that ``name`` belongs to (both ends go). No-op if absent."""
    if link_exists(name, netns):
        _ip("link", "del", name, netns=netns, check=False)


def pair_names(prefix: str, i: int) -> tuple[str, str]:
    return _check_name(f"{prefix}{i}m"), _check_name(f"{prefix}{i}s")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bus_agent.sim.netns", description=__doc__.split("\n\n")[0])
    p.add_argument("command", choices=("up", "down"))
    p.add_argument("--prefix", default="zd")
    p.add_argument("--count", type=int, default=1)
    p.add_argument("--netns", action="store_true", help="one namespace per end, named like the interface")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        for i in range(args.count):
            m, s = pair_names(args.prefix, i)
            if args.command == "up":
                veth_up(m, s, master_netns=m if args.netns else None, sim_netns=s if args.netns else None)
                print(f"{m} {s}")
            else:
                veth_down(m, m if args.netns else None)
                veth_down(s, s if args.netns else None)
                if args.netns:
                    netns_del(m)
                    netns_del(s)
    except NetnsError as exc:
        print(f"netns: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
