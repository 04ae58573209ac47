"""veth pairs and network namespaces for simulated segments (root; idempotent).

    python -m bus_agent.sim.netns up   --prefix zd --count 2 [--netns]
    python -m bus_agent.sim.netns down --prefix zd --count 2 [--netns]

Pair ``i`` is ``<prefix><i>m`` (master side: give it to pysoem) and ``<prefix><i>s`` (simulator
side: give it to ``ecat-sim``). With ``--netns`` each end lives in its own namespace
``<prefix><i>m`` / ``<prefix><i>s`` so test hosts stay apart. Re-running ``up`` or ``down``
is safe. SOEM does not bring links up: ``up`` does, and disables IPv6 on both ends so the
kernel sends no router solicitations on them.

The multi-host bed (``multihost_plan`` / ``multihost_up`` / ``multihost_down``; also
``python -m bus_agent.sim.netns multihost up|down --prefix mh --hosts 2 [--extra sup]`` and
deploy/multihost.sh) makes each host a namespace ``<prefix>h<i>`` with an address on a private
/24 (``lan0``, default 10.213.7.<i>), plugged into a Linux bridge in namespace ``<prefix>sw``,
plus an EtherCAT veth pair ``ecm0`` (master) / ``ecs0`` (ecat-sim) inside the host namespace.
No namespace has a default route: the subnet never reaches the outside.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import subprocess
import sys
from dataclasses import dataclass

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



# ---- multi-host bed: hosts as namespaces on one virtual switch -------------------------------

#: Default subnet (first three octets) of the multi-host bed: a /24 of 10.0.0.0/8 that exists
#: only inside the bed's namespaces (no default route anywhere, so nothing leaves them).
MULTIHOST_SUBNET = "10.213.7"
#: Host i (1-based) gets .<i>; extra namespaces (a supervisor, ...) get .101, .102, ...
EXTRA_HOST_BASE = 101
LAN_IFNAME = "lan0"
BRIDGE_IFNAME = "br0"
ECAT_MASTER_IFNAME = "ecm0"
ECAT_SIM_IFNAME = "ecs0"
#: Each bed records its namespaces here at ``up`` so ``down`` finds them all, extras included.
STATE_DIR = "/run/zenoh-drives"
_PREFIX_RE = re.compile(r"^[A-Za-z][A-Za-z0-9]{0,7}$")
_SUBNET_RE = re.compile(r"^10\.(\d{1,3})\.(\d{1,3})$")


@dataclass(frozen=True)
class BedHost:
    """One host of the bed: namespace ``netns`` with ``address`` on ``lan0``; ``port`` is its
    bridge port in the switch namespace. ``ecat_master``/``ecat_sim``: the EtherCAT veth pair
    inside ``netns`` (None for extra namespaces)."""

    name: str
    netns: str
    address: str
    port: str
    ecat_master: str | None
    ecat_sim: str | None

    def exec_argv(self, *argv: str) -> list[str]:
        """``argv`` run inside this host's namespace."""
        return ["ip", "netns", "exec", self.netns, *argv]


@dataclass(frozen=True)
class MultiHostBed:
    prefix: str
    subnet: str
    switch_netns: str
    hosts: tuple[BedHost, ...]

    @property
    def cidr(self) -> str:
        return f"{self.subnet}.0/24"

    def host(self, name: str) -> BedHost:
        for h in self.hosts:
            if h.name == name:
                return h
        raise NetnsError(f"no host {name!r} in bed {self.prefix} ({', '.join(h.name for h in self.hosts)})")

    def namespaces(self) -> list[str]:
        return [self.switch_netns, *(h.netns for h in self.hosts)]


def multihost_plan(prefix: str, hosts: int = 2, *, subnet: str = MULTIHOST_SUBNET,
                   extra: tuple[str, ...] = ()) -> MultiHostBed:
    """Names and addresses of a bed (pure): hosts ``h1..h<hosts>`` with EtherCAT pairs, plus
    ``extra`` namespaces (e.g. ``("sup",)``) on the same switch without one."""
    if not _PREFIX_RE.match(prefix):
        raise NetnsError(f"bed prefix {prefix!r}: a letter then up to 7 of [A-Za-z0-9]")
    m = _SUBNET_RE.match(subnet)
    if not m or not all(0 <= int(o) <= 255 for o in m.groups()):
        raise NetnsError(f"subnet {subnet!r}: the first three octets of a /24 in 10.0.0.0/8, e.g. {MULTIHOST_SUBNET}")
    if not 1 <= hosts <= 99:
        raise NetnsError(f"hosts {hosts}: 1..99")
    names = [f"h{i}" for i in range(1, hosts + 1)]
    for x in extra:
        if not re.match(r"^[a-z][a-z0-9]{0,4}$", x) or x in names or x == "sw":
            raise NetnsError(f"extra namespace {x!r}: 1..5 of [a-z0-9], unique, not 'sw' or h<i>")
        names.append(x)
    bed_hosts = []
    for i, name in enumerate(names):
        is_host = i < hosts
        octet = i + 1 if is_host else EXTRA_HOST_BASE + i - hosts
        bed_hosts.append(BedHost(name=name, netns=_check_name(f"{prefix}{name}"), address=f"{subnet}.{octet}",
                                 port=_check_name(f"p{name}"),
                                 ecat_master=ECAT_MASTER_IFNAME if is_host else None,
                                 ecat_sim=ECAT_SIM_IFNAME if is_host else None))
    return MultiHostBed(prefix=prefix, subnet=subnet, switch_netns=_check_name(f"{prefix}sw"), hosts=tuple(bed_hosts))


def _state_path(prefix: str) -> str:
    return os.path.join(STATE_DIR, f"multihost-{prefix}.json")


def _recorded(prefix: str) -> list[str]:
    try:
        with open(_state_path(prefix)) as f:
            names = json.load(f).get("namespaces", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [n for n in names if isinstance(n, str) and n.startswith(prefix)]


def multihost_up(bed: MultiHostBed) -> None:
    """Create (or complete) the bed: switch namespace with bridge ``br0``, one namespace per
    host with ``lan0`` on the bridge and, for hosts, the EtherCAT pair. Idempotent."""
    sw = bed.switch_netns
    # Recorded before anything exists, so a run that fails halfway can still be removed.
    os.makedirs(STATE_DIR, exist_ok=True)
    with open(_state_path(bed.prefix), "w") as f:
        json.dump({"namespaces": sorted(set(bed.namespaces()) | set(_recorded(bed.prefix)))}, f)
    netns_add(sw)
    if not link_exists(BRIDGE_IFNAME, sw):
        _ip("link", "add", BRIDGE_IFNAME, "type", "bridge", netns=sw)
    _disable_ipv6(BRIDGE_IFNAME, sw)
    _ip("link", "set", BRIDGE_IFNAME, "up", netns=sw)
    for h in bed.hosts:
        netns_add(h.netns)
        if not link_exists(LAN_IFNAME, h.netns):
            veth_down(h.port, sw)  # half-made by an earlier run
            _ip("link", "add", h.port, "type", "veth", "peer", "name", LAN_IFNAME, "netns", h.netns, netns=sw)
        _disable_ipv6(h.port, sw)
        _ip("link", "set", h.port, "master", BRIDGE_IFNAME, "up", netns=sw)
        _disable_ipv6(LAN_IFNAME, h.netns)
        _ip("addr", "replace", f"{h.address}/24", "dev", LAN_IFNAME, netns=h.netns)
        _ip("link", "set", LAN_IFNAME, "up", netns=h.netns)
        if h.ecat_master and h.ecat_sim:
            if not link_exists(h.ecat_master, h.netns):
                veth_down(h.ecat_sim, h.netns)
                _ip("link", "add", h.ecat_master, "type", "veth", "peer", "name", h.ecat_sim, netns=h.netns)
            for end in (h.ecat_master, h.ecat_sim):
                _disable_ipv6(end, h.netns)
                _ip("link", "set", end, "up", netns=h.netns)
    log.info("multi-host bed %s up: %s on %s", bed.prefix, ", ".join(h.name for h in bed.hosts), bed.cidr)


def multihost_link(bed: MultiHostBed, host: str, up: bool) -> None:
    """Plug (``up``) or pull (not ``up``) the cable of ``host`` at the switch."""
    _ip("link", "set", bed.host(host).port, "up" if up else "down", netns=bed.switch_netns)


def netns_pids(name: str) -> list[int]:
    """Processes still running inside namespace ``name``."""
    if not netns_exists(name):
        return []
    proc = _ip("netns", "pids", name, check=False)
    return [int(p) for p in proc.stdout.split() if p.isdigit()]


def multihost_down(prefix: str, hosts: int = 0, *, extra: tuple[str, ...] = ()) -> list[int]:
    """Delete every namespace of the bed ``prefix`` (their interfaces go with them): those
    recorded at ``up``, the switch, ``<prefix>h<i>`` for any i found, and ``extra``. Safe after a failed or partial run and when
    nothing exists. Returns the pids still inside (their namespace lives on until they exit)."""
    if not _PREFIX_RE.match(prefix):
        raise NetnsError(f"bed prefix {prefix!r}: a letter then up to 7 of [A-Za-z0-9]")
    names = {f"{prefix}sw", *(f"{prefix}h{i}" for i in range(1, hosts + 1)), *(f"{prefix}{x}" for x in extra),
             *_recorded(prefix)}
    host_re = re.compile(rf"^{re.escape(prefix)}h\d{{1,2}}$")
    try:
        names.update(n for n in os.listdir("/run/netns") if host_re.match(n))
    except FileNotFoundError:
        pass
    left: list[int] = []
    for name in sorted(names):
        left += netns_pids(name)
        netns_del(name)
    try:
        os.unlink(_state_path(prefix))
    except FileNotFoundError:
        pass
    return left


def multihost_main(argv: list[str]) -> int:
    """``python -m bus_agent.sim.netns multihost up|down ...`` (deploy/multihost.sh)."""
    p = argparse.ArgumentParser(prog="python -m bus_agent.sim.netns multihost",
                                description="hosts as network namespaces on one virtual switch")
    p.add_argument("command", choices=("up", "down", "cut", "plug"))
    p.add_argument("--prefix", default="mh", help="namespace name prefix (a letter, then up to 7 alphanumerics)")
    p.add_argument("--hosts", type=int, default=2, help="host namespaces h1..hN, each with an EtherCAT pair")
    p.add_argument("--extra", action="append", default=[], metavar="NAME",
                   help="extra namespace on the switch without EtherCAT (e.g. sup); repeatable")
    p.add_argument("--subnet", default=MULTIHOST_SUBNET, help="first three octets of the bed's /24 (10.x.y)")
    p.add_argument("--host", help="cut|plug: the host whose cable to pull or plug")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        bed = multihost_plan(args.prefix, args.hosts, subnet=args.subnet, extra=tuple(args.extra))
        if args.command == "up":
            multihost_up(bed)
            for h in bed.hosts:
                ecat = f" ecat_master={h.ecat_master} ecat_sim={h.ecat_sim}" if h.ecat_master else ""
                print(f"{h.name} netns={h.netns} address={h.address}{ecat}")
        elif args.command == "down":
            left = multihost_down(bed.prefix, args.hosts, extra=tuple(args.extra))
            if left:
                print(f"netns: processes still inside the removed namespaces: {' '.join(map(str, left))}",
                      file=sys.stderr)
        else:
            if not args.host:
                raise NetnsError(f"{args.command} needs --host NAME")
            multihost_link(bed, args.host, args.command == "plug")
    except NetnsError as exc:
        print(f"netns: {exc}", file=sys.stderr)
        return 1
    return 0

def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["multihost"]:
        return multihost_main(argv[1:])
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
